//! What every object of a scene shares: when it is there ([`Timeline`]), how its surface
//! returns light ([`Finish`]), the checks of their values, and how a scene file writes them.
//! The scene and each object kind build on these; `scene` re-exports the public ones.

use std::fmt::Write as _;

use serde::Deserialize;

use super::label::Label;

/// When an object is in the scene and how it gets to its place, in seconds of scene
/// time (see the module documentation). The default is "there, still, all the time".
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Timeline {
    /// When it appears; `None` = from the start.
    pub appear_s: Option<f64>,
    /// When it is removed; `None` = never.
    pub remove_s: Option<f64>,
    /// Where it appears, (x, y) metres, when it slides in to its centre.
    pub from: Option<[f64; 2]>,
    /// When it stands at its centre, having slid from `from` since `appear_s`.
    pub still_s: Option<f64>,
}

impl Label {
    /// When the label is on its box (it moves with the box: no `from`).
    pub fn timeline(&self) -> Timeline {
        Timeline {
            appear_s: self.appear_s,
            remove_s: self.remove_s,
            from: None,
            still_s: None,
        }
    }
}

/// Latest time a timeline may name, seconds (about 116 days).
pub const MAX_SCENE_TIME_S: f64 = 1.0e7;

impl Timeline {
    /// Whether it is the default: there, still, all the time.
    pub fn is_always(&self) -> bool {
        *self == Self::default()
    }

    /// When it appears, seconds (0 when there from the start).
    pub fn appear(&self) -> f64 {
        self.appear_s.unwrap_or(0.0)
    }

    /// When it stands still at its centre: `still_s` when it slides in, else when it
    /// appears.
    pub fn still(&self) -> f64 {
        self.still_s.unwrap_or_else(|| self.appear())
    }

    /// Whether it is in the scene at scene time `t_s`.
    pub fn present(&self, t_s: f64) -> bool {
        t_s >= self.appear() && self.remove_s.is_none_or(|r| t_s < r)
    }

    /// Whether it is in the scene and sliding at `t_s`.
    pub fn moving(&self, t_s: f64) -> bool {
        self.present(t_s) && self.from.is_some() && t_s < self.still()
    }

    /// Where an object resting at `center` stands at `t_s`; `None` when it is absent.
    /// From `still_s` on (and always without `from`) exactly `center`.
    pub fn position(&self, center: [f64; 2], t_s: f64) -> Option<[f64; 2]> {
        if !self.present(t_s) {
            return None;
        }
        match (self.from, self.still_s) {
            (Some(from), Some(still)) if t_s < still => {
                let f = (t_s - self.appear()) / (still - self.appear());
                Some([
                    from[0] + (center[0] - from[0]) * f,
                    from[1] + (center[1] - from[1]) * f,
                ])
            }
            _ => Some(center),
        }
    }

    /// Checks the rules of a timeline; `at` names a field (`box[0].still_s`).
    pub(crate) fn validate(&self, at: &dyn Fn(&str) -> String) -> Result<(), SceneError> {
        for (name, value) in [
            ("appear_s", self.appear_s),
            ("remove_s", self.remove_s),
            ("still_s", self.still_s),
        ] {
            if let Some(v) = value
                && !(v.is_finite() && (0.0..=MAX_SCENE_TIME_S).contains(&v))
            {
                return Err(invalid(
                    at(name),
                    format!("must be seconds of scene time from 0 to {MAX_SCENE_TIME_S}, got {v}"),
                ));
            }
        }
        if let Some(from) = self.from {
            coordinates(&at("from"), &from)?;
        }
        let appear = self.appear();
        match (self.from, self.still_s) {
            (Some(_), None) => {
                return Err(invalid(
                    at("from"),
                    "needs still_s: the time it stands at its centre after sliding from `from`",
                ));
            }
            (None, Some(_)) => {
                return Err(invalid(
                    at("still_s"),
                    "needs from: the point it slides from, starting at appear_s",
                ));
            }
            (Some(_), Some(still)) if still <= appear => {
                return Err(invalid(
                    at("still_s"),
                    format!("must be after appear_s ({appear} s), got {still}"),
                ));
            }
            _ => {}
        }
        if let Some(remove) = self.remove_s {
            let (after, when) = match self.still_s {
                Some(still) => ("still_s", still),
                None => ("appear_s", appear),
            };
            if remove <= when {
                return Err(invalid(
                    at("remove_s"),
                    format!("must be after {after} ({when} s), got {remove}"),
                ));
            }
        }
        Ok(())
    }
}

/// How an object's surface returns the D415's light (see the module documentation): the
/// default is a matte, light surface that always returns enough, as every object did
/// before finishes existed.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
pub struct Finish {
    /// Share of the infrared light the surface sends back, 0 (black) to 1 (the default:
    /// bright enough everywhere). Below 1 a pixel's depth is missing the more often the
    /// less light comes back (darker, farther, more slanted).
    #[serde(default = "default_reflectivity")]
    pub reflectivity: f64,
    /// How mirror-like the surface is, 0 (matte, the default) to 1. Where the projector's
    /// mirror image falls into the imagers the pixels saturate and lose their depth; the
    /// color image shows a highlight.
    #[serde(default)]
    pub gloss: f64,
}

fn default_reflectivity() -> f64 {
    1.0
}

impl Default for Finish {
    fn default() -> Self {
        Self {
            reflectivity: 1.0,
            gloss: 0.0,
        }
    }
}

impl Finish {
    /// Whether it is the default (matte, always enough light).
    pub fn is_default(&self) -> bool {
        *self == Self::default()
    }

    pub(crate) fn validate(&self, at: &dyn Fn(&str) -> String) -> Result<(), SceneError> {
        for (name, value) in [("reflectivity", self.reflectivity), ("gloss", self.gloss)] {
            if !(0.0..=1.0).contains(&value) {
                return Err(invalid(
                    at(name),
                    format!("must be from 0 to 1, got {value}"),
                ));
            }
        }
        Ok(())
    }
}

/// The timeline fields every object of a scene file may carry (flattened into the
/// object's table).
#[derive(Deserialize)]
pub(crate) struct TimelineFile {
    #[serde(default)]
    appear_s: Option<f64>,
    #[serde(default)]
    remove_s: Option<f64>,
    #[serde(default)]
    from: Option<[f64; 2]>,
    #[serde(default)]
    still_s: Option<f64>,
}

impl From<TimelineFile> for Timeline {
    fn from(f: TimelineFile) -> Self {
        Self {
            appear_s: f.appear_s,
            remove_s: f.remove_s,
            from: f.from,
            still_s: f.still_s,
        }
    }
}

/// Why a scene was refused.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SceneError {
    /// The file could not be read.
    #[error("cannot read scene file {path}: {source}")]
    Io {
        /// The path.
        path: String,
        /// The OS error.
        source: std::io::Error,
    },
    /// Not valid TOML of the scene shape (the message has line and column).
    #[error("scene: {0}")]
    Parse(String),
    /// A value outside what the field allows.
    #[error("scene: {field}: {reason}")]
    Invalid {
        /// Which field, e.g. `camera[1].serial`.
        field: String,
        /// What is wrong and what is allowed.
        reason: String,
    },
}

pub(crate) fn invalid(field: impl Into<String>, reason: impl Into<String>) -> SceneError {
    SceneError::Invalid {
        field: field.into(),
        reason: reason.into(),
    }
}

/// Largest coordinate magnitude of a position, point or direction, metres.
pub const MAX_COORDINATE_M: f64 = 1000.0;
/// Largest size (box edge, radius, height, label width), metres.
pub const MAX_SIZE_M: f64 = 100.0;

pub(crate) fn finite(field: &str, values: &[f64]) -> Result<(), SceneError> {
    if values.iter().all(|v| v.is_finite()) {
        Ok(())
    } else {
        Err(invalid(field, "must be finite numbers"))
    }
}

pub(crate) fn coordinates(field: &str, values: &[f64]) -> Result<(), SceneError> {
    if values
        .iter()
        .all(|v| v.is_finite() && v.abs() <= MAX_COORDINATE_M)
    {
        Ok(())
    } else {
        Err(invalid(
            field,
            format!("must be finite numbers within ±{MAX_COORDINATE_M} m, got {values:?}"),
        ))
    }
}

pub(crate) fn positive(field: &str, values: &[f64]) -> Result<(), SceneError> {
    if values
        .iter()
        .all(|v| v.is_finite() && *v > 0.0 && *v <= MAX_SIZE_M)
    {
        Ok(())
    } else {
        Err(invalid(
            field,
            format!("must be positive (metres) and at most {MAX_SIZE_M} m, got {values:?}"),
        ))
    }
}

/// Checks where an object stands, `at` naming its fields: its centre on the floor and
/// its yaw (`None` for a vertical cylinder, which has none).
pub(crate) fn check_place(
    at: &dyn Fn(&str) -> String,
    center: &[f64; 2],
    yaw_deg: Option<f64>,
) -> Result<(), SceneError> {
    coordinates(&at("center"), center)?;
    match yaw_deg {
        Some(yaw) => finite(&at("yaw_deg"), &[yaw]),
        None => Ok(()),
    }
}

/// Checks how an object's surface returns light and when it is there, `at` naming its
/// fields.
pub(crate) fn check_surface(
    at: &dyn Fn(&str) -> String,
    finish: &Finish,
    timeline: &Timeline,
) -> Result<(), SceneError> {
    finish.validate(at)?;
    timeline.validate(at)
}

/// `text` as a TOML basic string.
pub(crate) fn quoted(text: &str) -> String {
    let mut out = String::with_capacity(text.len() + 2);
    out.push('"');
    for c in text.chars() {
        match c {
            '"' => out.push_str("\\\""),
            '\\' => out.push_str("\\\\"),
            c if c.is_control() => {
                let _ = write!(out, "\\u{:04X}", u32::from(c));
            }
            c => out.push(c),
        }
    }
    out.push('"');
    out
}

/// A name as the scene file spells it: serde's lowercase of the variant.
pub(crate) fn lower(value: impl std::fmt::Debug) -> String {
    format!("{value:?}").to_lowercase()
}

/// A finish's lines in an object's table of a scene file.
pub(crate) fn write_finish(out: &mut String, f: &Finish) {
    let _ = writeln!(
        out,
        "reflectivity = {:?}\ngloss = {:?}",
        f.reflectivity, f.gloss
    );
}

/// A timeline's lines in an object's table of a scene file (none for the default).
pub(crate) fn write_timeline(out: &mut String, t: &Timeline) {
    for (name, value) in [("appear_s", t.appear_s), ("still_s", t.still_s)] {
        if let Some(v) = value {
            let _ = writeln!(out, "{name} = {v:?}");
        }
    }
    if let Some(from) = t.from {
        let _ = writeln!(out, "from = {from:?}");
    }
    if let Some(v) = t.remove_s {
        let _ = writeln!(out, "remove_s = {v:?}");
    }
}
