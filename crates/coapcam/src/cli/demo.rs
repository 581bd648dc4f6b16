//! `coapcam demo`: the whole job on synthetic cameras, in one process: a server with the
//! two-camera scene on a free loopback port, discovery, the floor cut from the clouds,
//! grabs saved as files, a measurement, and the dimensions next to the scene's truth.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{Context as _, bail};
use clap::Args;
use coap::ContentFormat;
use geometry::{DimensionConfig, Dimensions, Shape};
use rgbd::Scene;

use super::{Exit, out, outln};
use coapcam::client::CamClient;
use coapcam::client::measure::{
    self, CloudMeasurement, FLOOR_CUT_M, Source, prepare_cameras, truth, yaw_difference,
};
use coapcam::client::{annotate, codes};
use coapcam::report::{Billing, Parcel, describe};
use coapcam::repr::Stream;
use coapcam::server::SceneServer;
use coapcam::vision::codes::Code;
use coapcam::vision::picture::{self, save};

/// Flags of `demo`.
#[derive(Debug, Args)]
pub(crate) struct DemoArgs {
    /// Directory for the pictures, the cloud and the server's state.
    #[arg(long, value_name = "DIR", default_value = "coapcam-demo")]
    dir: PathBuf,
    /// A scene file instead of the built-in two-camera scene.
    #[arg(long, value_name = "FILE")]
    scene: Option<PathBuf>,
}

/// The labels of the scene's boxes, as `describe` names codes: `qr "PKG-0001"`, or
/// `none`.
fn scene_codes(scene: &Scene) -> String {
    let labels: Vec<String> = scene
        .boxes
        .iter()
        .filter_map(|b| b.label.as_ref())
        .map(|l| {
            let code = Code {
                kind: l.kind.into(),
                text: l.text.clone(),
            };
            code.to_string()
        })
        .collect();
    if labels.is_empty() {
        "none".into()
    } else {
        labels.join(", ")
    }
}

/// Runs `demo`.
pub(crate) async fn run(args: DemoArgs) -> anyhow::Result<Exit> {
    let scene = match &args.scene {
        Some(path) => {
            Scene::load(path).with_context(|| format!("loading scene {}", path.display()))?
        }
        None => Scene::default_demo(),
    };
    let dir = &args.dir;
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let server = SceneServer::start(
        &scene,
        &dir.join("state"),
        SocketAddr::from(([127, 0, 0, 1], 0)),
    )
    .await?;
    let uri = format!("coap://{}", server.addr()?);
    outln!(
        "server: {} synthetic D415 camera(s) on {uri}",
        scene.cameras.len()
    );
    let client = CamClient::at(server.addr()?, Duration::from_secs(30))?;
    let serials = client.cameras().await?;
    outln!("discovered cameras: {}", serials.join(", "));
    let Some(first) = serials.first() else {
        bail!("the server has no camera");
    };
    prepare_cameras(&client, &serials, 1.0, true).await?;
    outln!(
        "application-config: roi3d from {:.0} mm above the floor (the floor is not sent), flying-pixel stage and spatial filter on; color 1920x1080",
        FLOOR_CUT_M * 1e3
    );

    save_grabs(&client, first, dir).await?;
    let m = measure::measure_once(&client, &Source::All, &DimensionConfig::default()).await?;
    let codes = codes::read_cameras(&client, &m.grabbed.cameras).await?;
    let cloud_path = dir.join("cloud.ply");
    let ply = geometry::encode_ply(&m.grabbed.cloud.points, Some("coapcam demo, metres, z up"))
        .context("encoding the PLY cloud")?;
    std::fs::write(&cloud_path, ply)
        .with_context(|| format!("writing {}", cloud_path.display()))?;
    outln!(
        "wrote {} ({} points)",
        cloud_path.display(),
        m.grabbed.cloud.len()
    );
    let top = dir.join("top.png");
    save(&picture::top_view(&m.grabbed.cloud, m.dimensions()), &top)?;
    outln!("wrote {}", top.display());
    let annotated = dir.join("annotated.png");
    let Parcel::Measured(dimensions, shape) = &m.parcel else {
        bail!("nothing on the table: the scene's box was not seen");
    };
    // The demo's own unrounded measurement, beside the scene's truth.
    annotate::from_server(&client, first, dimensions, None, Some(&codes), &annotated).await?;
    outln!("wrote {} (camera {first})", annotated.display());
    outln!("");
    out!("{}", report(&m, dimensions, *shape, truth(&scene)));
    outln!(
        "codes: {}; on the scene's parcels: {}",
        describe(&codes),
        scene_codes(&scene)
    );
    Ok(Exit::Success)
}

/// color.jpg (a picture for people: JPEG at the server's quality), depth.png (16-bit raw
/// units), depth-view.png and depth-color.png of one camera.
async fn save_grabs(client: &CamClient, serial: &str, dir: &Path) -> anyhow::Result<()> {
    let color = client
        .grab(serial, Stream::Color, Some(ContentFormat::IMAGE_JPEG))
        .await?;
    let path = dir.join("color.jpg");
    std::fs::write(&path, &color.payload).with_context(|| format!("writing {}", path.display()))?;
    outln!("wrote {} (camera {serial})", path.display());
    let depth = client.grab_depth(serial).await?;
    let raw = image::ImageBuffer::<image::Luma<u16>, _>::from_raw(
        depth.width,
        depth.height,
        depth.values.clone(),
    )
    .context("the depth image's size")?;
    let (gray, colored) = picture::depth_views(&depth);
    let depth_views = [
        ("depth-view.png", gray.into()),
        ("depth-color.png", image::DynamicImage::from(colored)),
    ];
    save(&raw, &dir.join("depth.png"))?;
    outln!("wrote {}", dir.join("depth.png").display());
    for (name, picture) in depth_views {
        let path = dir.join(name);
        picture
            .save_with_format(&path, image::ImageFormat::Png)
            .with_context(|| format!("writing {}", path.display()))?;
        outln!("wrote {}", path.display());
    }
    Ok(())
}

/// The measurement of `d`, the scene's box (its volume billed as its measured `shape`
/// says), next to the truth, as a table.
fn report(m: &CloudMeasurement, d: &Dimensions, shape: Shape, truth: Option<[f64; 4]>) -> String {
    let billing = Billing::default();
    let measured = [d.length_mm, d.width_mm, d.height_mm, d.yaw_deg];
    let names = ["length mm", "width mm", "height mm", "yaw deg"];
    let mut out = format!(
        "{:<10} {:>9} {:>9} {:>8}\n",
        "", "measured", "scene", "error"
    );
    for (i, name) in names.iter().enumerate() {
        match truth {
            Some(t) => {
                let error = if i == 3 {
                    yaw_difference(measured[i], t[i])
                } else {
                    measured[i] - t[i]
                };
                out += &format!(
                    "{name:<10} {:>9.1} {:>9.1} {error:>+8.1}\n",
                    measured[i], t[i]
                );
            }
            None => out += &format!("{name:<10} {:>9.1} {:>9} {:>8}\n", measured[i], "-", "-"),
        }
    }
    out += &format!(
        "volume {:.2} l, volumetric weight {:.2} kg, {} points from {} camera(s), cycle {:.0} ms ({:.2} MB)\n",
        billing.volume_l(d, shape),
        billing.volumetric_weight_kg(d, shape),
        d.points,
        m.grabbed.cameras.len(),
        m.cycle.as_secs_f64() * 1e3,
        m.grabbed.bytes as f64 / 1e6
    );
    out
}
