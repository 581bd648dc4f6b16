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

    /// The content formats its resources offer, the first being the default.
    pub fn formats(self) -> &'static [ContentFormat] {
        use ContentFormat as Cf;
        match self {
            Self::Color => &[Cf::OCTET_STREAM, Cf::IMAGE_PNG, Cf::IMAGE_JPEG, Cf::CBOR],
            Self::Depth => &[
                Cf::OCTET_STREAM,
                Cf::IMAGE_PNG,
                Cf::CBOR,
                Cf::RVL,
                Cf::RVL_ZSTD,
            ],
            Self::Pointcloud => &[
                Cf::OCTET_STREAM,
                Cf::CBOR,
                Cf::PLY,
                Cf::DEPTH_CLOUD,
                Cf::CLOUD_MM,
            ],
        }
    }

    /// Its compact form, which the typed client asks for first: JPEG (lossy, for
    /// pictures), RVL+zstd (lossless), the compact cloud (the same points).
    pub fn compact(self) -> ContentFormat {
        match self {
            Self::Color => ContentFormat::IMAGE_JPEG,
            Self::Depth => ContentFormat::RVL_ZSTD,
            Self::Pointcloud => ContentFormat::DEPTH_CLOUD,
        }
    }

    /// Its resources' `ct` in discovery: every format it offers, the default first.
    pub fn ct(self) -> String {
        let numbers: Vec<String> = self.formats().iter().map(|cf| cf.0.to_string()).collect();
        numbers.join(" ")
    }

    /// The diagnostic of a 4.06 Not Acceptable: the formats it is served in.
    pub fn not_acceptable(self) -> String {
        let names: Vec<String> = self
            .formats()
            .iter()
            .map(|cf| format!("{} ({})", cf.0, format_name(*cf)))
            .collect();
        format!("{} is served as {}", self.name(), or_list(&names))
    }

    /// The content format a file named `*.ext` holds (`png`, `jpg`, `ply`, `rvl`,
    /// `rvl.zst`, `bin` for the thesis packet), if the stream is offered in it.
    pub fn format_of_extension(self, ext: &str) -> Option<ContentFormat> {
        self.formats()
            .iter()
            .copied()
            .find(|cf| extensions(*cf).contains(&ext.to_ascii_lowercase().as_str()))
    }

    /// The file extensions it can be written to, e.g. `.png, .jpg or .bin`.
    pub fn extensions(self) -> String {
        let exts: Vec<String> = self
            .formats()
            .iter()
            .filter_map(|cf| extensions(*cf).first())
            .map(|e| format!(".{e}"))
            .collect();
        or_list(&exts)
    }
}

/// How a content format of [`Stream::formats`] is named for people.
fn format_name(cf: ContentFormat) -> &'static str {
    match cf {
        ContentFormat::OCTET_STREAM => "thesis packet",
        ContentFormat::IMAGE_PNG => "PNG",
        ContentFormat::IMAGE_JPEG => "JPEG",
        ContentFormat::CBOR => "CBOR",
        ContentFormat::PLY => "PLY",
        ContentFormat::RVL => "RVL",
        ContentFormat::RVL_ZSTD => "RVL+zstd",
        ContentFormat::DEPTH_CLOUD => "compact cloud",
        ContentFormat::CLOUD_MM => "millimetre cloud",
        _ => "other",
    }
}

/// File extensions of a content format of [`Stream::formats`], the usual one first.
fn extensions(cf: ContentFormat) -> &'static [&'static str] {
    match cf {
        ContentFormat::OCTET_STREAM => &["bin"],
        ContentFormat::IMAGE_PNG => &["png"],
        ContentFormat::IMAGE_JPEG => &["jpg", "jpeg"],
        ContentFormat::PLY => &["ply"],
        ContentFormat::RVL => &["rvl"],
        ContentFormat::RVL_ZSTD => &["rvl.zst"],
        ContentFormat::DEPTH_CLOUD => &["dcl"],
        ContentFormat::CLOUD_MM => &["qmm"],
        _ => &[],
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
        assert_eq!(Stream::of("pointcloud"), Some(Stream::Pointcloud));
    }
}
