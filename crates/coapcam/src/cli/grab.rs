//! `coapcam grab`: one new frame of one camera (or every camera's merged cloud) into a
//! file whose extension chooses the representation, and optionally a picture for people.

use std::path::{Path, PathBuf};

use anyhow::{Context as _, bail};
use clap::Args;
use coap::{ContentFormat, Response};
use coapcam::client::CamClient;
use coapcam::repr::{self, ColorDecoder, Stream};
use coapcam::vision::picture::{self, save, sibling};
use rgbd::ColorSettings;

use super::{Bars, CameraArgs, Exit, TransmissionArgs};

/// The streams, named for the command line.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum What {
    /// The color image.
    Color,
    /// The depth image.
    Depth,
    /// The point cloud.
    Pointcloud,
}

impl From<What> for Stream {
    fn from(what: What) -> Self {
        match what {
            What::Color => Self::Color,
            What::Depth => Self::Depth,
            What::Pointcloud => Self::Pointcloud,
        }
    }
}

/// Flags of `grab`.
#[derive(Debug, Args)]
pub(crate) struct GrabArgs {
    /// What to grab.
    #[arg(value_name = "STREAM")]
    what: What,
    #[command(flatten)]
    cameras: CameraArgs,
    /// Output file; its extension chooses the format: .jpg (color, for people), .png
    /// (color, lossless; depth as 16-bit PNG of raw units), .rvl and .rvl.zst (depth,
    /// lossless), .ply (point cloud, binary PLY), .dcl (the compact cloud: filtered depth
    /// and its geometry), .qmm (a cloud in whole millimetres), .bin (the thesis packet).
    #[arg(short = 'o', long = "output", value_name = "FILE")]
    output: PathBuf,
    /// With a .jpg file: the JPEG quality, 1-100 (the server's default is 90).
    #[arg(long, value_name = "Q", value_parser = clap::value_parser!(u8).range(1..=100))]
    jpeg_quality: Option<u8>,
    /// Also write what a person looks at, as PNG: the color image; depth in grayscale
    /// (near bright) plus a colour-mapped copy named FILE-color.png; a point cloud seen
    /// from above, coloured by height.
    #[arg(long, value_name = "FILE.png")]
    view: Option<PathBuf>,
    #[command(flatten)]
    transmission: TransmissionArgs,
}

/// The content format a file named `path` holds for `stream` (the extension decides, by
/// the table of [`Stream::formats`]).
fn file_format(path: &Path, stream: Stream) -> anyhow::Result<ContentFormat> {
    let name = path
        .file_name()
        .and_then(|n| n.to_str())
        .unwrap_or_default();
    let ext = if name.to_ascii_lowercase().ends_with(".rvl.zst") {
        "rvl.zst"
    } else {
        path.extension()
            .and_then(|e| e.to_str())
            .unwrap_or_default()
    };
    if Stream::ALL
        .iter()
        .all(|s| s.format_of_extension(ext).is_none())
    {
        bail!(
            "{}: the extension must be .jpg, .png, .rvl, .rvl.zst, .ply, .dcl, .qmm or .bin",
            path.display()
        );
    }
    stream.format_of_extension(ext).with_context(|| {
        let all: Vec<String> = Stream::ALL
            .iter()
            .map(|s| format!("{} as {}", s.name(), s.extensions()))
            .collect();
        format!(
            "{}: {} cannot be written as .{ext}: {}",
            path.display(),
            stream.name(),
            all.join("; ")
        )
    })
}

/// The Accept option of a grab for a file in `cf`: none for the thesis packet, the
/// resources' default.
fn accept(cf: ContentFormat) -> Option<ContentFormat> {
    (cf != ContentFormat::OCTET_STREAM).then_some(cf)
}

/// Runs `grab`.
pub(crate) async fn run(args: GrabArgs) -> anyhow::Result<Exit> {
    let stream = Stream::from(args.what);
    if args.cameras.all && stream != Stream::Pointcloud {
        bail!("--all is for point clouds: every camera's cloud merged");
    }
    let kind = file_format(&args.output, stream)?;
    if let Some(v) = &args.view
        && file_format(v, Stream::Color).ok() != Some(ContentFormat::IMAGE_PNG)
    {
        bail!("--view writes PNG: give a .png file name");
    }
    if args.jpeg_quality.is_some() && kind != ContentFormat::IMAGE_JPEG {
        bail!("--jpeg-quality is for color written to a .jpg file");
    }
    let client = args
        .cameras
        .connect(&args.transmission)
        .await?
        .with_progress(Bars::shown());
    let (sn, response) = if args.cameras.all {
        (None, client.grab_all(accept(kind)).await?)
    } else {
        let sn = client.one_camera(args.cameras.camera.as_deref()).await?;
        let response = match args.jpeg_quality {
            Some(q) => client.grab_jpeg(&sn, q).await?,
            None => client.grab(&sn, stream, accept(kind)).await?,
        };
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
    Ok(Exit::Success)
}

/// Writes the picture(s) of `--view` from the representation that arrived (from camera
/// `sn`, `None` with `--all`); returns the files written.
async fn write_view(
    client: &CamClient,
    sn: Option<&str>,
    args: &GrabArgs,
    kind: ContentFormat,
    response: &Response,
    path: &Path,
) -> anyhow::Result<Vec<PathBuf>> {
    let row = repr::Format::received(Some(kind))?;
    match Stream::from(args.what) {
        Stream::Color => {
            let image = match row.color_decoder()? {
                ColorDecoder::Image(decode) => decode(&response.payload)?,
                ColorDecoder::WithPixelFormat(decode) => {
                    let sn = sn.context("--all is for point clouds")?;
                    let settings: ColorSettings = client.get_json(sn, "color-settings").await?;
                    decode(&response.payload, settings.format.name())?
                }
            };
            save(&image, path)?;
            Ok(vec![path.to_owned()])
        }
        Stream::Depth => {
            let depth = row.decode_depth(&response.payload)?;
            let colored = sibling(path, "-color");
            let (gray, colored_view) = picture::depth_views(&depth);
            save(&gray, path)?;
            save(&colored_view, &colored)?;
            Ok(vec![path.to_owned(), colored])
        }
        Stream::Pointcloud => {
            let cloud = row.decode_cloud(&response.payload)?.cloud;
            save(&picture::top_view(&cloud, None), path)?;
            Ok(vec![path.to_owned()])
        }
    }
}
