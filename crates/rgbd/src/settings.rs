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

fn parse_raw(stream: Stream, json: &[u8]) -> Result<RawSettings, SettingsError> {
    serde_json::from_slice(json).map_err(|e| SettingsError::Json {
        stream: stream.name(),
        message: e.to_string(),
    })
}

/// Color sensor settings (Listing A.2).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize)]
pub struct ColorSettings {
    /// Pixel format.
    pub format: ColorFormat,
    /// Frames per second.
    pub fps: u32,
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
}

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

impl ColorSettings {
    /// Parses a color-settings document and checks it against `table`.
    pub fn from_json(json: &[u8], table: &ModeTable) -> Result<Self, SettingsError> {
        let raw = parse_raw(Stream::Color, json)?;
        let settings = Self {
            format: table.color_format(&raw.format)?,
            fps: raw.fps,
            width: raw.width,
            height: raw.height,
        };
        settings.validate(table)?;
        Ok(settings)
    }

    /// Checks the settings against `table`.
    pub fn validate(&self, table: &ModeTable) -> Result<(), ModeError> {
        table.color_format(self.format.name())?;
        table.check(Stream::Color, self.width, self.height, self.fps)
    }

    /// The document in the key order of Listing A.2, pretty-printed.
    pub fn to_json(&self) -> String {
        settings_json(self.format.name(), self.fps, self.width, self.height)
    }
}

/// Depth sensor settings (Listing A.1).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize)]
pub struct DepthSettings {
    /// Pixel format (Z16).
    pub format: DepthFormat,
    /// Frames per second.
    pub fps: u32,
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
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

impl DepthSettings {
    /// Parses a depth-settings document and checks it against `table`.
    pub fn from_json(json: &[u8], table: &ModeTable) -> Result<Self, SettingsError> {
        let raw = parse_raw(Stream::Depth, json)?;
        let settings = Self {
            format: table.depth_format(&raw.format)?,
            fps: raw.fps,
            width: raw.width,
            height: raw.height,
        };
        settings.validate(table)?;
        Ok(settings)
    }

    /// Checks the settings against `table`.
    pub fn validate(&self, table: &ModeTable) -> Result<(), ModeError> {
        table.depth_format(self.format.name())?;
        table.check(Stream::Depth, self.width, self.height, self.fps)
    }

    /// The document in the key order of Listing A.1, pretty-printed.
    pub fn to_json(&self) -> String {
        settings_json(self.format.name(), self.fps, self.width, self.height)
    }
}

fn settings_json(format: &str, fps: u32, width: u32, height: u32) -> String {
    format!(
        "{{\n  \"format\": \"{format}\",\n  \"fps\": {fps},\n  \"width\": {width},\n  \"height\": {height}\n}}"
    )
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
