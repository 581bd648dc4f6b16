//! What the representations share: what the server encodes from ([`Subject`]), how an
//! encoding fails, and what the client reads back ([`Decoders`]). Each format's module
//! implements them; the table in [`super`] names which module serves which format.

use geometry::{Point3, PointCloud, Roi3, Transform};
use image::RgbImage;
use rgbd::{ColorFrame, DepthFrame, Extrinsics, Intrinsics, Serial};

/// An encoder of a [`Format`](super::Format) row.
pub type Encode = fn(&Subject<'_>) -> Result<Vec<u8>, EncodeError>;

/// What a representation is encoded from: a frame of one stream and what the formats
/// carry beside its pixels or points.
#[derive(Debug, Clone, Copy)]
pub enum Subject<'a> {
    /// A color frame.
    Color {
        /// The frame.
        frame: &'a ColorFrame,
        /// Its camera's color intrinsics (CBOR).
        intrinsics: &'a Intrinsics,
        /// Its camera's depth->color extrinsics (CBOR).
        depth_to_color: &'a Extrinsics,
        /// Its camera (CBOR).
        serial: &'a Serial,
        /// The JPEG quality, 1-100.
        quality: u8,
    },
    /// A depth frame.
    Depth {
        /// The frame.
        frame: &'a DepthFrame,
        /// Its camera's depth intrinsics (CBOR).
        intrinsics: &'a Intrinsics,
        /// Its camera (CBOR).
        serial: &'a Serial,
    },
    /// A point cloud.
    Cloud {
        /// The points.
        points: &'a [Point3],
        /// When the depth they were computed from was grabbed.
        timestamp_us: u64,
        /// Where they came from.
        source: CloudSource<'a>,
        /// The cameras' depth they were computed from (the compact cloud sends that).
        parts: &'a [DepthPart],
    },
}

impl Subject<'_> {
    /// The resource name of the stream it is a frame of.
    pub fn stream_name(&self) -> &'static str {
        match self {
            Self::Color { .. } => "color",
            Self::Depth { .. } => "depth",
            Self::Cloud { .. } => "pointcloud",
        }
    }

    /// The error of an encoder given a stream its format does not serve.
    pub(crate) fn not_served(&self, format: &'static str) -> EncodeError {
        EncodeError::NotServed {
            stream: self.stream_name(),
            format,
        }
    }
}

/// The client's decoders of one [`Format`](super::Format), per stream (`None`: not read back).
#[derive(Debug, Clone, Copy)]
pub struct Decoders {
    /// A color image.
    pub color: Option<ColorDecoder>,
    /// A depth image.
    pub depth: Option<DecodeDepth>,
    /// A point cloud, with its cameras and time where the format carries them.
    pub cloud: Option<DecodeCloud>,
}

/// A decoder of depth images.
pub type DecodeDepth = fn(&[u8]) -> anyhow::Result<DepthImage>;
/// A decoder of point clouds.
pub type DecodeCloud = fn(&[u8]) -> anyhow::Result<Cloud>;

impl Decoders {
    /// Decodes nothing.
    pub const NONE: Self = Self {
        color: None,
        depth: None,
        cloud: None,
    };
}

/// How a format's color is read back.
#[derive(Debug, Clone, Copy)]
pub enum ColorDecoder {
    /// From the body alone.
    Image(fn(&[u8]) -> anyhow::Result<RgbImage>),
    /// From the body and the camera's pixel format (`rgb8`, ...), which it does not carry:
    /// the reader asks the camera's `color-settings` for it.
    WithPixelFormat(fn(&[u8], &str) -> anyhow::Result<RgbImage>),
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
    #[error("{stream} is not served as {format}")]
    /// A format's encoder was given a stream the format does not serve.
    NotServed {
        /// The stream's name.
        stream: &'static str,
        /// The format's label.
        format: &'static str,
    },
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

/// A point cloud read back, with the cameras that made it (CBOR's `serial`, or `serials`
/// of a merged cloud) and its timestamp, where its representation carries them.
pub struct Cloud {
    /// The points, metres.
    pub cloud: PointCloud,
    /// Serials of the cameras that made it.
    pub serials: Vec<String>,
    /// When it was grabbed, microseconds since the UNIX epoch.
    pub timestamp_us: u64,
    /// What each camera saw (pose and intrinsics), where the representation carries it
    /// (the compact cloud); empty otherwise.
    pub views: Vec<geometry::View>,
    /// Each camera's frame, where the representation tells them apart (the compact
    /// cloud); empty otherwise.
    pub frames: Vec<CameraFrame>,
}

/// One camera's frame in a cloud: which, and when it was captured.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CameraFrame {
    /// The camera's serial.
    pub serial: String,
    /// The depth frame's number.
    pub frame_number: u64,
    /// Its capture time, µs since the UNIX epoch on the server's clock.
    pub timestamp_us: u64,
}

/// A depth image: Z16 values in raw units and the metres per unit.
#[derive(Debug, Clone, PartialEq)]
pub struct DepthImage {
    /// Pixels per row.
    pub width: u32,
    /// Rows.
    pub height: u32,
    /// Seconds since the UNIX epoch.
    pub timestamp_s: u32,
    /// Metres per depth unit.
    pub depth_scale: f32,
    /// Row-major, `width * height` values; 0 = no depth.
    pub values: Vec<u16>,
}

/// One camera's cloud as what it is computed from.
#[derive(Debug, Clone, PartialEq)]
pub struct DepthPart {
    /// The camera's serial number.
    pub serial: String,
    /// The depth image after `roi2d` and post-processing (its frame number and timestamp
    /// those of the grab).
    pub depth: DepthFrame,
    /// The intrinsics of `depth`.
    pub intrinsics: Intrinsics,
    /// Camera frame to the common frame (the 3d-transformation).
    pub transform: Transform,
    /// The box kept (`roi3d`), in the common frame.
    pub roi: Roi3,
    /// Applied after the crop: the server's ICP registration of this camera, if any.
    pub correction: Option<Transform>,
}

/// The length a body must have: the product of `factors` (points x bytes a point, or
/// width x height x bytes a pixel), `None` when it overflows. Decoders compare it with
/// the bytes that arrived, so an announced size never wraps into a match.
pub(crate) fn checked_len(factors: &[u64]) -> Option<u64> {
    factors
        .iter()
        .try_fold(1u64, |len, &factor| len.checked_mul(factor))
}
