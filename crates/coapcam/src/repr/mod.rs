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
pub mod codec;
pub mod no_depth;
pub mod packet;
pub mod ply;
pub mod raster;
pub mod rvl;

use coap::ContentFormat;

pub use self::codec::{
    CameraFrame, Cloud, CloudSource, ColorDecoder, DecodeError, Decoders, DepthImage, DepthPart,
    Encode, EncodeError, Subject,
};

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
#[derive(Debug, Clone, Copy)]
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
    /// The server's encoder: a frame of one of [`Format::streams`] as a body.
    pub encode: Encode,
    /// The client's decoders: which streams it reads back from this format, and how.
    pub decode: Decoders,
}

/// Every representation a camera's resources serve, the default (the thesis packet)
/// first; a stream's formats are its rows in this order. Adding a representation is a
/// module here and a row.
pub const FORMATS: [Format; 9] = {
    use Stream::{Color, Depth, Pointcloud};
    const ALL: &[Stream] = &Stream::ALL;
    [
        Format {
            format: ContentFormat::OCTET_STREAM,
            media_type: "application/octet-stream",
            name: "octet-stream",
            label: "thesis packet",
            extensions: &["bin"],
            streams: ALL,
            encode: packet::encode,
            decode: packet::DECODERS,
        },
        Format {
            format: ContentFormat::IMAGE_PNG,
            media_type: "image/png",
            name: "png",
            label: "PNG",
            extensions: &["png"],
            streams: &[Color, Depth],
            encode: raster::encode_png,
            decode: raster::PNG_DECODERS,
        },
        Format {
            format: ContentFormat::IMAGE_JPEG,
            media_type: "image/jpeg",
            name: "jpeg",
            label: "JPEG",
            extensions: &["jpg", "jpeg"],
            streams: &[Color],
            encode: raster::encode_jpeg,
            decode: raster::JPEG_DECODERS,
        },
        Format {
            format: ContentFormat::CBOR,
            media_type: "application/cbor",
            name: "cbor",
            label: "CBOR",
            extensions: &[],
            streams: ALL,
            encode: cbor::encode,
            decode: cbor::DECODERS,
        },
        Format {
            format: PLY,
            media_type: "application/x-ply",
            name: "ply",
            label: "PLY",
            extensions: &["ply"],
            streams: &[Pointcloud],
            encode: ply::encode,
            decode: ply::DECODERS,
        },
        Format {
            format: RVL,
            media_type: "application/x-rvl",
            name: "rvl",
            label: "RVL",
            extensions: &["rvl"],
            streams: &[Depth],
            encode: rvl::encode_rvl,
            decode: rvl::RVL_DECODERS,
        },
        Format {
            format: RVL_ZSTD,
            media_type: "application/x-rvl+zstd",
            name: "rvl-zstd",
            label: "RVL+zstd",
            extensions: &["rvl.zst"],
            streams: &[Depth],
            encode: rvl::encode_rvl_zstd,
            decode: rvl::RVL_ZSTD_DECODERS,
        },
        Format {
            format: DEPTH_CLOUD,
            media_type: "application/x-depth-cloud+zstd",
            name: "depth-cloud",
            label: "compact cloud",
            extensions: &["dcl"],
            streams: &[Pointcloud],
            encode: clouds::encode_depth_cloud,
            decode: clouds::DEPTH_CLOUD_DECODERS,
        },
        Format {
            format: CLOUD_MM,
            media_type: "application/x-cloud-mm+zstd",
            name: "cloud-mm",
            label: "millimetre cloud",
            extensions: &["qmm"],
            streams: &[Pointcloud],
            encode: clouds::encode_mm,
            decode: clouds::MM_DECODERS,
        },
    ]
};

impl Format {
    /// The row of `cf`, if it is one of the representations.
    pub fn of(cf: ContentFormat) -> Option<&'static Self> {
        FORMATS.iter().find(|f| f.format == cf)
    }

    /// The row of a received body's content format, the thesis packet's when it names
    /// none (coapcam's servers then send the packet).
    pub fn received(cf: Option<ContentFormat>) -> Result<&'static Self, DecodeError> {
        let cf = cf.unwrap_or(ContentFormat::OCTET_STREAM);
        Self::of(cf).ok_or_else(|| DecodeError::UnknownFormat(Self::describe(cf)))
    }

    /// Its body as a frame of `subject`'s stream.
    pub fn encode(&self, subject: &Subject<'_>) -> Result<Vec<u8>, EncodeError> {
        (self.encode)(subject)
    }

    /// Reads a depth image back from a body in this format.
    pub fn decode_depth(&self, body: &[u8]) -> Result<DepthImage, DecodeError> {
        let decode = self.decode.depth.ok_or_else(|| self.not_read("depth"))?;
        decode(body)
    }

    /// Reads a point cloud back from a body in this format.
    pub fn decode_cloud(&self, body: &[u8]) -> Result<Cloud, DecodeError> {
        let decode = self
            .decode
            .cloud
            .ok_or_else(|| self.not_read("a point cloud"))?;
        decode(body)
    }

    /// How color is read back from a body in this format.
    pub fn color_decoder(&self) -> Result<ColorDecoder, DecodeError> {
        self.decode.color.ok_or_else(|| self.not_read("color"))
    }

    fn not_read(&self, stream: &'static str) -> DecodeError {
        DecodeError::NotRead {
            stream,
            format: self.label,
        }
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

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use geometry::{Point3, Roi3, Transform};
    use rgbd::Serial;
    use rgbd::{ColorFormat, ColorFrame, DepthFrame, DistortionModel, Extrinsics, Intrinsics};

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

    /// The words of an error and its causes, as the commands print them.
    fn words(e: DecodeError) -> String {
        crate::error_text(&e)
    }

    #[test]
    fn a_body_that_cannot_be_read_says_which_and_why() {
        let unknown = Format::received(Some(ContentFormat(65_000))).map(|f| f.label);
        assert!(
            matches!(&unknown, Err(DecodeError::UnknownFormat(cf)) if cf == "65000"),
            "{unknown:?}"
        );
        let ply = Format::of(PLY).expect("PLY's row");
        let depth = ply.decode_depth(b"ply");
        assert!(matches!(
            depth,
            Err(DecodeError::NotRead {
                stream: "depth",
                format: "PLY"
            })
        ));
        assert_eq!(
            words(depth.expect_err("PLY carries no depth")),
            "coapcam does not read depth from PLY"
        );
        let packet = Format::of(ContentFormat::OCTET_STREAM).expect("the packet's row");
        assert_eq!(
            words(packet.decode_depth(&[2, 0, 1]).expect_err("3 bytes")),
            "reading the depth packet: depth packet: 3 bytes, the header alone is 14"
        );
        assert_eq!(
            words(
                packet
                    .decode_cloud(&[3, 11, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0])
                    .err()
                    .expect("point size 11")
            ),
            "reading the point-cloud packet: point-cloud packet: point size 11, expected 12"
        );
        let png = Format::of(ContentFormat::IMAGE_PNG).expect("PNG's row");
        let not_png = png.decode_depth(b"not a PNG");
        assert!(
            matches!(
                &not_png,
                Err(DecodeError::Image {
                    what: "depth PNG",
                    ..
                })
            ),
            "{not_png:?}"
        );
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

    #[test]
    fn each_row_encodes_its_streams_and_decodes_them_back() {
        let serial = Serial::parse("840412060746").expect("a serial");
        let k = Intrinsics {
            width: 4,
            height: 2,
            ppx: 2.0,
            ppy: 1.0,
            fx: 3.0,
            fy: 3.0,
            model: DistortionModel::None,
            coeffs: [0.0; 5],
        };
        let rgb = color(ColorFormat::Rgb8, 4, 2, 12);
        let depth = DepthFrame {
            width: 4,
            height: 2,
            stride: 4,
            depth_scale: 0.001,
            timestamp_us: 1_700_000_000_500_000,
            frame_number: 1,
            data: vec![0, 900, 901, 0, 1000, 1001, 1002, 0],
        };
        let mut part = DepthPart {
            serial: serial.as_str().to_owned(),
            depth: depth.clone(),
            intrinsics: k,
            transform: Transform::identity(),
            roi: Roi3::new(Point3::new(-5.0, -5.0, 0.0), Point3::new(5.0, 5.0, 5.0))
                .expect("a box"),
            correction: None,
        };
        let points = part.points().expect("deprojects");
        assert_eq!(points.len(), 5);
        let subjects = [
            Subject::Color {
                frame: &rgb,
                intrinsics: &k,
                depth_to_color: &Extrinsics::IDENTITY,
                serial: &serial,
                quality: 90,
            },
            Subject::Depth {
                frame: &depth,
                intrinsics: &k,
                serial: &serial,
            },
            Subject::Cloud {
                points: &points,
                timestamp_us: 1_700_000_000_500_000,
                source: CloudSource::Camera {
                    serial: &serial,
                    frame: 1,
                },
                parts: std::slice::from_ref(&part),
            },
        ];
        for row in &FORMATS {
            for (subject, stream) in subjects.iter().zip(Stream::ALL) {
                let body = row.encode(subject);
                assert_eq!(
                    body.is_ok(),
                    row.streams.contains(&stream),
                    "{} of {}: {body:?}",
                    row.label,
                    stream.name()
                );
                let Ok(body) = body else { continue };
                match stream {
                    Stream::Color => match row.color_decoder() {
                        Ok(ColorDecoder::Image(decode)) => {
                            assert_eq!(decode(&body).expect("decodes").dimensions(), (4, 2));
                        }
                        Ok(ColorDecoder::WithPixelFormat(decode)) => {
                            let image = decode(&body, ColorFormat::Rgb8.name()).expect("decodes");
                            assert_eq!(image.as_raw(), &rgb.data);
                        }
                        Err(_) => {}
                    },
                    Stream::Depth => {
                        if let Ok(d) = row.decode_depth(&body) {
                            assert_eq!(d.values, depth.data, "{}", row.label);
                        }
                    }
                    Stream::Pointcloud => {
                        if let Ok(c) = row.decode_cloud(&body) {
                            assert_eq!(c.cloud.points.len(), points.len(), "{}", row.label);
                        }
                    }
                }
            }
        }
        assert!(FORMATS[0].decode_cloud(b"short").is_err());
        assert!(Format::received(Some(ContentFormat::JSON)).is_err());
        assert_eq!(
            Format::received(None).map(|f| f.format).ok(),
            Some(ContentFormat::OCTET_STREAM)
        );
    }
}
