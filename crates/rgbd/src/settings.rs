//! The depth-settings and color-settings documents (thesis Listings A.1, A.2).
//!
//! ```json
//! { "format": "Z16", "fps": 30, "width": 1280, "height": 720 }
//! ```

use serde::{Deserialize, Serialize};

use crate::frame::{ColorFormat, DepthFormat};
use crate::mode::{ModeError, ModeTable, Stream};

/// Why a settings document was refused. `Display` is the 4.00 diagnostic.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum SettingsError {
    /// Not JSON of the expected shape (missing or unknown field, wrong type); the
    /// message names the field.
    #[error("{stream} settings: {}", crate::clip(.message, crate::MESSAGE_CHARS))]
    Json {
        /// "color" or "depth".
        stream: &'static str,
        /// serde_json's description, with line and column.
        message: String,
    },
    /// Well-formed, but the camera does not offer the mode.
    #[error(transparent)]
    Mode(#[from] ModeError),
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawSettings {
    format: String,
    fps: u32,
    width: u32,
    height: u32,
}

/// A sensor's pixel format as the settings documents name it: [`ColorFormat`] or
/// [`DepthFormat`].
pub trait SensorFormat: Copy {
    /// The sensor's stream.
    const STREAM: Stream;

    /// The name in the documents ("BGR8", "Z16").
    fn name(self) -> &'static str;

    /// The format called `name`, if `table` offers it.
    fn offered(table: &ModeTable, name: &str) -> Result<Self, ModeError>;
}

impl SensorFormat for ColorFormat {
    const STREAM: Stream = Stream::Color;

    fn name(self) -> &'static str {
        Self::name(self)
    }

    fn offered(table: &ModeTable, name: &str) -> Result<Self, ModeError> {
        table.color_format(name)
    }
}

impl SensorFormat for DepthFormat {
    const STREAM: Stream = Stream::Depth;

    fn name(self) -> &'static str {
        Self::name(self)
    }

    fn offered(table: &ModeTable, name: &str) -> Result<Self, ModeError> {
        table.depth_format(name)
    }
}

/// A sensor's settings: its format and mode ([`ColorSettings`], [`DepthSettings`]).
/// Deserializing reads a document without checking it against a camera's modes (a
/// client's copy of what a server holds); [`Settings::from_json`] checks it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Settings<F> {
    /// Pixel format.
    pub format: F,
    /// Frames per second.
    pub fps: u32,
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
}

/// Color sensor settings (Listing A.2).
pub type ColorSettings = Settings<ColorFormat>;

/// Depth sensor settings (Listing A.1).
pub type DepthSettings = Settings<DepthFormat>;

impl Default for ColorSettings {
    /// The thesis example: BGR8, 30 fps, 1280x720.
    fn default() -> Self {
        Self {
            format: ColorFormat::Bgr8,
            fps: 30,
            width: 1280,
            height: 720,
        }
    }
}

impl Default for DepthSettings {
    /// The thesis example and the D415's best depth mode: Z16, 30 fps, 1280x720.
    fn default() -> Self {
        Self {
            format: DepthFormat::Z16,
            fps: 30,
            width: 1280,
            height: 720,
        }
    }
}

impl<F: SensorFormat> Settings<F> {
    /// Parses a settings document and checks it against `table`.
    pub fn from_json(json: &[u8], table: &ModeTable) -> Result<Self, SettingsError> {
        let raw: RawSettings = serde_json::from_slice(json).map_err(|e| SettingsError::Json {
            stream: F::STREAM.name(),
            message: e.to_string(),
        })?;
        let settings = Self {
            format: F::offered(table, &raw.format)?,
            fps: raw.fps,
            width: raw.width,
            height: raw.height,
        };
        settings.validate(table)?;
        Ok(settings)
    }

    /// Checks the settings against `table`.
    pub fn validate(&self, table: &ModeTable) -> Result<(), ModeError> {
        F::offered(table, self.format.name())?;
        table.check(F::STREAM, self.width, self.height, self.fps)
    }

    /// The document in the key order of Listings A.1 and A.2, pretty-printed.
    pub fn to_json(&self) -> String {
        let Self {
            format,
            fps,
            width,
            height,
        } = self;
        format!(
            "{{\n  \"format\": \"{}\",\n  \"fps\": {fps},\n  \"width\": {width},\n  \"height\": {height}\n}}",
            format.name()
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn listing_a1_and_a2_round_trip() {
        let t = ModeTable::d415();
        let a1 = br#"{ "format": "Z16", "fps": 30, "width": 1280, "height": 720 }"#;
        let d = DepthSettings::from_json(a1, &t).unwrap();
        assert_eq!(d, DepthSettings::default());
        assert_eq!(
            DepthSettings::from_json(d.to_json().as_bytes(), &t).unwrap(),
            d
        );
        let a2 = br#"{ "format": "BGR8", "fps": 30, "width": 1280, "height": 720 }"#;
        let c = ColorSettings::from_json(a2, &t).unwrap();
        assert_eq!(c, ColorSettings::default());
        assert_eq!(
            ColorSettings::from_json(c.to_json().as_bytes(), &t).unwrap(),
            c
        );
    }

    #[test]
    fn missing_and_unknown_fields_are_named() {
        let t = ModeTable::d415();
        let e = DepthSettings::from_json(br#"{"format":"Z16","fps":30,"width":1280}"#, &t)
            .unwrap_err()
            .to_string();
        assert!(e.contains("height"), "{e}");
        let e = ColorSettings::from_json(
            br#"{"format":"RGB8","fps":30,"width":640,"height":480,"gain":3}"#,
            &t,
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("gain"), "{e}");
    }
}
