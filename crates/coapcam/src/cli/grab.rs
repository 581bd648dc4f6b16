//! `coapcam grab`: one new frame of one camera (or every camera's merged cloud) into a
//! file whose extension chooses the representation, and optionally a picture for people.

use std::path::{Path, PathBuf};

use anyhow::Context as _;
use clap::Args;
use coap::{ContentFormat, Response};
use coapcam::client::CamClient;
use coapcam::repr::{self, ColorDecoder, Stream};
use coapcam::vision::picture::{self, save, sibling};
use rgbd::ColorSettings;

use super::part_file::PartFile;
use super::{Bars, CameraArgs, Exit, TransmissionArgs, folder_exists, usage};

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
    /// `-` writes to standard output, in the format of --format (the thesis packet
    /// without it). Its folder must exist: that is checked before anything is grabbed.
    #[arg(short = 'o', long = "output", value_name = "FILE")]
    output: PathBuf,
    /// With `-o -`: the format written to standard output, as an extension (jpg, png,
    /// rvl, rvl.zst, ply, dcl, qmm, bin).
    #[arg(long, value_name = "EXT")]
    format: Option<String>,
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

/// The extension of a file named `path` (`rvl.zst` for a double one).
fn extension(path: &Path) -> &str {
    let name = path
        .file_name()
        .and_then(|n| n.to_str())
        .unwrap_or_default();
    if name.to_ascii_lowercase().ends_with(".rvl.zst") {
        "rvl.zst"
    } else {
        path.extension()
            .and_then(|e| e.to_str())
            .unwrap_or_default()
    }
}

/// The content format a file with extension `ext` (named `name` in messages) holds for
/// `stream`, by the table of [`Stream::formats`]; a [`Usage`] error names what fits.
fn file_format(name: &str, ext: &str, stream: Stream) -> anyhow::Result<ContentFormat> {
    let ext = ext.trim_start_matches('.');
    if Stream::ALL
        .iter()
        .all(|s| s.format_of_extension(ext).is_none())
    {
        usage!(
            "{name}: the extension must be .jpg, .png, .rvl, .rvl.zst, .ply, .dcl, .qmm or .bin"
        );
    }
    match stream.format_of_extension(ext) {
        Some(cf) => Ok(cf),
        None => {
            let all: Vec<String> = Stream::ALL
                .iter()
                .map(|s| format!("{} as {}", s.name(), s.extensions()))
                .collect();
            usage!(
                "{name}: {} cannot be written as .{ext}: {}",
                stream.name(),
                all.join("; ")
            )
        }
    }
}

/// Where the grab goes: a [`PartFile`] beside the output, made before anything is grabbed
/// (so a folder that does not exist or cannot be written fails first) and renamed to it
/// once the body is written; removed if the command ends before. Or standard output
/// (`-o -`).
enum Destination {
    /// The temporary file, and the output as named.
    File(PartFile, PathBuf),
    Stdout,
}

impl Destination {
    fn open(output: &Path) -> anyhow::Result<Self> {
        if output.as_os_str() == "-" {
            return Ok(Self::Stdout);
        }
        Ok(Self::File(PartFile::create(output)?, output.to_path_buf()))
    }

    /// Writes `body` and makes it the output.
    fn write(self, body: &[u8]) -> anyhow::Result<()> {
        match self {
            Self::Stdout => {
                use std::io::Write as _;
                let mut out = std::io::stdout().lock();
                out.write_all(body)
                    .and_then(|()| out.flush())
                    .context("writing standard output")?;
                eprintln!("coapcam: wrote {} bytes to standard output", body.len());
            }
            Self::File(mut part, output) => {
                part.write(body)?;
                part.keep()?;
                eprintln!("coapcam: wrote {} ({} bytes)", output.display(), body.len());
            }
        }
        Ok(())
    }
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
        usage!("--all is for point clouds: every camera's cloud merged");
    }
    let stdout = args.output.as_os_str() == "-";
    let kind = match (&args.format, stdout) {
        (Some(ext), true) => file_format("--format", ext, stream)?,
        (None, true) => ContentFormat::OCTET_STREAM,
        (Some(_), false) => {
            usage!("--format is for -o - (standard output); a file's extension chooses its format")
        }
        (None, false) => file_format(
            &args.output.display().to_string(),
            extension(&args.output),
            stream,
        )?,
    };
    if let Some(v) = &args.view
        && !extension(v).eq_ignore_ascii_case("png")
    {
        usage!("--view writes PNG: give a .png file name");
    }
    if args.jpeg_quality.is_some() && kind != ContentFormat::IMAGE_JPEG {
        usage!("--jpeg-quality is for color written to a .jpg file");
    }
    if let Some(v) = &args.view {
        folder_exists(v)?;
    }
    let destination = Destination::open(&args.output)?;
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
    destination.write(&response.payload)?;
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
