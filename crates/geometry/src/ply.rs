//! Point clouds as binary little-endian PLY (the Stanford polygon format), the file format
//! Open3D, CloudCompare and MeshLab read.
//!
//! The writer emits exactly this header, then `12 × N` bytes of little-endian `f32`
//! triples:
//!
//! ```text
//! ply
//! format binary_little_endian 1.0
//! comment <optional, one line>
//! element vertex N
//! property float x
//! property float y
//! property float z
//! end_header
//! ```
//!
//! The reader accepts binary little-endian files with a single `vertex` element of scalar
//! properties (any of the PLY scalar types, in any order) among which `x`, `y` and `z` are
//! `float` or `double`; other scalar properties (normals, colours) are skipped. List
//! properties, other elements, ASCII and big-endian files are refused. The vertex count
//! must match the data that follows exactly.

use std::io::Write;

use crate::{Point3, PointCloud};

/// Longest header the reader scans for `end_header`, in bytes.
pub const MAX_HEADER_BYTES: usize = 4096;

/// Longest comment the writer accepts, in bytes.
pub const MAX_COMMENT_BYTES: usize = 256;

/// Why a PLY file could not be written or read.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum PlyError {
    /// The writer failed.
    #[error("cannot write PLY: {0}")]
    Io(#[from] std::io::Error),
    /// The comment holds a line break or a non-printable character, or is too long.
    #[error(
        "a PLY comment must be printable ASCII without line breaks, at most {MAX_COMMENT_BYTES} bytes"
    )]
    InvalidComment,
    /// The data does not start with the `ply` magic line.
    #[error("not a PLY file: the first line is not \"ply\"")]
    NotPly,
    /// No `end_header` line within [`MAX_HEADER_BYTES`].
    #[error("PLY header has no end_header line within {MAX_HEADER_BYTES} bytes")]
    HeaderTooLong,
    /// The header is not ASCII text.
    #[error("PLY header is not ASCII text")]
    HeaderNotAscii,
    /// The format line names something other than `binary_little_endian 1.0`.
    #[error("PLY format {found:?} is not supported (only binary_little_endian 1.0)")]
    UnsupportedFormat {
        /// The format line's arguments.
        found: String,
    },
    /// A header line could not be understood.
    #[error("PLY header line {line} is not understood: {reason}")]
    BadHeader {
        /// One-based line number in the header.
        line: usize,
        /// What was wrong.
        reason: &'static str,
    },
    /// A property is a list or has an unknown type.
    #[error("PLY property {name:?} has type {ty:?}; only scalar types are supported")]
    UnsupportedProperty {
        /// The property's name.
        name: String,
        /// The declared type.
        ty: String,
    },
    /// The vertex element lacks `x`, `y` or `z` as `float` or `double`.
    #[error("PLY vertex element lacks property {axis} as float or double")]
    MissingCoordinate {
        /// The missing axis.
        axis: char,
    },
    /// The vertex count does not match the length of the data after the header.
    #[error(
        "PLY declares {declared} vertices of {stride} bytes but {data_bytes} data bytes follow"
    )]
    LengthMismatch {
        /// Vertex count in the header.
        declared: u64,
        /// Bytes per vertex.
        stride: usize,
        /// Bytes after `end_header`.
        data_bytes: usize,
    },
}

/// Writes the points (e.g. a [`PointCloud`]'s `points`) as binary little-endian PLY with
/// an optional one-line `comment`.
///
/// The writer is not buffered here: pass a `BufWriter` for files.
pub fn write_ply<W: Write>(
    points: &[Point3],
    comment: Option<&str>,
    mut out: W,
) -> Result<(), PlyError> {
    if let Some(text) = comment
        && (text.len() > MAX_COMMENT_BYTES || !text.bytes().all(|b| (b' '..=b'~').contains(&b)))
    {
        return Err(PlyError::InvalidComment);
    }
    let mut header = String::from("ply\nformat binary_little_endian 1.0\n");
    if let Some(text) = comment {
        header.push_str("comment ");
        header.push_str(text);
        header.push('\n');
    }
    header.push_str(&format!(
        "element vertex {}\nproperty float x\nproperty float y\nproperty float z\nend_header\n",
        points.len()
    ));
    out.write_all(header.as_bytes())?;
    const CHUNK_POINTS: usize = 4096;
    let mut buf = Vec::with_capacity(CHUNK_POINTS.min(points.len()) * 12);
    for chunk in points.chunks(CHUNK_POINTS) {
        buf.clear();
        for p in chunk {
            buf.extend_from_slice(&p.x.to_le_bytes());
            buf.extend_from_slice(&p.y.to_le_bytes());
            buf.extend_from_slice(&p.z.to_le_bytes());
        }
        out.write_all(&buf)?;
    }
    out.flush()?;
    Ok(())
}

/// The points as a binary little-endian PLY file in memory (see [`write_ply`]).
pub fn encode_ply(points: &[Point3], comment: Option<&str>) -> Result<Vec<u8>, PlyError> {
    let mut out = Vec::with_capacity(160 + comment.map_or(0, str::len) + points.len() * 12);
    write_ply(points, comment, &mut out)?;
    Ok(out)
}

/// A scalar PLY type: its size and whether it can hold a coordinate.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Scalar {
    Float,
    Double,
    Other(usize),
}

impl Scalar {
    fn parse(ty: &str) -> Option<Self> {
        Some(match ty {
            "float" | "float32" => Self::Float,
            "double" | "float64" => Self::Double,
            "char" | "uchar" | "int8" | "uint8" => Self::Other(1),
            "short" | "ushort" | "int16" | "uint16" => Self::Other(2),
            "int" | "uint" | "int32" | "uint32" => Self::Other(4),
            _ => return None,
        })
    }

    fn size(self) -> usize {
        match self {
            Self::Float => 4,
            Self::Double => 8,
            Self::Other(n) => n,
        }
    }
}

/// Reads a binary little-endian PLY point cloud (see the module documentation for what is
/// accepted). Only the `x`, `y` and `z` properties are kept.
pub fn decode_ply(data: &[u8]) -> Result<PointCloud, PlyError> {
    let scan = &data[..data.len().min(MAX_HEADER_BYTES)];
    let end = find_end_header(scan).ok_or_else(|| {
        if scan.starts_with(b"ply") {
            PlyError::HeaderTooLong
        } else {
            PlyError::NotPly
        }
    })?;
    let header = std::str::from_utf8(&data[..end]).map_err(|_| PlyError::HeaderNotAscii)?;
    if !header.is_ascii() {
        return Err(PlyError::HeaderNotAscii);
    }
    let body = &data[end..];

    let mut lines = header.lines().map(|l| l.trim_end_matches('\r'));
    if lines.next() != Some("ply") {
        return Err(PlyError::NotPly);
    }
    let mut vertices: Option<u64> = None;
    let mut format_seen = false;
    // (name, type, offset in the vertex record)
    let mut props: Vec<(String, Scalar, usize)> = Vec::new();
    let mut stride = 0usize;
    for (i, line) in lines.enumerate() {
        let number = i + 2;
        let bad = |reason| PlyError::BadHeader {
            line: number,
            reason,
        };
        let mut words = line.split_ascii_whitespace();
        match words.next() {
            Some("format") => {
                let rest: Vec<&str> = words.collect();
                if rest != ["binary_little_endian", "1.0"] {
                    return Err(PlyError::UnsupportedFormat {
                        found: rest.join(" ").chars().take(64).collect(),
                    });
                }
                format_seen = true;
            }
            Some("comment" | "obj_info") => {}
            Some("element") => {
                if vertices.is_some() {
                    return Err(bad("only one element (vertex) is supported"));
                }
                if words.next() != Some("vertex") {
                    return Err(bad("only the vertex element is supported"));
                }
                let count = words
                    .next()
                    .and_then(|n| n.parse::<u64>().ok())
                    .ok_or_else(|| bad("the vertex count is not a non-negative integer"))?;
                if words.next().is_some() {
                    return Err(bad("unexpected words after the vertex count"));
                }
                vertices = Some(count);
            }
            Some("property") => {
                if vertices.is_none() {
                    return Err(bad("property before element"));
                }
                let ty = words.next().ok_or_else(|| bad("property without a type"))?;
                let name = words.next().ok_or_else(|| bad("property without a name"))?;
                let scalar = Scalar::parse(ty)
                    .filter(|_| words.next().is_none())
                    .ok_or_else(|| PlyError::UnsupportedProperty {
                        name: name.chars().take(64).collect(),
                        ty: ty.chars().take(64).collect(),
                    })?;
                if props.iter().any(|(n, _, _)| n == name) {
                    return Err(bad("duplicate property name"));
                }
                props.push((name.to_owned(), scalar, stride));
                stride += scalar.size();
            }
            Some("end_header") => break,
            Some(_) => return Err(bad("unknown keyword")),
            None => return Err(bad("empty line")),
        }
    }
    if !format_seen {
        return Err(PlyError::UnsupportedFormat {
            found: String::new(),
        });
    }
    let declared = vertices.ok_or(PlyError::BadHeader {
        line: 0,
        reason: "no vertex element",
    })?;
    let coordinate = |axis: char| {
        props
            .iter()
            .find(|(n, _, _)| n.len() == 1 && n.starts_with(axis))
            .and_then(|(_, s, off)| match s {
                Scalar::Float | Scalar::Double => Some((*s, *off)),
                Scalar::Other(_) => None,
            })
            .ok_or(PlyError::MissingCoordinate { axis })
    };
    let axes = [coordinate('x')?, coordinate('y')?, coordinate('z')?];
    let mismatch = PlyError::LengthMismatch {
        declared,
        stride,
        data_bytes: body.len(),
    };
    let matches = usize::try_from(declared)
        .ok()
        .and_then(|count| count.checked_mul(stride))
        == Some(body.len());
    if !matches {
        return Err(mismatch);
    }
    let read = |record: &[u8], (scalar, off): (Scalar, usize)| -> f32 {
        let mut b8 = [0u8; 8];
        let size = scalar.size();
        b8[..size].copy_from_slice(&record[off..off + size]);
        match scalar {
            Scalar::Double => f64::from_le_bytes(b8) as f32,
            _ => f32::from_le_bytes([b8[0], b8[1], b8[2], b8[3]]),
        }
    };
    let points = body
        .chunks_exact(stride)
        .map(|r| Point3::new(read(r, axes[0]), read(r, axes[1]), read(r, axes[2])))
        .collect();
    Ok(PointCloud { points })
}

/// Offset just past the `end_header` line, if the header ends within `scan`.
fn find_end_header(scan: &[u8]) -> Option<usize> {
    const MARK: &[u8] = b"\nend_header";
    let at = scan.windows(MARK.len()).position(|w| w == MARK)? + MARK.len();
    match scan.get(at..)? {
        [b'\n', ..] => Some(at + 1),
        [b'\r', b'\n', ..] => Some(at + 2),
        _ => None,
    }
}
