//! The application-config document (thesis Listing A.3): 2D and 3D regions of
//! interest, grab timeouts, ICP and the depth post-processing chain.

use std::time::Duration;

use geometry::{Point3, Roi3};
use rgbd::PostProcessingConfig;
use rgbd::filter::Roi2;
use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};
use serde_json::{Map, Value};

/// The keys of the document, all required in a PUT.
const KEYS: [&str; 6] = [
    "roi2d",
    "roi3d",
    "depth_grab_timeout_ms",
    "color_grab_timeout_ms",
    "icp",
    "postprocessing",
];

/// Longest grab timeout accepted, milliseconds.
const MAX_TIMEOUT_MS: u64 = 600_000;

/// A document that is not a valid application config; the text names the field and
/// what it accepts.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct AppConfigError(String);

/// A validated application config.
#[derive(Debug, Clone, PartialEq)]
pub struct AppConfig {
    /// Window of the images and of the depth pixels used for point clouds.
    pub roi2d: Roi2,
    /// Box of the points kept, in the output frame (after the 3D transformation).
    pub roi3d: Roi3,
    /// Longest wait for a depth frame.
    pub depth_grab_timeout_ms: u64,
    /// Longest wait for a color frame.
    pub color_grab_timeout_ms: u64,
    /// Register this camera's cloud with ICP in `/cams/pointclouds`.
    pub icp: bool,
    /// Depth filters run before deprojection.
    pub postprocessing: PostProcessingConfig,
}

impl Default for AppConfig {
    /// The whole of the largest frame, a box of ±100 m, 10 s timeouts (as the
    /// thesis listing), no ICP, no filters.
    fn default() -> Self {
        let roi3d = Roi3::new(
            Point3::new(-100.0, -100.0, -100.0),
            Point3::new(100.0, 100.0, 100.0),
        )
        .unwrap_or_else(|_| Roi3::everything());
        Self {
            roi2d: Roi2 {
                px: 0,
                py: 0,
                width: 1920,
                height: 1080,
            },
            roi3d,
            depth_grab_timeout_ms: 10_000,
            color_grab_timeout_ms: 10_000,
            icp: false,
            postprocessing: PostProcessingConfig::default(),
        }
    }
}

fn field<T: DeserializeOwned>(doc: &Map<String, Value>, key: &str) -> Result<T, AppConfigError> {
    let value = doc
        .get(key)
        .ok_or_else(|| AppConfigError(format!("{key} is missing")))?;
    serde_json::from_value(value.clone()).map_err(|e| AppConfigError(format!("{key}: {e}")))
}

fn timeout(doc: &Map<String, Value>, key: &str) -> Result<u64, AppConfigError> {
    let ms: u64 = field(doc, key)?;
    if (1..=MAX_TIMEOUT_MS).contains(&ms) {
        Ok(ms)
    } else {
        Err(AppConfigError(format!(
            "{key} = {ms} is not allowed: an integer from 1 to {MAX_TIMEOUT_MS} (milliseconds)"
        )))
    }
}

impl Serialize for AppConfig {
    /// The document: `icp` as 0 or 1, the post-processing stages as 0, 1 or their
    /// parameters.
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        #[derive(Serialize)]
        struct Document<'a> {
            roi2d: &'a Roi2,
            roi3d: &'a Roi3,
            depth_grab_timeout_ms: u64,
            color_grab_timeout_ms: u64,
            icp: u8,
            postprocessing: &'a PostProcessingConfig,
        }
        Document {
            roi2d: &self.roi2d,
            roi3d: &self.roi3d,
            depth_grab_timeout_ms: self.depth_grab_timeout_ms,
            color_grab_timeout_ms: self.color_grab_timeout_ms,
            icp: u8::from(self.icp),
            postprocessing: &self.postprocessing,
        }
        .serialize(s)
    }
}

impl<'de> Deserialize<'de> for AppConfig {
    /// A complete document, validated as [`AppConfig::from_json`] does.
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let doc = Map::<String, Value>::deserialize(d)?;
        Self::from_map(&doc).map_err(serde::de::Error::custom)
    }
}

impl AppConfig {
    /// Parses and validates a complete document.
    pub fn from_json(json: &[u8]) -> Result<Self, AppConfigError> {
        let doc: Map<String, Value> = serde_json::from_slice(json)
            .map_err(|e| AppConfigError(format!("not a JSON object: {e}")))?;
        Self::from_map(&doc)
    }

    /// Validates a complete document, read field by field so that an error names its
    /// field.
    fn from_map(doc: &Map<String, Value>) -> Result<Self, AppConfigError> {
        if let Some(unknown) = doc.keys().find(|k| !KEYS.contains(&k.as_str())) {
            return Err(AppConfigError(format!(
                "unknown field {unknown:?}; the fields are {}",
                KEYS.join(", ")
            )));
        }
        let roi2d: Roi2 = field(doc, "roi2d")?;
        if roi2d.width == 0 || roi2d.height == 0 {
            return Err(AppConfigError(
                "roi2d.width and roi2d.height must be at least 1 pixel".to_string(),
            ));
        }
        let roi3d: Roi3 = field(doc, "roi3d")?;
        let icp = match field::<u64>(doc, "icp")? {
            0 => false,
            1 => true,
            other => {
                return Err(AppConfigError(format!(
                    "icp = {other} is not allowed: 0 (off) or 1 (on)"
                )));
            }
        };
        let postprocessing = doc
            .get("postprocessing")
            .ok_or_else(|| AppConfigError("postprocessing is missing".to_string()))
            .and_then(|v| {
                PostProcessingConfig::from_json(v.to_string().as_bytes())
                    .and_then(|c| c.validate().map(|()| c))
                    .map_err(|e| AppConfigError(e.to_string()))
            })?;
        Ok(Self {
            roi2d,
            roi3d,
            depth_grab_timeout_ms: timeout(doc, "depth_grab_timeout_ms")?,
            color_grab_timeout_ms: timeout(doc, "color_grab_timeout_ms")?,
            icp,
            postprocessing,
        })
    }

    /// The document, with the keys of Listing A.3, pretty-printed.
    pub fn to_json(&self) -> String {
        // Every field is a struct of numbers or a number: serializing cannot fail.
        serde_json::to_string_pretty(self).unwrap_or_default()
    }

    /// The depth grab timeout.
    pub fn depth_timeout(&self) -> Duration {
        Duration::from_millis(self.depth_grab_timeout_ms)
    }

    /// The color grab timeout.
    pub fn color_timeout(&self) -> Duration {
        Duration::from_millis(self.color_grab_timeout_ms)
    }

    /// Checks that `roi2d` overlaps each of `frames` (a stream's name, its width and
    /// height: the frames the camera sends now), so that no grab refuses it later.
    pub fn check_frames(&self, frames: &[(&str, u32, u32)]) -> Result<(), AppConfigError> {
        let r = self.roi2d;
        for &(stream, width, height) in frames {
            if r.px >= width || r.py >= height {
                let (key, value, limit) = if r.px >= width {
                    ("px", r.px, width)
                } else {
                    ("py", r.py, height)
                };
                return Err(AppConfigError(format!(
                    "roi2d.{key} = {value} lies outside the {width}x{height} {stream} frame: it must be below {limit}"
                )));
            }
        }
        Ok(())
    }

    /// `roi2d` clipped to a `width` x `height` frame; `None` when they do not overlap.
    pub fn roi_in(&self, width: u32, height: u32) -> Option<Roi2> {
        let r = self.roi2d;
        (r.px < width && r.py < height).then(|| Roi2 {
            px: r.px,
            py: r.py,
            width: r.width.min(width - r.px),
            height: r.height.min(height - r.py),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const LISTING_A3: &str = r#"{
        "roi2d": {"px": 0, "py": 0, "width": 1280, "height": 720},
        "roi3d": {"min_x": -0.25, "max_x": 0.25, "min_y": -0.25, "max_y": 0.25,
                  "min_z": 0.1, "max_z": 0.3},
        "depth_grab_timeout_ms": 10000, "color_grab_timeout_ms": 10000, "icp": 1,
        "postprocessing": {"decimation": 1, "spatial": 1, "holefilling": 0}
    }"#;

    #[test]
    fn thesis_listing_round_trips() {
        let c = AppConfig::from_json(LISTING_A3.as_bytes()).expect("listing A.3");
        assert!(c.icp);
        assert!(c.postprocessing.decimation.is_some() && c.postprocessing.holefilling.is_none());
        let again = AppConfig::from_json(c.to_json().as_bytes()).expect("own output");
        assert_eq!(again, c);
        assert_eq!(
            AppConfig::from_json(AppConfig::default().to_json().as_bytes()),
            Ok(AppConfig::default())
        );
    }

    #[test]
    fn errors_name_the_field() {
        let bad = |from: &str, to: &str| {
            AppConfig::from_json(LISTING_A3.replace(from, to).as_bytes())
                .expect_err("invalid")
                .to_string()
        };
        assert!(bad("\"icp\": 1", "\"icp\": 2").contains("icp = 2"));
        assert!(
            bad(
                "\"depth_grab_timeout_ms\": 10000",
                "\"depth_grab_timeout_ms\": 0"
            )
            .contains("depth_grab_timeout_ms")
        );
        assert!(bad("\"min_z\": 0.1", "\"min_z\": 0.5").contains("roi3d"));
        assert!(bad("\"px\": 0,", "").contains("roi2d"));
        assert!(bad("\"icp\": 1", "\"icq\": 1").contains("icq"));
        assert!(bad("\"width\": 1280", "\"width\": 0").contains("roi2d.width"));
    }

    #[test]
    fn roi_is_clipped_to_the_frame() {
        let c = AppConfig::default();
        assert_eq!(
            c.roi_in(640, 480).map(|r| (r.width, r.height)),
            Some((640, 480))
        );
        let mut off = c;
        off.roi2d.px = 700;
        assert_eq!(off.roi_in(640, 480), None);
    }
}
