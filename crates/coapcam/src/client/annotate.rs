//! `--annotate`: the measured box drawn onto a color frame, through the frame's CBOR
//! representation (color intrinsics and depth->color extrinsics) and the camera's
//! 3d-transformation.

use bytes::Bytes;
use coap::Code;
use geometry::{Dimensions, TransformError};

use super::{CallError, CamClient};
use crate::report::Seen;
use crate::repr::Stream;
use crate::repr::cbor::{CborError, ColorCapture};
use crate::vision::picture;

/// An annotated picture that could not be made: the frame or the camera's
/// 3d-transformation not had or not read, the box not drawn, or the picture not saved.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum AnnotateError {
    /// The color frame or the 3d-transformation was not had (transparent: the causes the
    /// command's exit status looks for are the [`CallError`]'s sources, not itself).
    #[error(transparent)]
    Call(#[from] CallError),
    /// The 3d-transformation's document did not read.
    #[error("reading the 3d-transformation")]
    Transformation(#[source] TransformError),
    /// The 3d-transformation did not compose into one transform.
    #[error("composing the 3d-transformation")]
    Compose(#[source] TransformError),
    /// The color frame's CBOR did not read.
    #[error(transparent)]
    Capture(#[from] CborError),
    /// The box could not be drawn in the frame's view.
    #[error(transparent)]
    Project(#[from] picture::ProjectError),
    /// The picture could not be written.
    #[error(transparent)]
    Save(#[from] picture::SaveError),
}

/// The pixel at which a world point (the 3d-transformation's output frame) is seen in
/// `capture`, given the camera's `depth_to_world` transformation; `None` behind the
/// camera ([`picture::projector`]).
pub fn projector(
    capture: &ColorCapture,
    depth_to_world: &geometry::Transform,
) -> Result<impl Fn([f64; 3]) -> Option<[f32; 2]> + use<>, picture::ProjectError> {
    picture::projector(capture.intrinsics, capture.depth_to_color, depth_to_world)
}

/// Grabs a color frame of `serial` and draws `dims` onto it (`--annotate`), written with
/// the decimals of `division_mm` (the division they were rounded to; `None`: unrounded),
/// with the codes read (`None` when they were not asked for).
pub async fn from_server(
    client: &CamClient,
    serial: &str,
    dims: &Dimensions,
    division_mm: Option<f64>,
    codes: Option<&[Seen]>,
    path: &std::path::Path,
) -> Result<(), AnnotateError> {
    drawn_on_a_frame(client, serial, path, |image, capture, transform| {
        picture::annotate_frame(
            image,
            dims,
            &crate::report::box_caption(dims, division_mm),
            code_texts(codes).as_deref(),
            capture.intrinsics,
            capture.depth_to_color,
            transform,
        )
    })
    .await
}

/// Grabs a color frame of `serial` and draws onto it the parcel the measurement refused
/// (its footprint `corners_m` when known) and `reason` (`--annotate` of a refusal).
pub async fn refused_from_server(
    client: &CamClient,
    serial: &str,
    corners_m: Option<&[[f64; 2]; 4]>,
    reason: &str,
    codes: Option<&[Seen]>,
    path: &std::path::Path,
) -> Result<(), AnnotateError> {
    drawn_on_a_frame(client, serial, path, |image, capture, transform| {
        picture::annotate_refused_frame(
            image,
            corners_m,
            reason,
            code_texts(codes).as_deref(),
            capture.intrinsics,
            capture.depth_to_color,
            transform,
        )
    })
    .await
}

/// The codes' texts as the legend shows them.
fn code_texts(codes: Option<&[Seen]>) -> Option<Vec<String>> {
    codes.map(|seen| seen.iter().map(|s| s.code.to_string()).collect())
}

/// Grabs a color frame of `serial`, has `draw` mark it (given the capture's calibration
/// and the camera's 3d-transformation), and saves it to `path`.
async fn drawn_on_a_frame(
    client: &CamClient,
    serial: &str,
    path: &std::path::Path,
    draw: impl FnOnce(
        &mut image::RgbImage,
        &ColorCapture,
        &geometry::Transform,
    ) -> Result<(), picture::ProjectError>,
) -> Result<(), AnnotateError> {
    let (mut image, capture, transform) = frame(client, serial).await?;
    draw(&mut image, &capture, &transform)?;
    Ok(picture::save(&image, path)?)
}

/// A new color frame of `serial` (its image taken out of the capture) and the camera's
/// 3d-transformation.
async fn frame(
    client: &CamClient,
    serial: &str,
) -> Result<(image::RgbImage, ColorCapture, geometry::Transform), AnnotateError> {
    let transformation_path = crate::api::paths::camera(serial, "3d-transformation");
    let (color, transformation) = tokio::try_join!(
        client.grab(serial, Stream::Color, Some(coap::ContentFormat::CBOR)),
        client.call(Code::GET, &transformation_path, Bytes::new(), None, None),
    )?;
    let transform = geometry::Transformation::from_json(&transformation.payload)
        .map_err(AnnotateError::Transformation)?
        .to_transform()
        .map_err(AnnotateError::Compose)?;
    let mut capture = ColorCapture::from_cbor(&color.payload)?;
    let image = std::mem::take(&mut capture.image);
    Ok((image, capture, transform))
}
