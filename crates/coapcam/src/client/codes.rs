//! The codes on the parcel as the cameras see them (`measure --codes`, `demo`): a new color
//! image of every camera at once, read by [`crate::vision::codes`].

use std::net::SocketAddr;

use anyhow::Context as _;
use coap::ContentFormat;

use super::CamClient;
use crate::report::Seen;
use crate::repr::Stream;
use crate::vision::codes::{Code, read};

/// Grabs a new PNG color image of camera `serial` and reads the codes in it.
async fn read_camera(client: &CamClient, serial: &str) -> anyhow::Result<Vec<Code>> {
    let png = client
        .grab(serial, Stream::Color, Some(ContentFormat::IMAGE_PNG))
        .await?
        .payload;
    tokio::task::spawn_blocking(move || -> anyhow::Result<Vec<Code>> {
        let image = image::load_from_memory_with_format(&png, image::ImageFormat::Png)
            .context("decoding the PNG color image")?;
        Ok(read(&image.to_luma8()))
    })
    .await
    .context("the code reading task failed")?
    .with_context(|| format!("reading codes from camera {serial}"))
}

/// Reads the codes each camera (server, serial) sees in a new color image, all cameras
/// at once; each code once, with the cameras that read it.
pub async fn read_cameras(
    client: &CamClient,
    cameras: &[(SocketAddr, String)],
) -> anyhow::Result<Vec<Seen>> {
    let mut tasks = tokio::task::JoinSet::new();
    for (server, serial) in cameras.iter().cloned() {
        let one = CamClient::unicast(client, server);
        tasks.spawn(async move { read_camera(&one, &serial).await.map(|c| (serial, c)) });
    }
    let mut read = Vec::new();
    while let Some(done) = tasks.join_next().await {
        read.push(done.context("a code reading task failed")??);
    }
    Ok(Seen::gather(read))
}
