//! Representations: each wire format's encoder (the server's) and decoder (the client's)
//! together, and the one table of which stream is offered in which content format.
//!
//! | content format | color | depth | point cloud | module |
//! |---|---|---|---|---|
//! | 42 `application/octet-stream`: the thesis packet (the default) | yes | yes | yes | [`packet`] |
//! | 23 `image/png` | 8-bit RGB(A) | 16-bit raw units | | [`raster`] |
//! | 22 `image/jpeg` | yes | | | [`raster`] |
//! | 60 `application/cbor`: a map with intrinsics and provenance | yes | yes | yes | [`cbor`] |
//! | 65100 PLY, binary little-endian | | | yes | [`ply`] |
//! | 65101 RVL: run lengths and nibble-coded differences, lossless | | yes | | [`rvl`] |
//! | 65102 RVL in a zstd frame | | yes | | [`rvl`] |
//! | 65103 compact cloud: filtered depth (RVL) and its geometry, in zstd | | | yes | [`clouds`] |
//! | 65104 millimetre cloud: quantized, delta coded, in zstd | | | yes | [`clouds`] |

pub mod cbor;
pub mod clouds;
pub mod packet;
pub mod ply;
pub mod raster;
pub mod rvl;

use coap::ContentFormat;
use rgbd::Serial;

/// What a grab resource produces.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Stream {
    /// The color image.
    Color,
    /// The depth image.
    Depth,
    /// The point cloud.
    Pointcloud,
}

impl Stream {
    /// Every stream, in the order of [`Stream::index`].
    pub const ALL: [Self; 3] = [Self::Color, Self::Depth, Self::Pointcloud];

    /// The resource name under `/cams/<sn>/`.
    pub fn name(self) -> &'static str {
        match self {
            Self::Color => "color",
            Self::Depth => "depth",
            Self::Pointcloud => "pointcloud",
        }
    }

    /// The stream whose resource is called `name`.
    pub fn of(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|s| s.name() == name)
    }

    /// The resource type (`rt`) of its resources in `/.well-known/core`.
    pub fn resource_type(self) -> &'static str {
        match self {
            Self::Color => "rgbd.color",
            Self::Depth => "rgbd.depth",
            Self::Pointcloud => "rgbd.pointcloud",
        }
    }

    /// Its position in [`Stream::ALL`].
    pub fn index(self) -> usize {
        self as usize
    }

    /// The content formats its resources offer, the first being the default: the rows of
    /// [`FORMATS`] that serve it, in the table's order.
    pub fn formats(self) -> impl Iterator<Item = ContentFormat> {
        FORMATS
            .iter()
            .filter(move |f| f.streams.contains(&self))
            .map(|f| f.format)
    }

    /// Whether its resources offer `cf`.
    pub fn offers(self, cf: ContentFormat) -> bool {
        self.formats().any(|f| f == cf)
    }

    /// Its compact form, which the typed client asks for first: JPEG (lossy, for
    /// pictures), RVL+zstd (lossless), the compact cloud (the same points).
    pub fn compact(self) -> ContentFormat {
        match self {
            Self::Color => ContentFormat::IMAGE_JPEG,
            Self::Depth => RVL_ZSTD,
            Self::Pointcloud => DEPTH_CLOUD,
        }
    }

    /// Its resources' `ct` in discovery: every format it offers, the default first.
    pub fn ct(self) -> String {
        let numbers: Vec<String> = self.formats().map(|cf| cf.0.to_string()).collect();
        numbers.join(" ")
    }

    /// The diagnostic of a 4.06 Not Acceptable: the formats it is served in.
    pub fn not_acceptable(self) -> String {
        let names: Vec<String> = self
            .formats()
            .filter_map(Format::of)
            .map(|f| format!("{} ({})", f.format.0, f.label))
            .collect();
        format!("{} is served as {}", self.name(), or_list(&names))
    }

    /// The content format a file named `*.ext` holds (`png`, `jpg`, `ply`, `rvl`,
    /// `rvl.zst`, `bin` for the thesis packet), if the stream is offered in it.
    pub fn format_of_extension(self, ext: &str) -> Option<ContentFormat> {
        let ext = ext.to_ascii_lowercase();
        self.formats()
            .filter_map(Format::of)
            .find(|f| f.extensions.contains(&ext.as_str()))
            .map(|f| f.format)
    }

    /// The file extensions it can be written to, e.g. `.png, .jpg or .bin`.
    pub fn extensions(self) -> String {
        let exts: Vec<String> = self
            .formats()
            .filter_map(Format::of)
            .filter_map(|f| f.extensions.first())
            .map(|e| format!(".{e}"))
            .collect();
        or_list(&exts)
    }
}

/// 65100: `application/x-ply`, binary little-endian PLY. coapcam's own numbers are from
/// the experimental range 65000-65535 (RFC 7252 §12.3), which IANA never assigns: they
/// mean these formats only between coapcam peers.
pub const PLY: ContentFormat = ContentFormat(65100);
/// 65101: `application/x-rvl`, a 16-bit depth image RVL-compressed.
pub const RVL: ContentFormat = ContentFormat(65101);
/// 65102: `application/x-rvl+zstd`, that RVL image in a zstd frame.
pub const RVL_ZSTD: ContentFormat = ContentFormat(65102);
/// 65103: `application/x-depth-cloud+zstd`, the compact cloud: each camera's filtered
/// depth (RVL) with the intrinsics, transform and region that make it the points, in a
/// zstd frame.
pub const DEPTH_CLOUD: ContentFormat = ContentFormat(65103);
/// 65104: `application/x-cloud-mm+zstd`, the millimetre cloud: integer millimetres, delta
/// coded, in a zstd frame.
pub const CLOUD_MM: ContentFormat = ContentFormat(65104);

/// One representation: a row of [`FORMATS`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Format {
    /// Its content format number.
    pub format: ContentFormat,
    /// Its media type.
    pub media_type: &'static str,
    /// Its short name on the command line (`--accept ply`).
    pub name: &'static str,
    /// How people call it (the 4.06 diagnostic, tables).
    pub label: &'static str,
    /// File extensions that hold it, the usual one first (none: not written to files).
    pub extensions: &'static [&'static str],
    /// The streams served in it.
    pub streams: &'static [Stream],
}

/// Every representation a camera's resources serve, the default (the thesis packet)
/// first; a stream's formats are its rows in this order. Adding a representation is a
/// module here and a row.
pub const FORMATS: [Format; 9] = {
    use Stream::{Color, Depth, Pointcloud};
    const ALL: &[Stream] = &Stream::ALL;
    [
        row(
            ContentFormat::OCTET_STREAM,
            "application/octet-stream",
            "octet-stream",
            "thesis packet",
            &["bin"],
            ALL,
        ),
        row(
            ContentFormat::IMAGE_PNG,
            "image/png",
            "png",
            "PNG",
            &["png"],
            &[Color, Depth],
        ),
        row(
            ContentFormat::IMAGE_JPEG,
            "image/jpeg",
            "jpeg",
            "JPEG",
            &["jpg", "jpeg"],
            &[Color],
        ),
        row(
            ContentFormat::CBOR,
            "application/cbor",
            "cbor",
            "CBOR",
            &[],
            ALL,
        ),
        row(
            PLY,
            "application/x-ply",
            "ply",
            "PLY",
            &["ply"],
            &[Pointcloud],
        ),
        row(RVL, "application/x-rvl", "rvl", "RVL", &["rvl"], &[Depth]),
        row(
            RVL_ZSTD,
            "application/x-rvl+zstd",
            "rvl-zstd",
            "RVL+zstd",
            &["rvl.zst"],
            &[Depth],
        ),
        row(
            DEPTH_CLOUD,
            "application/x-depth-cloud+zstd",
            "depth-cloud",
            "compact cloud",
            &["dcl"],
            &[Pointcloud],
        ),
        row(
            CLOUD_MM,
            "application/x-cloud-mm+zstd",
            "cloud-mm",
            "millimetre cloud",
            &["qmm"],
            &[Pointcloud],
        ),
    ]
};

const fn row(
    format: ContentFormat,
    media_type: &'static str,
    name: &'static str,
    label: &'static str,
    extensions: &'static [&'static str],
    streams: &'static [Stream],
) -> Format {
    Format {
        format,
        media_type,
        name,
        label,
        extensions,
        streams,
    }
}

impl Format {
    /// The row of `cf`, if it is one of the representations.
    pub fn of(cf: ContentFormat) -> Option<&'static Self> {
        FORMATS.iter().find(|f| f.format == cf)
    }

    /// The media type of `cf`: coapcam's own from the table, else the CoAP registry's; the
    /// number when neither knows it.
    pub fn describe(cf: ContentFormat) -> String {
        match Self::of(cf) {
            Some(f) => f.media_type.to_owned(),
            None => cf.to_string(),
        }
    }

    /// A content format from the command line: a number, a media type or a short name,
    /// coapcam's own ([`FORMATS`]) or the CoAP registry's.
    pub fn parse(text: &str) -> Result<ContentFormat, String> {
        let t = text.trim();
        if let Some(f) = FORMATS
            .iter()
            .find(|f| f.name.eq_ignore_ascii_case(t) || f.media_type.eq_ignore_ascii_case(t))
        {
            return Ok(f.format);
        }
        t.parse::<ContentFormat>().map_err(|e| match e {
            coap::content_format::ParseError::Unknown(_) => format!(
                "unknown content format {t:?}: use a number (0-65535), a media type such as \
                 application/json, or a short name such as json, cbor, png, jpeg, \
                 octet-stream, link-format, text, ply, rvl, rvl-zstd, depth-cloud or cloud-mm"
            ),
            other => other.to_string(),
        })
    }
}

/// `a, b or c`.
fn or_list(items: &[String]) -> String {
    match items {
        [] => String::new(),
        [one] => one.clone(),
        [first @ .., last] => format!("{} or {last}", first.join(", ")),
    }
}

/// A representation could not be encoded.
#[derive(Debug, thiserror::Error)]
pub enum EncodeError {
    #[error("encoding {format}: {source}")]
    /// A PNG or JPEG encoder failed.
    Image {
        /// `PNG` or `JPEG`.
        format: &'static str,
        /// The encoder's error.
        source: image::ImageError,
    },
    #[error("encoding CBOR: {0}")]
    /// The CBOR writer failed.
    Cbor(#[from] ciborium::ser::Error<std::io::Error>),
    #[error("encoding PLY: {0}")]
    /// The PLY writer failed.
    Ply(#[from] geometry::PlyError),
    #[error("compressing with zstd: {0}")]
    /// zstd failed.
    Zstd(#[from] std::io::Error),
}

/// Where a point cloud came from, for its CBOR map and PLY comment.
#[derive(Debug, Clone, Copy)]
pub enum CloudSource<'a> {
    /// One camera's grab.
    Camera {
        /// The camera.
        serial: &'a Serial,
        /// The frame number of the depth frame.
        frame: u64,
    },
    /// `/cams/pointclouds`: the cameras whose clouds were merged.
    Merged {
        /// The cameras, in the order they were merged.
        serials: &'a [Serial],
    },
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use rgbd::{ColorFormat, ColorFrame};

    /// A color frame of `width` x `height` pixels in `format`, rows `stride` bytes apart.
    pub(crate) fn color(format: ColorFormat, width: u32, height: u32, stride: usize) -> ColorFrame {
        ColorFrame {
            format,
            width,
            height,
            stride,
            timestamp_us: 1_700_000_000_500_000,
            frame_number: 1,
            data: vec![7; stride * height as usize],
        }
    }

    #[test]
    fn the_table_names_formats_and_extensions() {
        assert_eq!(
            Stream::Color.not_acceptable(),
            "color is served as 42 (thesis packet), 23 (PNG), 22 (JPEG) or 60 (CBOR)"
        );
        assert_eq!(Stream::Pointcloud.extensions(), ".bin, .ply, .dcl or .qmm");
        assert_eq!(
            Stream::Color.format_of_extension("JPEG"),
            Some(ContentFormat::IMAGE_JPEG)
        );
        assert_eq!(Stream::Depth.format_of_extension("jpg"), None);
        assert_eq!(Stream::Depth.formats().last(), Some(RVL_ZSTD));
        assert_eq!(Format::parse("ply"), Ok(PLY));
        assert_eq!(Format::parse("application/x-rvl+zstd"), Ok(RVL_ZSTD));
        assert_eq!(Format::parse(" 65104 "), Ok(CLOUD_MM));
        assert_eq!(Format::parse("json"), Ok(ContentFormat::JSON));
        assert!(Format::parse("tiff").is_err_and(|e| e.contains("depth-cloud")));
        assert_eq!(
            Format::describe(DEPTH_CLOUD),
            "application/x-depth-cloud+zstd"
        );
        assert_eq!(Format::describe(ContentFormat::IMAGE_PNG), "image/png");
        for f in &FORMATS {
            assert_eq!(Format::parse(f.name), Ok(f.format));
            assert_eq!(Format::parse(f.media_type), Ok(f.format));
        }
        assert_eq!(Stream::of("pointcloud"), Some(Stream::Pointcloud));
    }
}
