//! Making a measurement to record, the one way every measurement path does it (a client's
//! `POST /cams/dimensions`, the station's HTTP and automatic ones): the edge measurement
//! of every camera (with the codes when asked), a photo (JPEG) of the first camera in
//! merge order, taken while the clouds are grabbed, and the measured box drawn onto that
//! photo (PNG). The cameras are a [`Rig`], which the server's `/cams` tree is; the result
//! is a [`Measured`]. The server keeps what it measures for a client through
//! [`Records`], which the station above it implements with its results log.

use std::future::Future;
use std::pin::Pin;
use std::sync::Arc;

use geometry::Transformation;
use rgbd::{Camera, ColorFrame, Extrinsics, Intrinsics, Serial};

use crate::api::record::{CameraPose, Event, Trigger};
use crate::report::{EdgeQuery, Found, Measurement};
use crate::repr::raster;
use crate::vision::picture;

/// A measurement made to be recorded: what [`measure`] hands on.
#[derive(Debug, Clone)]
pub struct Measured {
    /// What made it.
    pub trigger: Trigger,
    /// The measurement.
    pub measurement: Measurement,
    /// Each camera's serial and 3d-transformation.
    pub cameras: Vec<CameraPose>,
    /// The photo, JPEG.
    pub photo_jpeg: Option<Vec<u8>>,
    /// The annotated picture, PNG.
    pub annotated_png: Option<Vec<u8>>,
    /// SHA-256 (hex) of the legally relevant parameters in force when it was measured
    /// ([`Rig::parameters_sha256`]).
    pub parameters_sha256: String,
}

/// Where a camera server keeps each measurement it makes for a client
/// (`POST /cams/dimensions`) before it answers: the station's results log. With none set
/// the server measures without pictures and keeps nothing.
pub trait Records: Send + Sync + 'static {
    /// Keeps `measured`; the error says, in words fit for the client, why it was not
    /// kept (the client is then told that it was measured but not recorded).
    fn keep(
        &self,
        measured: Measured,
    ) -> Pin<Box<dyn Future<Output = Result<(), String>> + Send + '_>>;

    /// Keeps the change of a legally relevant parameter, before it is answered; it
    /// blocks (call it on the blocking pool). The error says, in words fit for the
    /// client, why it was not kept (the change is then undone).
    fn change(&self, event: Event) -> Result<(), String>;
}

/// JPEG quality of the photo: a legible label and parcel at a tenth of the PNG's bytes.
pub const PHOTO_QUALITY: u8 = 85;

/// A color frame of one camera, with what drawing on it needs.
#[derive(Debug, Clone)]
pub struct Shot {
    /// The frame.
    pub frame: ColorFrame,
    /// The color camera's intrinsics for this frame.
    pub intrinsics: Intrinsics,
    /// Where a point of the depth camera lies in the color camera's frame.
    pub depth_to_color: Extrinsics,
    /// The camera's 3d-transformation (depth frame -> table frame).
    pub transformation: Transformation,
}

/// A connected camera with its 3d-transformation, as the watcher looks through it.
#[derive(Clone)]
pub struct RigCamera {
    /// Its serial.
    pub serial: Serial,
    /// The camera.
    pub camera: Arc<dyn Camera>,
    /// Its 3d-transformation now.
    pub transformation: Transformation,
}

/// What measuring needs of a server's cameras. The `/cams` tree is the one there is; the
/// station's watcher and HTTP side measure through it.
pub trait Rig: Send + Sync + 'static {
    /// Why a measurement failed.
    type Error: std::error::Error + Send + Sync + 'static;

    /// The edge measurement of every camera, as `query` asks.
    fn measure(
        &self,
        query: &EdgeQuery,
    ) -> impl Future<Output = Result<Measurement, Self::Error>> + Send;

    /// A new color frame of camera `serial`.
    fn shot(&self, serial: Serial) -> impl Future<Output = Result<Shot, String>> + Send;

    /// The serial and 3d-transformation of each camera of `serials`.
    fn poses(&self, serials: &[String]) -> Vec<CameraPose>;

    /// The connected cameras, in merge order.
    fn cameras(&self) -> Vec<RigCamera>;

    /// SHA-256 (hex) of the legally relevant parameters in force now
    /// ([`crate::api::record::parameters_sha256`] of every connected camera's documents).
    fn parameters_sha256(&self) -> String;
}

/// Measures with every camera of `rig` as `query` asks and, with `pictures`, takes the
/// photo and draws the annotated picture: the [`Measured`] to record as made by
/// `trigger`. A photo or picture that cannot be made is left out, with a warning in the
/// measurement saying why.
pub async fn measure<R: Rig>(
    rig: &R,
    query: &EdgeQuery,
    trigger: Trigger,
    pictures: bool,
) -> Result<Measured, R::Error> {
    let first = rig.cameras().first().map(|c| c.serial);
    let shot = async {
        match (pictures, first) {
            (true, Some(serial)) => Some(rig.shot(serial).await),
            (true, None) => Some(Err("no camera is connected".to_owned())),
            (false, _) => None,
        }
    };
    let (measurement, shot) = tokio::join!(rig.measure(query), shot);
    let mut measurement = measurement?;
    let (photo_jpeg, annotated_png) = match shot {
        None => (None, None),
        Some(Err(why)) => {
            measurement.warnings.push(format!("no photo: {why}"));
            (None, None)
        }
        Some(Ok(shot)) => {
            let found = measurement.parcel.clone();
            let points = usize::try_from(measurement.parcel_points).unwrap_or(usize::MAX);
            let codes: Option<Vec<String>> = measurement
                .codes
                .as_ref()
                .map(|seen| seen.iter().map(|s| s.code.to_string()).collect());
            let made = tokio::task::spawn_blocking(move || {
                pictures_of(&shot, &found, points, codes.as_deref())
            })
            .await
            .unwrap_or_else(|e| {
                let why = format!("the pictures' task failed: {e}");
                (Err(why.clone()), Err(why))
            });
            let photo = made
                .0
                .map_err(|why| measurement.warnings.push(format!("no photo: {why}")))
                .ok();
            let annotated = made
                .1
                .map_err(|why| {
                    measurement
                        .warnings
                        .push(format!("no annotated picture: {why}"))
                })
                .ok()
                .flatten();
            (photo, annotated)
        }
    };
    Ok(Measured {
        trigger,
        parameters_sha256: rig.parameters_sha256(),
        cameras: rig.poses(&measurement.cameras),
        measurement,
        photo_jpeg,
        annotated_png,
    })
}

/// A picture, or why it could not be made.
type Picture<T> = Result<T, String>;

/// The photo (JPEG) of `shot` and, when a parcel was measured, the box drawn onto it
/// (PNG; `None` when nothing was on the table).
fn pictures_of(
    shot: &Shot,
    found: &Found,
    points: usize,
    codes: Option<&[String]>,
) -> (Picture<Vec<u8>>, Picture<Option<Vec<u8>>>) {
    let photo = raster::color_jpeg(&shot.frame, PHOTO_QUALITY).map_err(|e| e.to_string());
    let Found::Measured(reported) = found else {
        return (photo, Ok(None));
    };
    let annotated = (|| {
        let transform = shot
            .transformation
            .to_transform()
            .map_err(|e| format!("the 3d-transformation: {e}"))?;
        let mut image = raster::color_rgb(&shot.frame);
        let dims = reported.dimensions(points);
        picture::annotate_frame(
            &mut image,
            &dims,
            &crate::report::box_caption(&dims, reported.division_mm),
            codes,
            shot.intrinsics,
            shot.depth_to_color,
            &transform,
        )
        .map_err(|e| format!("{e:#}"))?;
        let mut png = Vec::new();
        image
            .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
            .map_err(|e| format!("PNG: {e}"))?;
        Ok(Some(png))
    })();
    (photo, annotated)
}
