//! `--annotate`: the measured box drawn onto a color frame, through the frame's CBOR
//! representation (color intrinsics and depth->color extrinsics) and the camera's
//! 3d-transformation.

use anyhow::{Context as _, bail};
use bytes::Bytes;
use coap::Code;
use geometry::Dimensions;

use crate::cbor;
use crate::client::{CamClient, Stream};

/// A color frame as the server's CBOR representation carries it: RGB pixels, the color
/// intrinsics and the depth->color extrinsics.
pub(crate) struct ColorCapture {
    pub(crate) image: image::RgbImage,
    pub(crate) intrinsics: rgbd::Intrinsics,
    pub(crate) depth_to_color: rgbd::Extrinsics,
}

impl ColorCapture {
    /// Reads the CBOR color representation (DESIGN.md §5).
    pub(crate) fn from_cbor(body: &[u8]) -> anyhow::Result<Self> {
        let value: ciborium::Value =
            ciborium::from_reader(body).context("decoding the CBOR color frame")?;
        let map = value
            .as_map()
            .context("the CBOR color frame is not a map")?;
        let (width, height) = (cbor::u32_of(map, "width")?, cbor::u32_of(map, "height")?);
        let bpp = cbor::u32_of(map, "pixel_size")? as usize;
        let format = cbor::field(map, "format")?
            .as_text()
            .context("format is not text")?;
        let data = cbor::field(map, "data")?
            .as_bytes()
            .context("data is not bytes")?;
        let image = crate::view::rgb_image(data, width, height, bpp, format)
            .map_err(|e| anyhow::anyhow!("the CBOR color frame: {e}"))?;
        let k = cbor::field(map, "intrinsics")?
            .as_map()
            .context("intrinsics is not a map")?;
        let model_name = cbor::field(k, "model")?
            .as_text()
            .context("model is not text")?;
        let f = |key: &str| -> anyhow::Result<f32> {
            Ok(cbor::field(k, key)?
                .as_float()
                .with_context(|| format!("{key} is not a number"))? as f32)
        };
        let intrinsics = rgbd::Intrinsics {
            width: cbor::u32_of(k, "width")?,
            height: cbor::u32_of(k, "height")?,
            ppx: f("ppx")?,
            ppy: f("ppy")?,
            fx: f("fx")?,
            fy: f("fy")?,
            model: rgbd::DistortionModel::from_name(model_name)
                .with_context(|| format!("unknown distortion model {model_name:?}"))?,
            coeffs: cbor::floats(cbor::field(k, "coeffs")?)?,
        };
        let e = cbor::field(map, "depth_to_color")?
            .as_map()
            .context("depth_to_color is not a map")?;
        let depth_to_color = rgbd::Extrinsics {
            rotation: cbor::floats(cbor::field(e, "rotation")?)?,
            translation: cbor::floats(cbor::field(e, "translation")?)?,
        };
        Ok(Self {
            image,
            intrinsics,
            depth_to_color,
        })
    }

    /// The pixel at which a world point (the 3d-transformation's output frame) is seen,
    /// given the camera's `depth_to_world` transformation; `None` behind the camera.
    pub(crate) fn projector(
        &self,
        depth_to_world: &geometry::Transform,
    ) -> anyhow::Result<impl Fn([f64; 3]) -> Option<[f32; 2]> + '_> {
        let inverse = depth_to_world
            .linear
            .try_inverse()
            .context("the 3d-transformation cannot be inverted")?;
        let translation = depth_to_world.translation;
        if !self.intrinsics.is_pinhole() {
            bail!(
                "the color stream's {} distortion cannot be drawn through",
                self.intrinsics.model.name()
            );
        }
        Ok(move |[x, y, z]: [f64; 3]| {
            let world = nalgebra::Vector3::new(x as f32, y as f32, z as f32);
            let depth = inverse * (world - translation);
            let c = self.depth_to_color.transform([depth.x, depth.y, depth.z]);
            (c[2] > 1e-3)
                .then(|| self.intrinsics.project(c).ok())
                .flatten()
        })
    }
}

/// Grabs a color frame of `serial` and draws `dims` onto it (`--annotate`).
pub(crate) async fn from_server(
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
    crate::view::annotate(&mut image, dims, capture.projector(&transform)?);
    crate::grab_cmd::save(&image, path)
}
