//! The codes on the parcel as the cameras see them (`measure --codes`, `demo`): a new color
//! image of every camera at once, read by [`crate::vision::codes`].

use std::collections::BTreeMap;
use std::net::SocketAddr;

use anyhow::Context as _;
use coap::ContentFormat;

use super::CamClient;
use crate::repr::Stream;
use crate::vision::codes::{Code, read};

/// A code and the cameras that read it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Seen {
    /// The code.
    pub code: Code,
    /// Serials of the cameras whose image it was read from.
    pub cameras: Vec<String>,
}

impl Seen {
    /// The entry of the `codes` array of `measure --json`.
    pub fn to_json(&self) -> serde_json::Value {
        serde_json::json!({
            "kind": self.code.kind.name(),
            "text": self.code.text,
            "cameras": self.cameras,
        })
    }
}

/// The codes one line of text names: `qr "PKG-0001" (840412060746, ...)`, or `none`.
pub fn describe(seen: &[Seen]) -> String {
    if seen.is_empty() {
        return "none".into();
    }
    let each: Vec<String> = seen
        .iter()
        .map(|s| format!("{} ({})", s.code, s.cameras.join(", ")))
        .collect();
    each.join(", ")
}

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
    let mut seen: BTreeMap<Code, Vec<String>> = BTreeMap::new();
    while let Some(done) = tasks.join_next().await {
        let (serial, codes) = done.context("a code reading task failed")??;
        for code in codes {
            seen.entry(code).or_default().push(serial.clone());
        }
    }
    Ok(seen
        .into_iter()
        .map(|(code, mut cameras)| {
            cameras.sort();
            Seen { code, cameras }
        })
        .collect())
}
