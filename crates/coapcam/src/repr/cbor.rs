//! Reading the server's CBOR maps (DESIGN.md §5): fields by name, and point clouds with
//! the serials of the cameras that made them.

use anyhow::{Context as _, bail};
use geometry::PointCloud;

use crate::packet;

/// A CBOR map's entries.
type Map = [(ciborium::Value, ciborium::Value)];

/// A field of a CBOR map.
pub(crate) fn field<'a>(map: &'a Map, key: &str) -> anyhow::Result<&'a ciborium::Value> {
    map.iter()
        .find(|(k, _)| k.as_text() == Some(key))
        .map(|(_, v)| v)
        .with_context(|| format!("the CBOR map has no {key:?}"))
}

pub(crate) fn floats<const N: usize>(value: &ciborium::Value) -> anyhow::Result<[f32; N]> {
    let items = value.as_array().context("expected an array of numbers")?;
    let mut out = [0.0; N];
    if items.len() != N {
        bail!("expected {N} numbers, found {}", items.len());
    }
    for (o, v) in out.iter_mut().zip(items) {
        *o = v.as_float().context("expected a number")? as f32;
    }
    Ok(out)
}

pub(crate) fn u32_of(map: &Map, key: &str) -> anyhow::Result<u32> {
    let v = field(map, key)?
        .as_integer()
        .with_context(|| format!("{key} is not an integer"))?;
    u32::try_from(v).with_context(|| format!("{key} is out of range"))
}

/// A point cloud from its CBOR map, with the cameras that made it (`serial`, or
/// `serials` of a merged cloud) and its timestamp.
pub(crate) struct Cloud {
    pub(crate) cloud: PointCloud,
    pub(crate) serials: Vec<String>,
    pub(crate) timestamp_us: u64,
}

impl Cloud {
    /// Reads the CBOR point-cloud map, checking `points` against the data.
    pub(crate) fn from_cbor(body: &[u8]) -> anyhow::Result<Self> {
        let value: ciborium::Value =
            ciborium::from_reader(body).context("decoding the CBOR point cloud")?;
        let map = value
            .as_map()
            .context("the CBOR point cloud is not a map")?;
        let data = field(map, "data")?
            .as_bytes()
            .context("data is not bytes")?;
        let count = u32_of(map, "points")? as usize;
        if count.checked_mul(12) != Some(data.len()) {
            bail!(
                "{count} points announced, {} bytes of points arrived",
                data.len()
            );
        }
        let text = |v: &ciborium::Value| {
            v.as_text()
                .map(str::to_owned)
                .context("a serial is not text")
        };
        let serials = match field(map, "serials") {
            Ok(list) => list
                .as_array()
                .context("serials is not an array")?
                .iter()
                .map(text)
                .collect::<anyhow::Result<_>>()?,
            Err(_) => vec![text(field(map, "serial")?)?],
        };
        let timestamp_us = field(map, "timestamp_us")?
            .as_integer()
            .and_then(|v| u64::try_from(v).ok())
            .context("timestamp_us is not a count of microseconds")?;
        Ok(Self {
            cloud: packet::points(data),
            serials,
            timestamp_us,
        })
    }
}
