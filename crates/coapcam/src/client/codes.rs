//! The codes on the parcel as the cameras see them (`measure --codes`, `demo`): a new color
//! image of every camera at once, read by [`crate::vision::codes`].

use std::net::SocketAddr;

use coap::ContentFormat;

use super::{CallError, CamClient};
use crate::report::Seen;
use crate::repr::Stream;
use crate::vision::codes::{Code, read};

/// The codes could not be read: a camera's image not had or not decoded, or a reading
/// task that did not end.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum CodesError {
    /// A color image was not had (transparent: the causes the
    /// command's exit status looks for are the [`CallError`]'s sources, not itself).
    #[error(transparent)]
    Call(#[from] CallError),
    /// A camera's image is not a PNG that decodes.
    #[error("reading codes from camera {serial}: decoding the PNG color image")]
    Decode {
        /// The camera.
        serial: String,
        /// Why.
        source: image::ImageError,
    },
    /// The task reading one image panicked or was cancelled.
    #[error("the code reading task failed")]
    Reading(#[source] tokio::task::JoinError),
    /// The task of one camera panicked or was cancelled.
    #[error("a code reading task failed")]
    Camera(#[source] tokio::task::JoinError),
}

/// Grabs a new PNG color image of camera `serial` and reads the codes in it.
async fn read_camera(client: &CamClient, serial: &str) -> Result<Vec<Code>, CodesError> {
    let png = client
        .grab(serial, Stream::Color, Some(ContentFormat::IMAGE_PNG))
        .await?
        .payload;
    tokio::task::spawn_blocking(move || {
        let image = image::load_from_memory_with_format(&png, image::ImageFormat::Png)?;
        Ok(read(&image.to_luma8()))
    })
    .await
    .map_err(CodesError::Reading)?
    .map_err(|source| CodesError::Decode {
        serial: serial.to_owned(),
        source,
    })
}

/// Reads the codes each camera (server, serial) sees in a new color image, all cameras
/// at once; each code once, with the cameras that read it.
pub async fn read_cameras(
    client: &CamClient,
    cameras: &[(SocketAddr, String)],
) -> Result<Vec<Seen>, CodesError> {
    let mut tasks = tokio::task::JoinSet::new();
    for (server, serial) in cameras.iter().cloned() {
        let one = CamClient::unicast(client, server);
        tasks.spawn(async move { read_camera(&one, &serial).await.map(|c| (serial, c)) });
    }
    let mut read = Vec::new();
    while let Some(done) = tasks.join_next().await {
        read.push(done.map_err(CodesError::Camera)??);
    }
    Ok(Seen::gather(read))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::client::ErrorResponse;

    /// A refusal wrapped in a [`CodesError`] keeps its [`ErrorResponse`] among the causes
    /// (where the command's exit status 3 finds it), and is said once.
    #[test]
    fn a_refusal_stays_among_the_causes() {
        let refused = super::super::check(
            "POST /cams/1/color",
            coap::Response::diagnostic(coap::Code::NOT_FOUND, "no camera"),
        )
        .expect_err("a 4.04");
        let e = CodesError::from(refused);
        let mut cause: Option<&(dyn std::error::Error + 'static)> = Some(&e);
        let mut found = false;
        while let Some(c) = cause {
            found |= c.is::<ErrorResponse>();
            cause = c.source();
        }
        assert!(found);
        assert_eq!(
            crate::error_text(&e),
            "POST /cams/1/color: 4.04 Not Found: no camera"
        );
    }
}
