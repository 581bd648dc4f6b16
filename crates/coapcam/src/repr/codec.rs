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
pub type DecodeDepth = fn(&[u8]) -> Result<DepthImage, DecodeError>;
/// A decoder of point clouds.
pub type DecodeCloud = fn(&[u8]) -> Result<Cloud, DecodeError>;

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
    Image(fn(&[u8]) -> Result<RgbImage, DecodeError>),
    /// From the body and the camera's pixel format (`rgb8`, ...), which it does not carry:
    /// the reader asks the camera's `color-settings` for it.
    WithPixelFormat(fn(&[u8], &str) -> Result<RgbImage, DecodeError>),
}

/// A body could not be read back as the frame or cloud it was asked for.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum DecodeError {
    /// The body's content format is none of the representations.
    #[error("an unknown content format ({0})")]
    UnknownFormat(String),
    /// The format does not carry the stream asked for, or coapcam does not read it back.
    #[error("coapcam does not read {stream} from {format}")]
    NotRead {
        /// `color`, `depth` or `a point cloud`.
        stream: &'static str,
        /// The format's label.
        format: &'static str,
    },
    /// A thesis packet does not hold what its header says.
    #[error("reading the {what} packet")]
    Packet {
        /// `color`, `depth` or `point-cloud`.
        what: &'static str,
        /// What does not fit.
        source: PacketError,
    },
    /// A PNG or JPEG body is not an image.
    #[error("decoding the {what}")]
    Image {
        /// `depth PNG` or `color image`.
        what: &'static str,
        /// The image decoder's error.
        source: image::ImageError,
    },
    /// A depth PNG that is not 16-bit grayscale (raw depth units).
    #[error("the depth PNG is not 16-bit grayscale")]
    DepthNotGray16,
    /// A CBOR map.
    #[error(transparent)]
    Cbor(#[from] CborError),
    /// A compact cloud.
    #[error(transparent)]
    DepthCloud(#[from] DepthCloudError),
    /// A millimetre cloud.
    #[error(transparent)]
    Mm(#[from] compact::WireError),
    /// RVL depth, plain or in zstd.
    #[error(transparent)]
    Rvl(#[from] compact::rvl::RvlError),
    /// A PLY cloud.
    #[error(transparent)]
    Ply(#[from] geometry::PlyError),
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

/// A packet that does not hold what its header says.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{what} packet: {problem}")]
pub struct PacketError {
    pub(super) what: &'static str,
    pub(super) problem: String,
}

/// Why a CBOR map could not be read.
#[derive(Debug, thiserror::Error)]
pub enum CborError {
    /// Not CBOR, or not a map of this kind (a key missing, a value of the wrong type).
    #[error("decoding the CBOR {what}: {source}")]
    Decode {
        /// `color frame`, `depth frame` or `point cloud`.
        what: &'static str,
        /// ciborium's description.
        source: ciborium::de::Error<std::io::Error>,
    },
    /// A map of another kind (its `type`).
    #[error("the CBOR map is of type {found}, not a {what} ({expected})")]
    Type {
        /// What was expected.
        what: &'static str,
        /// Its `type`.
        expected: u8,
        /// The map's `type`.
        found: u8,
    },
    /// The data does not hold what the header announces.
    #[error("the CBOR {what}: {why}")]
    Data {
        /// What was read.
        what: &'static str,
        /// What does not fit.
        why: String,
    },
    /// A point-cloud map that names no camera.
    #[error("the CBOR point cloud has neither serial nor serials")]
    NoCamera,
    /// An intrinsics map with an unknown distortion model.
    #[error("unknown distortion model {0:?}")]
    Model(String),
}

/// Why a compact cloud gave no points.
#[derive(Debug, thiserror::Error)]
pub enum DepthCloudError {
    /// The payload.
    #[error(transparent)]
    Payload(#[from] compact::cloud::CloudError),
    /// A part's region (the payload's decoder checks the same rules first).
    #[error("compact cloud: {0}")]
    Region(#[from] geometry::RoiError),
    /// A part's depth does not fit its intrinsics (the payload's decoder checks this
    /// first).
    #[error("compact cloud: {0}")]
    Deproject(#[from] rgbd::FilterError),
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
