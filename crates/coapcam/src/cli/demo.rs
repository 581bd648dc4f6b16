//! `coapcam demo`: the whole job on synthetic cameras, in one process: a server with the
//! two-camera scene on a free loopback port, discovery, the floor cut from the clouds,
//! grabs saved as files, a measurement, and the dimensions next to the scene's truth.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{Context as _, bail};
use clap::Args;
use coap::{ContentFormat, EndpointConfig};
use geometry::{DimensionConfig, Dimensions};
use rgbd::Scene;

use crate::client::{CamClient, Stream};
use crate::codes::Code;
use crate::grab_cmd::save;
use crate::measure::{self, Measurement, Source};
use crate::packet;
use crate::serve::SceneServer;
use crate::view;

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

/// Lowest point sent by the cameras, metres above the floor: the floor itself is not
/// transmitted (thesis §3.3.5), which makes the clouds several times smaller.
pub(crate) const FLOOR_CUT_M: f64 = 0.005;

/// Prepares every camera for measuring as the thesis does (§3.3.5): roi3d becomes the
/// box above the floor within `half_width_m` of the origin, and the spatial filter runs
/// (librealsense's defaults: it smooths the depth noise that widens a footprint's hull);
/// the rest of each application-config stays. With `for_codes` the color stream becomes
/// 1920x1080 at 30 fps (its format stays), so smaller codes can be read.
pub(crate) async fn prepare_cameras(
    client: &CamClient,
    serials: &[String],
    half_width_m: f64,
    for_codes: bool,
) -> anyhow::Result<()> {
    for sn in serials {
        if for_codes {
            let mut color = client.get_json(sn, "color-settings").await?;
            color["width"] = serde_json::json!(1920);
            color["height"] = serde_json::json!(1080);
            color["fps"] = serde_json::json!(30);
            client.put_json(sn, "color-settings", &color).await?;
        }
        let mut doc = client.get_json(sn, "application-config").await?;
        doc["roi3d"] = serde_json::json!({
            "min_x": -half_width_m, "max_x": half_width_m,
            "min_y": -half_width_m, "max_y": half_width_m,
            "min_z": FLOOR_CUT_M, "max_z": 3.0,
        });
        doc["postprocessing"]["spatial"] = serde_json::json!(1);
        client.put_json(sn, "application-config", &doc).await?;
    }
    Ok(())
}

/// The scene's largest box as measurements: length >= width, height, yaw of the long
/// side in (-90, 90].
pub(crate) fn truth(scene: &Scene) -> Option<[f64; 4]> {
    let b = scene
        .boxes
        .iter()
        .max_by(|a, b| (a.size[0] * a.size[1]).total_cmp(&(b.size[0] * b.size[1])))?;
    let (length, width, mut yaw) = if b.size[0] >= b.size[1] {
        (b.size[0], b.size[1], b.yaw_deg)
    } else {
        (b.size[1], b.size[0], b.yaw_deg + 90.0)
    };
    yaw = (yaw + 90.0).rem_euclid(180.0) - 90.0;
    if yaw <= -90.0 {
        yaw += 180.0;
    }
    Some([length * 1e3, width * 1e3, b.size[2] * 1e3, yaw])
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

/// Difference of two yaw angles of a rectangle's long side, in (-90, 90].
pub(crate) fn yaw_difference(a: f64, b: f64) -> f64 {
    let d = (a - b).rem_euclid(180.0);
    if d > 90.0 { d - 180.0 } else { d }
}

/// Runs `demo`.
pub(crate) async fn run(args: DemoArgs) -> anyhow::Result<bool> {
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
    println!(
        "server: {} synthetic D415 camera(s) on {uri}",
        scene.cameras.len()
    );
    let client =
        CamClient::connect(&uri, EndpointConfig::default(), Duration::from_secs(30)).await?;
    let serials = client.cameras().await?;
    println!("discovered cameras: {}", serials.join(", "));
    let Some(first) = serials.first() else {
        bail!("the server has no camera");
    };
    prepare_cameras(&client, &serials, 1.0, true).await?;
    println!(
        "application-config: roi3d from {:.0} mm above the floor (the floor is not sent), spatial filter on; color 1920x1080",
        FLOOR_CUT_M * 1e3
    );

    save_grabs(&client, first, dir).await?;
    let m = measure::measure_once(&client, &Source::All, &DimensionConfig::default()).await?;
    let codes = crate::codes::read_cameras(&client, &m.grabbed.cameras).await?;
    let cloud_path = dir.join("cloud.ply");
    let ply = geometry::encode_ply(&m.grabbed.cloud.points, Some("coapcam demo, metres, z up"))
        .context("encoding the PLY cloud")?;
    std::fs::write(&cloud_path, ply)
        .with_context(|| format!("writing {}", cloud_path.display()))?;
    println!(
        "wrote {} ({} points)",
        cloud_path.display(),
        m.grabbed.cloud.len()
    );
    let top = dir.join("top.png");
    save(&view::top_view(&m.grabbed.cloud), &top)?;
    println!("wrote {}", top.display());
    let annotated = dir.join("annotated.png");
    crate::annotate::from_server(&client, first, &m.dimensions, &annotated).await?;
    println!("wrote {} (camera {first})", annotated.display());
    println!();
    print!("{}", report(&m, truth(&scene)));
    println!(
        "codes: {}; on the scene's parcels: {}",
        crate::codes::describe(&codes),
        scene_codes(&scene)
    );
    Ok(true)
}

/// color.png, depth.png (16-bit raw units), depth-view.png and depth-color.png of one
/// camera.
async fn save_grabs(client: &CamClient, serial: &str, dir: &Path) -> anyhow::Result<()> {
    let color = client
        .grab(serial, Stream::Color, Some(ContentFormat::IMAGE_PNG))
        .await?;
    let path = dir.join("color.png");
    std::fs::write(&path, &color.payload).with_context(|| format!("writing {}", path.display()))?;
    println!("wrote {} (camera {serial})", path.display());
    let depth = client.grab(serial, Stream::Depth, None).await?;
    let depth = packet::depth(&depth.payload).context("reading the depth packet")?;
    let raw = image::ImageBuffer::<image::Luma<u16>, _>::from_raw(
        depth.width,
        depth.height,
        depth.values.clone(),
    )
    .context("the depth image's size")?;
    let (gray, colored) = view::depth_views(&depth);
    let depth_views = [
        ("depth-view.png", gray.into()),
        ("depth-color.png", image::DynamicImage::from(colored)),
    ];
    save(&raw, &dir.join("depth.png"))?;
    println!("wrote {}", dir.join("depth.png").display());
    for (name, picture) in depth_views {
        let path = dir.join(name);
        picture
            .save_with_format(&path, image::ImageFormat::Png)
            .with_context(|| format!("writing {}", path.display()))?;
        println!("wrote {}", path.display());
    }
    Ok(())
}

/// The measurement next to the truth, as a table.
fn report(m: &Measurement, truth: Option<[f64; 4]>) -> String {
    let d: &Dimensions = &m.dimensions;
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
        d.volume_l,
        m.volumetric_weight_kg(),
        d.points,
        m.grabbed.cameras.len(),
        m.cycle.as_secs_f64() * 1e3,
        m.grabbed.bytes as f64 / 1e6
    );
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_truth_names_the_long_side_and_its_yaw() {
        let mut scene = Scene::default_single();
        scene.boxes[0].size = [0.3, 0.5, 0.2];
        scene.boxes[0].yaw_deg = 30.0;
        assert_eq!(truth(&scene), Some([500.0, 300.0, 200.0, -60.0]));
        scene.boxes[0].size = [0.5, 0.3, 0.2];
        scene.boxes[0].yaw_deg = 100.0;
        assert_eq!(truth(&scene).map(|t| t[3].round()), Some(-80.0));
    }

    #[test]
    fn yaw_differences_wrap_at_half_a_turn() {
        assert_eq!(yaw_difference(89.0, -89.0), -2.0);
        assert_eq!(yaw_difference(10.0, 5.0), 5.0);
        assert_eq!(yaw_difference(-85.0, 85.0), 10.0);
    }
}
