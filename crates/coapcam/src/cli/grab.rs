//! `coapcam grab`: one new frame of one camera (or every camera's merged cloud) into a
//! file whose extension chooses the representation, and optionally a picture for people.

use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{Context as _, bail};
use clap::Args;
use coap::{ContentFormat, Response};
use image::{ImageFormat, RgbImage};

use crate::client::{CamClient, Stream};
use crate::packet::{self, DepthImage};
use crate::transmission::TransmissionArgs;
use crate::view;

/// Flags of `grab`.
#[derive(Debug, Args)]
pub(crate) struct GrabArgs {
    /// What to grab.
    stream: Stream,
    /// The server, coap://host[:port].
    #[arg(long, value_name = "URI")]
    server: String,
    /// The camera (12-digit serial); may be left out when the server has one camera.
    #[arg(long, value_name = "SN", conflicts_with = "all")]
    camera: Option<String>,
    /// Point clouds only: every camera of the server, merged (POST /cams/pointclouds).
    #[arg(long)]
    all: bool,
    /// Output file; its extension chooses the format: .png (color; depth as 16-bit PNG of
    /// raw units), .jpg (color), .ply (point cloud, binary PLY), .bin (the thesis packet).
    #[arg(short = 'o', long = "output", value_name = "FILE")]
    output: PathBuf,
    /// Also write what a person looks at, as PNG: the color image; depth in grayscale
    /// (near bright) plus a colour-mapped copy named FILE-color.png; a point cloud seen
    /// from above, coloured by height.
    #[arg(long, value_name = "FILE.png")]
    view: Option<PathBuf>,
    /// Give up after this many seconds.
    #[arg(long, value_name = "SECONDS", default_value_t = 60.0)]
    timeout: f64,
    #[command(flatten)]
    transmission: TransmissionArgs,
}

/// The representations `grab` writes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum FileKind {
    Png,
    Jpeg,
    Ply,
    Packet,
}

impl FileKind {
    fn of(path: &Path, stream: Stream) -> anyhow::Result<Self> {
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase)
            .unwrap_or_default();
        let kind = match ext.as_str() {
            "png" => Self::Png,
            "jpg" | "jpeg" => Self::Jpeg,
            "ply" => Self::Ply,
            "bin" => Self::Packet,
            _ => bail!(
                "{}: the extension must be .png, .jpg, .ply or .bin",
                path.display()
            ),
        };
        let fits = match stream {
            Stream::Color => matches!(kind, Self::Png | Self::Jpeg | Self::Packet),
            Stream::Depth => matches!(kind, Self::Png | Self::Packet),
            Stream::Pointcloud => matches!(kind, Self::Ply | Self::Packet),
        };
        if !fits {
            bail!(
                "{} cannot be written as .{ext}: color as .png, .jpg or .bin; depth as .png or .bin; pointcloud as .ply or .bin",
                stream.name()
            );
        }
        Ok(kind)
    }

    fn accept(self) -> Option<ContentFormat> {
        match self {
            Self::Png => Some(ContentFormat::IMAGE_PNG),
            Self::Jpeg => Some(ContentFormat::IMAGE_JPEG),
            Self::Ply => Some(ContentFormat::PLY),
            Self::Packet => None,
        }
    }
}

/// Runs `grab`.
pub(crate) async fn run(args: GrabArgs) -> anyhow::Result<bool> {
    if args.all && args.stream != Stream::Pointcloud {
        bail!("--all is for point clouds: every camera's cloud merged");
    }
    let kind = FileKind::of(&args.output, args.stream)?;
    if let Some(v) = &args.view
        && FileKind::of(v, Stream::Color).ok() != Some(FileKind::Png)
    {
        bail!("--view writes PNG: give a .png file name");
    }
    let timeout = Duration::try_from_secs_f64(args.timeout).context("--timeout")?;
    let client =
        CamClient::connect(&args.server, args.transmission.endpoint_config(), timeout).await?;
    let (sn, response) = if args.all {
        (None, client.grab_all(kind.accept()).await?)
    } else {
        let sn = client.one_camera(args.camera.as_deref()).await?;
        let response = client.grab(&sn, args.stream, kind.accept()).await?;
        (Some(sn), response)
    };
    std::fs::write(&args.output, &response.payload)
        .with_context(|| format!("writing {}", args.output.display()))?;
    eprintln!(
        "coapcam: wrote {} ({} bytes)",
        args.output.display(),
        response.payload.len()
    );
    if let Some(path) = &args.view {
        for written in write_view(&client, sn.as_deref(), &args, kind, &response, path).await? {
            eprintln!("coapcam: wrote {}", written.display());
        }
    }
    Ok(true)
}

/// Writes the picture(s) of `--view` from the representation that arrived (from camera
/// `sn`, `None` with `--all`); returns the files written.
async fn write_view(
    client: &CamClient,
    sn: Option<&str>,
    args: &GrabArgs,
    kind: FileKind,
    response: &Response,
    path: &Path,
) -> anyhow::Result<Vec<PathBuf>> {
    match args.stream {
        Stream::Color => {
            let image = match kind {
                FileKind::Png | FileKind::Jpeg => image::load_from_memory(&response.payload)
                    .context("decoding the color image")?
                    .to_rgb8(),
                FileKind::Packet | FileKind::Ply => {
                    let sn = sn.context("--all is for point clouds")?;
                    let settings = client.get_json(sn, "color-settings").await?;
                    color_from_packet(&response.payload, &settings)?
                }
            };
            save(&image, path)?;
            Ok(vec![path.to_owned()])
        }
        Stream::Depth => {
            let depth = match kind {
                FileKind::Png => depth_from_png(&response.payload)?,
                _ => packet::depth(&response.payload).context("reading the depth packet")?,
            };
            let colored = sibling(path, "-color");
            let (gray, colored_view) = view::depth_views(&depth);
            save(&gray, path)?;
            save(&colored_view, &colored)?;
            Ok(vec![path.to_owned(), colored])
        }
        Stream::Pointcloud => {
            let cloud = match kind {
                FileKind::Ply => {
                    geometry::decode_ply(&response.payload).context("reading the PLY cloud")?
                }
                _ => {
                    packet::cloud(&response.payload)
                        .context("reading the point-cloud packet")?
                        .cloud
                }
            };
            save(&view::top_view(&cloud), path)?;
            Ok(vec![path.to_owned()])
        }
    }
}

/// `dir/name-suffix.png` for `dir/name.png`.
pub(crate) fn sibling(path: &Path, suffix: &str) -> PathBuf {
    let stem = path.file_stem().and_then(|s| s.to_str()).unwrap_or("view");
    path.with_file_name(format!("{stem}{suffix}.png"))
}

/// Saves a picture as PNG (quietly: callers say what they wrote where their output goes).
pub(crate) fn save<P, C>(image: &image::ImageBuffer<P, C>, path: &Path) -> anyhow::Result<()>
where
    P: image::PixelWithColorType,
    [P::Subpixel]: image::EncodableLayout,
    C: std::ops::Deref<Target = [P::Subpixel]>,
{
    image
        .save_with_format(path, ImageFormat::Png)
        .with_context(|| format!("writing {}", path.display()))
}

/// A 16-bit grayscale PNG of raw depth units (the server's `image/png` depth).
fn depth_from_png(png: &[u8]) -> anyhow::Result<DepthImage> {
    let image = image::load_from_memory_with_format(png, ImageFormat::Png)
        .context("decoding the depth PNG")?;
    let image::DynamicImage::ImageLuma16(gray) = image else {
        bail!("the depth PNG is not 16-bit grayscale");
    };
    Ok(DepthImage {
        width: gray.width(),
        height: gray.height(),
        timestamp_s: 0,
        depth_scale: 0.001,
        values: gray.into_raw(),
    })
}

/// A color packet in the format the camera's color-settings name.
fn color_from_packet(payload: &[u8], settings: &serde_json::Value) -> anyhow::Result<RgbImage> {
    let format = settings
        .get("format")
        .and_then(|f| f.as_str())
        .context("the color-settings have no format")?;
    if payload.len() < 10 || payload[0] != 1 {
        bail!("not a color packet");
    }
    let width = u32::from(u16::from_be_bytes([payload[1], payload[2]]));
    let height = u32::from(u16::from_be_bytes([payload[3], payload[4]]));
    view::rgb_image(
        &payload[10..],
        width,
        height,
        usize::from(payload[5]),
        format,
    )
    .map_err(|e| anyhow::anyhow!("the color packet: {e}"))
}
