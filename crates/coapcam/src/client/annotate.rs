//! `--annotate`: the measured box drawn onto a color frame, through the frame's CBOR
//! representation (color intrinsics and depth->color extrinsics) and the camera's
//! 3d-transformation.

use anyhow::{Context as _, bail};
use bytes::Bytes;
use coap::Code;
use geometry::Dimensions;

use super::CamClient;
use crate::repr::Stream;
use crate::repr::cbor::ColorCapture;
use crate::vision::picture;

/// The pixel at which a world point (the 3d-transformation's output frame) is seen in
/// `capture`, given the camera's `depth_to_world` transformation; `None` behind the
/// camera.
pub fn projector<'a>(
    capture: &'a ColorCapture,
    depth_to_world: &geometry::Transform,
) -> anyhow::Result<impl Fn([f64; 3]) -> Option<[f32; 2]> + 'a> {
    let inverse = depth_to_world
        .linear
        .try_inverse()
        .context("the 3d-transformation cannot be inverted")?;
    let translation = depth_to_world.translation;
    if !capture.intrinsics.is_pinhole() {
        bail!(
            "the color stream's {} distortion cannot be drawn through",
            capture.intrinsics.model.name()
        );
    }
    Ok(move |[x, y, z]: [f64; 3]| {
        let world = nalgebra::Vector3::new(x as f32, y as f32, z as f32);
        let depth = inverse * (world - translation);
        let c = capture
            .depth_to_color
            .transform([depth.x, depth.y, depth.z]);
        (c[2] > 1e-3)
            .then(|| capture.intrinsics.project(c).ok())
            .flatten()
    })
}

/// Grabs a color frame of `serial` and draws `dims` onto it (`--annotate`).
pub async fn from_server(
    client: &CamClient,
    serial: &str,
    dims: &Dimensions,
    path: &std::path::Path,
) -> anyhow::Result<()> {
    let transformation_path = format!("/cams/{serial}/3d-transformation");
    let (color, transformation) = tokio::try_join!(
        client.grab(serial, Stream::Color, Some(coap::ContentFormat::CBOR)),
        client.call(Code::GET, &transformation_path, Bytes::new(), None, None),
    )?;
    let transform = geometry::Transformation::from_json(&transformation.payload)
        .context("reading the 3d-transformation")?
        .to_transform()
        .context("composing the 3d-transformation")?;
    let mut capture = ColorCapture::from_cbor(&color.payload)?;
    let mut image = std::mem::take(&mut capture.image);
    // The camera in the world: where its depth frame's origin goes.
    let camera = transform.translation.map(f64::from);
    picture::annotate(
        &mut image,
        dims,
        [camera.x, camera.y, camera.z],
        projector(&capture, &transform)?,
    );
    picture::save(&image, path)
}
