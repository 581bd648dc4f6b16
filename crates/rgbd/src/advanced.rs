//! The advanced-config document (thesis Listing A.5): the D400 advanced-mode JSON
//! that librealsense's `rs2_load_json` loads and realsense-viewer exports.
//!
//! A document is a flat JSON object of key -> string. Keys are checked against the
//! D400 advanced-mode key set of librealsense's JSON loader; values are checked by
//! kind (number, `"True"`/`"False"`, laser state, stream format). A document sent to
//! a camera may be partial: like `rs2_load_json`, only the given keys change. The
//! newer `{"parameters": {...}}` wrapper that realsense-viewer writes is accepted too;
//! next to `parameters` only its `device` and `schema version` keys may appear (ignored).
//!
//! Key spellings: a camera answers with the 92 keys of Listing A.5, spelled as
//! librealsense spells them. Four keys of the thesis listing are spelled differently
//! there (`param-medianthresha`, `param-lambdaacensus`, `param-censusvsiz`,
//! `param-rauminssum`); they are accepted as aliases of `param-medianthreshold`,
//! `param-lambdacensus`, `param-censusvsize` and `param-rauminnssum`, so the listing
//! as printed loads.

use std::collections::BTreeMap;
use std::fmt;

use crate::settings::DepthSettings;

/// What a value must look like.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Kind {
    /// A decimal number (librealsense parses it with `atof`).
    Number,
    /// An integer in an inclusive range.
    Integer { min: i64, max: i64 },
    /// `"True"` or `"False"`.
    Bool,
    /// `"off"`, `"on"` or `"auto"`.
    Laser,
    /// A depth stream format name (`"Z16"`).
    DepthFormat,
}

impl Kind {
    fn accepts(self, value: &str) -> bool {
        match self {
            Self::Number => value.trim().parse::<f64>().is_ok_and(f64::is_finite),
            Self::Integer { min, max } => value
                .trim()
                .parse::<i64>()
                .is_ok_and(|v| (min..=max).contains(&v)),
            Self::Bool => matches!(value, "True" | "False"),
            Self::Laser => matches!(value, "off" | "on" | "auto"),
            Self::DepthFormat => value == "Z16",
        }
    }

    fn expected(self) -> String {
        match self {
            Self::Number => "a decimal number such as \"400\" or \"0.375\"".to_owned(),
            Self::Integer { min, max } => format!("an integer from {min} to {max}"),
            Self::Bool => "\"True\" or \"False\"".to_owned(),
            Self::Laser => "\"off\", \"on\" or \"auto\"".to_owned(),
            Self::DepthFormat => "\"Z16\"".to_owned(),
        }
    }
}

const DIMENSION: Kind = Kind::Integer {
    min: 1,
    max: 65_535,
};

/// Micrometres per depth unit; librealsense's depth-units option spans 1e-6 .. 1e-2 m.
const UNITS: Kind = Kind::Integer {
    min: 1,
    max: 10_000,
};

/// The keys a D400 camera reports, with their kinds (the key set of Listing A.5).
const KEYS: &[(&str, Kind)] = &[
    ("aux-param-autoexposure-setpoint", Kind::Number),
    ("aux-param-colorcorrection1", Kind::Number),
    ("aux-param-colorcorrection10", Kind::Number),
    ("aux-param-colorcorrection11", Kind::Number),
    ("aux-param-colorcorrection12", Kind::Number),
    ("aux-param-colorcorrection2", Kind::Number),
    ("aux-param-colorcorrection3", Kind::Number),
    ("aux-param-colorcorrection4", Kind::Number),
    ("aux-param-colorcorrection5", Kind::Number),
    ("aux-param-colorcorrection6", Kind::Number),
    ("aux-param-colorcorrection7", Kind::Number),
    ("aux-param-colorcorrection8", Kind::Number),
    ("aux-param-colorcorrection9", Kind::Number),
    ("aux-param-depthclampmax", Kind::Number),
    ("aux-param-depthclampmin", Kind::Number),
    ("aux-param-disparityshift", Kind::Number),
    ("controls-autoexposure-auto", Kind::Bool),
    ("controls-autoexposure-manual", Kind::Number),
    ("controls-color-autoexposure-auto", Kind::Bool),
    ("controls-color-autoexposure-manual", Kind::Number),
    ("controls-color-backlight-compensation", Kind::Number),
    ("controls-color-brightness", Kind::Number),
    ("controls-color-contrast", Kind::Number),
    ("controls-color-gain", Kind::Number),
    ("controls-color-gamma", Kind::Number),
    ("controls-color-hue", Kind::Number),
    ("controls-color-power-line-frequency", Kind::Number),
    ("controls-color-saturation", Kind::Number),
    ("controls-color-sharpness", Kind::Number),
    ("controls-color-white-balance-auto", Kind::Bool),
    ("controls-color-white-balance-manual", Kind::Number),
    ("controls-depth-gain", Kind::Number),
    ("controls-depth-white-balance-auto", Kind::Bool),
    ("controls-laserpower", Kind::Number),
    ("controls-laserstate", Kind::Laser),
    ("ignoreSAD", Kind::Number),
    ("param-autoexposure-setpoint", Kind::Number),
    ("param-censusenablereg-udiameter", Kind::Number),
    ("param-censusenablereg-vdiameter", Kind::Number),
    ("param-censususize", Kind::Number),
    ("param-censusvsize", Kind::Number),
    ("param-depthclampmax", Kind::Number),
    ("param-depthclampmin", Kind::Number),
    ("param-depthunits", UNITS),
    ("param-disableraucolor", Kind::Number),
    ("param-disablesadcolor", Kind::Number),
    ("param-disablesadnormalize", Kind::Number),
    ("param-disablesloleftcolor", Kind::Number),
    ("param-disableslorightcolor", Kind::Number),
    ("param-disparitymode", Kind::Number),
    ("param-disparityshift", Kind::Number),
    ("param-lambdaad", Kind::Number),
    ("param-lambdacensus", Kind::Number),
    ("param-leftrightthreshold", Kind::Number),
    ("param-maxscorethreshb", Kind::Number),
    ("param-medianthreshold", Kind::Number),
    ("param-minscorethresha", Kind::Number),
    ("param-neighborthresh", Kind::Number),
    ("param-raumine", Kind::Number),
    ("param-rauminn", Kind::Number),
    ("param-rauminnssum", Kind::Number),
    ("param-raumins", Kind::Number),
    ("param-rauminw", Kind::Number),
    ("param-rauminwesum", Kind::Number),
    ("param-regioncolorthresholdb", Kind::Number),
    ("param-regioncolorthresholdg", Kind::Number),
    ("param-regioncolorthresholdr", Kind::Number),
    ("param-regionshrinku", Kind::Number),
    ("param-regionshrinkv", Kind::Number),
    ("param-robbinsmonrodecrement", Kind::Number),
    ("param-robbinsmonroincrement", Kind::Number),
    ("param-rsmdiffthreshold", Kind::Number),
    ("param-rsmrauslodiffthreshold", Kind::Number),
    ("param-rsmremovethreshold", Kind::Number),
    ("param-scanlineedgetaub", Kind::Number),
    ("param-scanlineedgetaug", Kind::Number),
    ("param-scanlineedgetaur", Kind::Number),
    ("param-scanlinep1", Kind::Number),
    ("param-scanlinep1onediscon", Kind::Number),
    ("param-scanlinep1twodiscon", Kind::Number),
    ("param-scanlinep2", Kind::Number),
    ("param-scanlinep2onediscon", Kind::Number),
    ("param-scanlinep2twodiscon", Kind::Number),
    ("param-secondpeakdelta", Kind::Number),
    ("param-texturecountthresh", Kind::Number),
    ("param-texturedifferencethresh", Kind::Number),
    ("param-usersm", Kind::Number),
    ("param-zunits", UNITS),
    ("stream-depth-format", Kind::DepthFormat),
    ("stream-fps", DIMENSION),
    ("stream-height", DIMENSION),
    ("stream-width", DIMENSION),
];

/// Other spellings librealsense (or the thesis listing) accepts for a reported key.
const ALIASES: &[(&str, &str)] = &[
    ("param-medianthresha", "param-medianthreshold"),
    ("param-lambdaacensus", "param-lambdacensus"),
    ("param-censusvsiz", "param-censusvsize"),
    ("param-rauminssum", "param-rauminnssum"),
    ("param-colorcorrection1", "aux-param-colorcorrection1"),
    ("param-colorcorrection2", "aux-param-colorcorrection2"),
    ("param-colorcorrection3", "aux-param-colorcorrection3"),
    ("param-colorcorrection4", "aux-param-colorcorrection4"),
    ("param-colorcorrection5", "aux-param-colorcorrection5"),
    ("param-colorcorrection6", "aux-param-colorcorrection6"),
    ("param-colorcorrection7", "aux-param-colorcorrection7"),
    ("param-colorcorrection8", "aux-param-colorcorrection8"),
    ("param-colorcorrection9", "aux-param-colorcorrection9"),
    ("param-colorcorrection10", "aux-param-colorcorrection10"),
    ("param-colorcorrection11", "aux-param-colorcorrection11"),
    ("param-colorcorrection12", "aux-param-colorcorrection12"),
];

/// Keys librealsense's D400 loader accepts and ignores (the D415 has no such control).
const IGNORED: &[&str] = &[
    "param-regionspatialthresholdu",
    "param-regionspatialthresholdv",
    "param-amplitude-factor",
    "aux-param-disparitymultiplier",
    "stream-ir-format",
    "result",
    "result:",
];

/// Reported keys that set the same device field; setting one sets the others.
const SAME_FIELD: &[(&str, &str)] = &[
    ("param-depthunits", "param-zunits"),
    ("param-depthclampmin", "aux-param-depthclampmin"),
    ("param-depthclampmax", "aux-param-depthclampmax"),
    ("param-disparityshift", "aux-param-disparityshift"),
    (
        "param-autoexposure-setpoint",
        "aux-param-autoexposure-setpoint",
    ),
    ("param-censusenablereg-udiameter", "param-censususize"),
    ("param-censusenablereg-vdiameter", "param-censusvsize"),
];

/// The reported spelling of `key` and its kind.
fn lookup(key: &str) -> Option<(&'static str, Kind)> {
    let canon = ALIASES
        .iter()
        .find(|(a, _)| *a == key)
        .map_or(key, |&(_, c)| c);
    KEYS.iter().find(|(k, _)| *k == canon).copied()
}

fn same_field(key: &str) -> Option<&'static str> {
    SAME_FIELD.iter().find_map(|&(a, b)| {
        if a == key {
            Some(b)
        } else if b == key {
            Some(a)
        } else {
            None
        }
    })
}

/// The keys realsense-viewer writes next to `parameters` (only `parameters` is read).
const WRAPPER_KEYS: [&str; 2] = ["device", "schema version"];

/// Why an advanced-config document was refused. `Display` is the 4.00 diagnostic.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum AdvancedError {
    /// Not valid JSON.
    #[error("advanced-config: not JSON: {0}")]
    Json(String),
    /// Valid JSON but not an object of key -> string (or `parameters` is not one).
    #[error("advanced-config: the document must be a JSON object of key -> string")]
    NotAnObject,
    /// A top-level key next to `parameters` other than `device` and `schema version`.
    #[error(
        "advanced-config: \"{}\" next to \"parameters\" is not allowed; allowed: \"device\", \"schema version\"",
        crate::echo(.0)
    )]
    UnknownWrapperKey(String),
    /// A key outside the D400 advanced-mode key set.
    #[error("advanced-config: \"{}\" is not a D400 advanced-mode key", crate::echo(.0))]
    UnknownKey(String),
    /// A value that is not a JSON string.
    #[error(
        "advanced-config: value of \"{}\" must be a JSON string such as \"400\"",
        crate::echo(.0)
    )]
    NotAString(String),
    /// A value of the wrong shape or range.
    #[error(
        "advanced-config: \"{}\" = \"{}\" is not allowed; expected {expected}",
        crate::echo(.key),
        crate::echo(.value)
    )]
    BadValue {
        /// The key.
        key: String,
        /// The refused value.
        value: String,
        /// What the key takes.
        expected: String,
    },
    /// Two spellings of the same device field with different values.
    #[error("advanced-config: \"{key}\" and \"{other}\" set the same field to different values")]
    Conflict {
        /// One key.
        key: String,
        /// The other key.
        other: String,
    },
    /// A preset name that does not exist.
    #[error(
        "unknown visual preset \"{}\"; allowed: {names}",
        crate::echo(.0),
        names = VisualPreset::names()
    )]
    UnknownPreset(String),
}

/// An advanced-config document: validated keys (in librealsense's spelling) -> string
/// values. Complete when it comes from a camera or a preset, possibly partial when it
/// comes from a client.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct AdvancedConfig {
    values: BTreeMap<&'static str, String>,
}

impl AdvancedConfig {
    /// Parses and validates a document.
    pub fn from_json(json: &[u8]) -> Result<Self, AdvancedError> {
        let doc: serde_json::Value =
            serde_json::from_slice(json).map_err(|e| AdvancedError::Json(e.to_string()))?;
        let serde_json::Value::Object(mut map) = doc else {
            return Err(AdvancedError::NotAnObject);
        };
        // realsense-viewer's newer wrapper: {"device": {...}, "parameters": {...}, "schema version": 1}
        if let Some(params) = map.remove("parameters") {
            let serde_json::Value::Object(params) = params else {
                return Err(AdvancedError::NotAnObject);
            };
            if let Some(key) = map.keys().find(|k| !WRAPPER_KEYS.contains(&k.as_str())) {
                return Err(AdvancedError::UnknownWrapperKey(key.clone()));
            }
            map = params;
        }
        let mut config = Self::default();
        // Which spelling set each device field in this document, to catch two
        // spellings of one field with different values.
        let mut set_by: BTreeMap<&'static str, (String, String)> = BTreeMap::new();
        for (key, value) in map {
            let serde_json::Value::String(value) = value else {
                return Err(AdvancedError::NotAString(key));
            };
            let Some(canon) = config.set(&key, &value)? else {
                continue;
            };
            for field in std::iter::once(canon).chain(same_field(canon)) {
                if let Some((other, earlier)) = set_by.get(field)
                    && *earlier != value
                {
                    return Err(AdvancedError::Conflict {
                        key,
                        other: other.clone(),
                    });
                }
            }
            set_by.insert(canon, (key, value));
        }
        Ok(config)
    }

    /// Sets one key (any accepted spelling) after checking it and its value, and
    /// returns the key as the camera reports it. Keys the D415 ignores are accepted
    /// and dropped (`Ok(None)`).
    pub fn set(&mut self, key: &str, value: &str) -> Result<Option<&'static str>, AdvancedError> {
        if IGNORED.contains(&key) {
            return Ok(None);
        }
        let (canon, kind) = lookup(key).ok_or_else(|| AdvancedError::UnknownKey(key.to_owned()))?;
        if !kind.accepts(value) {
            return Err(AdvancedError::BadValue {
                key: key.to_owned(),
                value: value.to_owned(),
                expected: kind.expected(),
            });
        }
        self.values.insert(canon, value.to_owned());
        if let Some(other) = same_field(canon) {
            self.values.insert(other, value.to_owned());
        }
        Ok(Some(canon))
    }

    /// The value of `key` (librealsense's spelling), if the document has it.
    pub fn get(&self, key: &str) -> Option<&str> {
        self.values.get(key).map(String::as_str)
    }

    /// Number of keys.
    pub fn len(&self) -> usize {
        self.values.len()
    }

    /// True when the document has no keys.
    pub fn is_empty(&self) -> bool {
        self.values.is_empty()
    }

    /// True when every key a D400 camera reports is present.
    pub fn is_complete(&self) -> bool {
        self.values.len() == KEYS.len()
    }

    /// Keys and values in key order.
    pub fn iter(&self) -> impl Iterator<Item = (&'static str, &str)> + '_ {
        self.values.iter().map(|(k, v)| (*k, v.as_str()))
    }

    /// Applies `update` on top of this document (keys of `update` win).
    pub fn merge(&mut self, update: &Self) {
        for (k, v) in &update.values {
            self.values.insert(k, v.clone());
        }
    }

    /// Sets the stream keys to describe the depth mode of `depth`.
    pub(crate) fn set_depth_mode(&mut self, depth: &DepthSettings) -> Result<(), AdvancedError> {
        for (key, value) in [
            ("stream-depth-format", depth.format.name().to_owned()),
            ("stream-fps", depth.fps.to_string()),
            ("stream-width", depth.width.to_string()),
            ("stream-height", depth.height.to_string()),
        ] {
            self.set(key, &value)?;
        }
        Ok(())
    }

    /// `depth` with fps, width and height taken from the stream keys where this
    /// document has them as numbers (not validated).
    pub(crate) fn depth_mode(&self, mut depth: DepthSettings) -> DepthSettings {
        let number = |key: &str, current: u32| {
            self.get(key)
                .and_then(|v| v.trim().parse::<u32>().ok())
                .unwrap_or(current)
        };
        depth.fps = number("stream-fps", depth.fps);
        depth.width = number("stream-width", depth.width);
        depth.height = number("stream-height", depth.height);
        depth
    }

    /// Micrometres per depth unit (`param-depthunits`), if present.
    pub fn depth_units_um(&self) -> Option<u32> {
        self.get("param-depthunits")
            .and_then(|v| v.trim().parse().ok())
    }

    /// The document as pretty-printed JSON with keys in order (as Listing A.5).
    pub fn to_json(&self) -> String {
        let mut out = String::from("{\n");
        let n = self.values.len();
        for (i, (k, v)) in self.values.iter().enumerate() {
            let key = serde_json::Value::String((*k).to_owned());
            let value = serde_json::Value::String(v.clone());
            out.push_str(&format!("  {key}: {value}"));
            out.push_str(if i + 1 < n { ",\n" } else { "\n" });
        }
        out.push('}');
        out
    }

    /// The complete document of a visual preset.
    pub fn preset(preset: VisualPreset) -> Self {
        let mut config = Self::default();
        for (key, value) in DEFAULT_D415.iter().chain(preset.overrides()) {
            config.insert_raw(key, *value);
        }
        for (key, value) in D415_STRINGS {
            config.values.insert(key, (*value).to_owned());
        }
        config
    }

    /// Inserts a firmware value of a preset table, converted to its JSON form as
    /// librealsense's writer does (scales, the inverted RSM bypass, 6 significant digits).
    fn insert_raw(&mut self, key: &'static str, raw: f64) {
        let json_value = match key {
            "param-rsmremovethreshold" => raw / 168.0,
            "param-regioncolorthresholdb"
            | "param-regioncolorthresholdg"
            | "param-regioncolorthresholdr" => raw / 1022.0,
            "param-usersm" => f64::from(u8::from(raw <= 0.0)),
            _ => raw,
        };
        let text = format_g6(json_value);
        self.values.insert(key, text.clone());
        if let Some(other) = same_field(key) {
            self.values.insert(other, text);
        }
    }
}

impl fmt::Display for AdvancedConfig {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.to_json())
    }
}

/// Formats like a C++ `std::ostream` with its default precision (`%g`, 6 significant
/// digits), which is how librealsense writes advanced-mode values: `%e` rounding to 6
/// digits decides the exponent X; for -4 <= X < 6 fixed notation, otherwise
/// `d.ddddde±XX`; trailing zeros (and a trailing point) removed. Non-finite values
/// (never in a preset table) print as Rust prints them.
fn format_g6(v: f64) -> String {
    const PRECISION: i32 = 6;
    if v == 0.0 {
        return "0".to_owned();
    }
    if !v.is_finite() {
        return format!("{v}");
    }
    let scientific = format!("{v:.*e}", (PRECISION - 1) as usize);
    let Some((mantissa, exponent)) = scientific.split_once('e') else {
        return scientific;
    };
    let Ok(exponent) = exponent.parse::<i32>() else {
        return scientific;
    };
    if (-4..PRECISION).contains(&exponent) {
        // exponent is in -4..=5, so decimals is in 0..=9.
        let decimals = (PRECISION - 1 - exponent) as usize;
        trim_zeros(&format!("{v:.decimals$}")).to_owned()
    } else {
        let sign = if exponent < 0 { '-' } else { '+' };
        format!("{}e{sign}{:02}", trim_zeros(mantissa), exponent.abs())
    }
}

/// `1.500` -> `1.5`, `2.000` -> `2`; text without a decimal point is returned as is.
fn trim_zeros(text: &str) -> &str {
    if text.contains('.') {
        text.trim_end_matches('0').trim_end_matches('.')
    } else {
        text
    }
}

/// The D400 visual presets (`rs2_rs400_visual_preset`) a D415 offers.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum VisualPreset {
    /// The camera's power-on values.
    Default,
    /// Tuned for hands and gestures.
    Hand,
    /// Fewer but more confident depth values; the usual choice for dimensioning.
    HighAccuracy,
    /// More depth values, more outliers.
    HighDensity,
    /// Between High Accuracy and High Density.
    MediumDensity,
    /// Color correction that removes the projector pattern from the IR images.
    RemoveIrPattern,
}

impl VisualPreset {
    /// Every preset.
    pub const ALL: [Self; 6] = [
        Self::Default,
        Self::Hand,
        Self::HighAccuracy,
        Self::HighDensity,
        Self::MediumDensity,
        Self::RemoveIrPattern,
    ];

    /// The name realsense-viewer shows ("High Accuracy", ...).
    pub fn name(self) -> &'static str {
        match self {
            Self::Default => "Default",
            Self::Hand => "Hand",
            Self::HighAccuracy => "High Accuracy",
            Self::HighDensity => "High Density",
            Self::MediumDensity => "Medium Density",
            Self::RemoveIrPattern => "Remove IR Pattern",
        }
    }

    /// Looks a preset up by [`VisualPreset::name`] (case-insensitive).
    pub fn from_name(name: &str) -> Result<Self, AdvancedError> {
        Self::ALL
            .into_iter()
            .find(|p| p.name().eq_ignore_ascii_case(name.trim()))
            .ok_or_else(|| AdvancedError::UnknownPreset(name.to_owned()))
    }

    fn names() -> String {
        Self::ALL
            .iter()
            .map(|p| p.name())
            .collect::<Vec<_>>()
            .join(", ")
    }

    /// Firmware values that differ from the D415 default (librealsense `presets.cpp`).
    fn overrides(self) -> &'static [(&'static str, f64)] {
        match self {
            Self::Default => &[],
            Self::Hand => HAND,
            Self::HighAccuracy => HIGH_ACCURACY,
            Self::HighDensity => HIGH_DENSITY,
            Self::MediumDensity => MEDIUM_DENSITY,
            Self::RemoveIrPattern => REMOVE_IR_PATTERN,
        }
    }
}

/// D415 power-on firmware values (librealsense `default_410`), by JSON key.
const DEFAULT_D415: &[(&str, f64)] = &[
    ("param-medianthreshold", 500.0),
    ("param-neighborthresh", 7.0),
    ("param-secondpeakdelta", 325.0),
    ("param-leftrightthreshold", 24.0),
    ("param-robbinsmonrodecrement", 10.0),
    ("param-robbinsmonroincrement", 10.0),
    ("param-minscorethresha", 1.0),
    ("param-maxscorethreshb", 2047.0),
    ("param-texturecountthresh", 0.0),
    ("param-texturedifferencethresh", 0.0),
    ("param-rsmdiffthreshold", 4.0),
    ("param-rsmremovethreshold", 63.0),
    ("param-usersm", 0.0),
    ("param-rsmrauslodiffthreshold", 1.0),
    ("param-raumine", 1.0),
    ("param-rauminn", 1.0),
    ("param-rauminnssum", 3.0),
    ("param-raumins", 1.0),
    ("param-rauminw", 1.0),
    ("param-rauminwesum", 3.0),
    ("param-regionshrinku", 3.0),
    ("param-regionshrinkv", 1.0),
    ("param-disableraucolor", 0.0),
    ("param-disablesadcolor", 0.0),
    ("param-disablesadnormalize", 0.0),
    ("param-disablesloleftcolor", 0.0),
    ("param-disableslorightcolor", 0.0),
    ("param-regioncolorthresholdb", 51.0),
    ("param-regioncolorthresholdg", 51.0),
    ("param-regioncolorthresholdr", 51.0),
    ("param-scanlineedgetaub", 72.0),
    ("param-scanlineedgetaug", 72.0),
    ("param-scanlineedgetaur", 72.0),
    ("param-scanlinep1", 60.0),
    ("param-scanlinep1onediscon", 105.0),
    ("param-scanlinep1twodiscon", 70.0),
    ("param-scanlinep2", 342.0),
    ("param-scanlinep2onediscon", 190.0),
    ("param-scanlinep2twodiscon", 130.0),
    ("param-lambdaad", 800.0),
    ("param-lambdacensus", 26.0),
    ("ignoreSAD", 0.0),
    ("aux-param-colorcorrection1", 0.461914),
    ("aux-param-colorcorrection2", 0.540039),
    ("aux-param-colorcorrection3", 0.540039),
    ("aux-param-colorcorrection4", 0.208008),
    ("aux-param-colorcorrection5", -0.332031),
    ("aux-param-colorcorrection6", -0.212891),
    ("aux-param-colorcorrection7", -0.212891),
    ("aux-param-colorcorrection8", 0.68457),
    ("aux-param-colorcorrection9", 0.930664),
    ("aux-param-colorcorrection10", -0.553711),
    ("aux-param-colorcorrection11", -0.553711),
    ("aux-param-colorcorrection12", 0.0458984),
    ("param-depthclampmax", 65536.0),
    ("param-depthclampmin", 0.0),
    ("param-depthunits", 1000.0),
    ("param-disparityshift", 0.0),
    ("param-disparitymode", 0.0),
    ("param-autoexposure-setpoint", 400.0),
    ("param-censusenablereg-udiameter", 9.0),
    ("param-censusenablereg-vdiameter", 9.0),
    ("controls-laserpower", 150.0),
    ("controls-color-autoexposure-manual", 156.0),
    ("controls-color-backlight-compensation", 0.0),
    ("controls-color-brightness", 0.0),
    ("controls-color-contrast", 50.0),
    ("controls-color-gain", 64.0),
    ("controls-color-gamma", 300.0),
    ("controls-color-hue", 0.0),
    ("controls-color-power-line-frequency", 3.0),
    ("controls-color-saturation", 64.0),
    ("controls-color-sharpness", 50.0),
    ("controls-color-white-balance-manual", 4600.0),
    ("controls-autoexposure-manual", 32000.0),
    ("controls-depth-gain", 16.0),
];

/// Keys whose D415 default is not a number; the stream keys describe the default
/// depth mode (they follow the camera's depth settings).
const D415_STRINGS: &[(&str, &str)] = &[
    ("controls-laserstate", "on"),
    ("controls-autoexposure-auto", "True"),
    ("controls-color-autoexposure-auto", "True"),
    ("controls-color-white-balance-auto", "True"),
    ("controls-depth-white-balance-auto", "False"),
    ("stream-depth-format", "Z16"),
    ("stream-fps", "30"),
    ("stream-height", "720"),
    ("stream-width", "1280"),
];

const HIGH_ACCURACY: &[(&str, f64)] = &[
    ("param-censusenablereg-udiameter", 9.0),
    ("param-censusenablereg-vdiameter", 9.0),
    ("param-medianthreshold", 796.0),
    ("param-neighborthresh", 108.0),
    ("param-secondpeakdelta", 647.0),
    ("param-leftrightthreshold", 10.0),
    ("param-robbinsmonrodecrement", 25.0),
    ("param-robbinsmonroincrement", 2.0),
    ("param-minscorethresha", 4.0),
    ("param-maxscorethreshb", 2893.0),
    ("param-texturecountthresh", 0.0),
    ("param-texturedifferencethresh", 1722.0),
    ("param-rsmdiffthreshold", 1.65625),
    ("param-rsmremovethreshold", 136.0),
    ("param-usersm", 0.0),
    ("param-rsmrauslodiffthreshold", 0.785714),
    ("param-raumine", 6.0),
    ("param-rauminn", 3.0),
    ("param-rauminnssum", 7.0),
    ("param-raumins", 2.0),
    ("param-rauminw", 2.0),
    ("param-rauminwesum", 12.0),
    ("param-regionshrinku", 3.0),
    ("param-regionshrinkv", 0.0),
    ("param-disableraucolor", 0.0),
    ("param-disablesadcolor", 0.0),
    ("param-disablesadnormalize", 0.0),
    ("param-disablesloleftcolor", 0.0),
    ("param-disableslorightcolor", 1.0),
    ("param-regioncolorthresholdb", 803.0),
    ("param-regioncolorthresholdg", 578.0),
    ("param-regioncolorthresholdr", 1007.0),
    ("param-scanlineedgetaub", 13.0),
    ("param-scanlineedgetaug", 15.0),
    ("param-scanlineedgetaur", 30.0),
    ("param-scanlinep1", 155.0),
    ("param-scanlinep1onediscon", 160.0),
    ("param-scanlinep1twodiscon", 59.0),
    ("param-scanlinep2", 190.0),
    ("param-scanlinep2onediscon", 507.0),
    ("param-scanlinep2twodiscon", 493.0),
    ("param-lambdaad", 751.0),
    ("param-lambdacensus", 6.0),
    ("ignoreSAD", 0.0),
];

const HIGH_DENSITY: &[(&str, f64)] = &[
    ("param-censusenablereg-udiameter", 9.0),
    ("param-censusenablereg-vdiameter", 9.0),
    ("param-medianthreshold", 789.0),
    ("param-neighborthresh", 12.0),
    ("param-secondpeakdelta", 222.0),
    ("param-leftrightthreshold", 18.0),
    ("param-robbinsmonrodecrement", 6.0),
    ("param-robbinsmonroincrement", 21.0),
    ("param-minscorethresha", 96.0),
    ("param-maxscorethreshb", 1443.0),
    ("param-texturecountthresh", 0.0),
    ("param-texturedifferencethresh", 2466.0),
    ("param-rsmdiffthreshold", 1.21875),
    ("param-rsmremovethreshold", 82.0),
    ("param-usersm", 0.0),
    ("param-rsmrauslodiffthreshold", 0.28125),
    ("param-raumine", 2.0),
    ("param-rauminn", 1.0),
    ("param-rauminnssum", 6.0),
    ("param-raumins", 3.0),
    ("param-rauminw", 3.0),
    ("param-rauminwesum", 7.0),
    ("param-regionshrinku", 4.0),
    ("param-regionshrinkv", 0.0),
    ("param-disableraucolor", 0.0),
    ("param-disablesadcolor", 0.0),
    ("param-disablesadnormalize", 0.0),
    ("param-disablesloleftcolor", 0.0),
    ("param-disableslorightcolor", 0.0),
    ("param-regioncolorthresholdb", 112.0),
    ("param-regioncolorthresholdg", 585.0),
    ("param-regioncolorthresholdr", 18.0),
    ("param-scanlineedgetaub", 8.0),
    ("param-scanlineedgetaug", 200.0),
    ("param-scanlineedgetaur", 279.0),
    ("param-scanlinep1", 55.0),
    ("param-scanlinep1onediscon", 326.0),
    ("param-scanlinep1twodiscon", 134.0),
    ("param-scanlinep2", 235.0),
    ("param-scanlinep2onediscon", 506.0),
    ("param-scanlinep2twodiscon", 206.0),
    ("param-lambdaad", 618.0),
    ("param-lambdacensus", 15.0),
    ("ignoreSAD", 0.0),
];

const MEDIUM_DENSITY: &[(&str, f64)] = &[
    ("param-censusenablereg-udiameter", 9.0),
    ("param-censusenablereg-vdiameter", 9.0),
    ("param-medianthreshold", 1021.0),
    ("param-neighborthresh", 97.0),
    ("param-secondpeakdelta", 600.0),
    ("param-leftrightthreshold", 19.0),
    ("param-robbinsmonrodecrement", 23.0),
    ("param-robbinsmonroincrement", 3.0),
    ("param-minscorethresha", 54.0),
    ("param-maxscorethreshb", 887.0),
    ("param-texturecountthresh", 0.0),
    ("param-texturedifferencethresh", 0.0),
    ("param-rsmdiffthreshold", 1.8125),
    ("param-rsmremovethreshold", 81.0),
    ("param-usersm", 0.0),
    ("param-rsmrauslodiffthreshold", 1.0),
    ("param-raumine", 3.0),
    ("param-rauminn", 1.0),
    ("param-rauminnssum", 6.0),
    ("param-raumins", 3.0),
    ("param-rauminw", 5.0),
    ("param-rauminwesum", 11.0),
    ("param-regionshrinku", 3.0),
    ("param-regionshrinkv", 1.0),
    ("param-disableraucolor", 0.0),
    ("param-disablesadcolor", 0.0),
    ("param-disablesadnormalize", 0.0),
    ("param-disablesloleftcolor", 0.0),
    ("param-disableslorightcolor", 1.0),
    ("param-regioncolorthresholdb", 14.0),
    ("param-regioncolorthresholdg", 723.0),
    ("param-regioncolorthresholdr", 186.0),
    ("param-scanlineedgetaub", 16.0),
    ("param-scanlineedgetaug", 259.0),
    ("param-scanlineedgetaur", 896.0),
    ("param-scanlinep1", 132.0),
    ("param-scanlinep1onediscon", 77.0),
    ("param-scanlinep1twodiscon", 234.0),
    ("param-scanlinep2", 342.0),
    ("param-scanlinep2onediscon", 390.0),
    ("param-scanlinep2twodiscon", 151.0),
    ("param-lambdaad", 935.0),
    ("param-lambdacensus", 26.0),
    ("ignoreSAD", 0.0),
];

const HAND: &[(&str, f64)] = &[
    ("param-medianthreshold", 240.0),
    ("param-neighborthresh", 110.0),
    ("param-secondpeakdelta", 31.0),
    ("param-leftrightthreshold", 20.0),
    ("param-robbinsmonrodecrement", 20.0),
    ("param-robbinsmonroincrement", 3.0),
    ("param-minscorethresha", 24.0),
    ("param-maxscorethreshb", 791.0),
    ("param-texturecountthresh", 0.0),
    ("param-texturedifferencethresh", 783.0),
    ("param-rsmdiffthreshold", 3.8125),
    ("param-rsmremovethreshold", 92.0),
    ("param-usersm", 0.0),
    ("param-rsmrauslodiffthreshold", 0.46875),
    ("param-raumine", 3.0),
    ("param-rauminn", 1.0),
    ("param-rauminnssum", 4.0),
    ("param-raumins", 3.0),
    ("param-rauminw", 1.0),
    ("param-rauminwesum", 14.0),
    ("param-regionshrinku", 3.0),
    ("param-regionshrinkv", 1.0),
    ("param-disableraucolor", 0.0),
    ("param-disablesadcolor", 0.0),
    ("param-disablesadnormalize", 0.0),
    ("param-disablesloleftcolor", 0.0),
    ("param-disableslorightcolor", 1.0),
    ("param-regioncolorthresholdb", 50.0),
    ("param-regioncolorthresholdg", 73.0),
    ("param-regioncolorthresholdr", 141.0),
    ("param-scanlineedgetaub", 130.0),
    ("param-scanlineedgetaug", 244.0),
    ("param-scanlineedgetaur", 618.0),
    ("param-scanlinep1", 63.0),
    ("param-scanlinep1onediscon", 14.0),
    ("param-scanlinep1twodiscon", 119.0),
    ("param-scanlinep2", 45.0),
    ("param-scanlinep2onediscon", 21.0),
    ("param-scanlinep2twodiscon", 12.0),
    ("ignoreSAD", 0.0),
    ("param-lambdaad", 1001.0),
    ("param-lambdacensus", 7.0),
    ("param-censusenablereg-udiameter", 9.0),
    ("param-censusenablereg-vdiameter", 3.0),
];

const REMOVE_IR_PATTERN: &[(&str, f64)] = &[
    ("aux-param-colorcorrection1", 0.520_507_991_313_9),
    ("aux-param-colorcorrection2", 1.990_234_017_372),
    ("aux-param-colorcorrection3", 1.506_836_056_709),
    ("aux-param-colorcorrection4", -2.0),
    ("aux-param-colorcorrection5", -2.0),
    ("aux-param-colorcorrection6", -0.082_030_996_680_26),
    ("aux-param-colorcorrection7", 1.123_046_994_209),
    ("aux-param-colorcorrection8", 1.013_671_994_209),
    ("aux-param-colorcorrection9", 1.698_241_949_081),
    ("aux-param-colorcorrection10", -2.0),
    ("aux-param-colorcorrection11", 0.575_195_014_476_8),
    ("aux-param-colorcorrection12", -0.411_132_991_313_9),
];

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn g6_formats_like_a_cpp_stream() {
        assert_eq!(format_g6(63.0 / 168.0), "0.375");
        assert_eq!(format_g6(51.0 / 1022.0), "0.0499022");
        assert_eq!(format_g6(65536.0), "65536");
        assert_eq!(format_g6(-0.553711), "-0.553711");
        assert_eq!(format_g6(0.0458984), "0.0458984");
    }

    #[test]
    fn g6_switches_to_exponent_notation_like_c_printf() {
        assert_eq!(format_g6(0.0001), "0.0001");
        assert_eq!(format_g6(0.0000123), "1.23e-05");
        assert_eq!(format_g6(999_999.0), "999999");
        assert_eq!(format_g6(999_999.7), "1e+06");
        assert_eq!(format_g6(1_234_567.0), "1.23457e+06");
        assert_eq!(format_g6(-2.5e-7), "-2.5e-07");
        assert_eq!(format_g6(1e100), "1e+100");
        assert_eq!(format_g6(0.5), "0.5");
    }

    #[test]
    fn presets_are_complete_documents() {
        for p in VisualPreset::ALL {
            let doc = AdvancedConfig::preset(p);
            assert!(doc.is_complete(), "{} has {} keys", p.name(), doc.len());
            assert_eq!(
                AdvancedConfig::from_json(doc.to_json().as_bytes()).unwrap(),
                doc
            );
        }
    }
}
