//! The post-processing chain of the application-config resource (thesis §3.3.3,
//! Figure 3.10, Listing A.3 `postprocessing`): decimation, then the flying-pixel filter
//! (coapcam's own stage, [`super::flying`]), then the spatial filter, then hole filling,
//! each optional.
//!
//! The spatial filter runs in the disparity domain (depth -> disparity -> spatial ->
//! depth), as librealsense's documentation recommends, so only a stereo camera has it
//! (another refuses a chain with it, [`FilterError::NoStereoPair`]); hole filling runs after the
//! conversion back to depth, where its mode names mean what they say (on disparity
//! "farest" would pick the nearest surface).
//!
//! Configuration keeps the thesis's keys. Each stage is `0` (off), `1` (on with
//! librealsense's defaults, as the thesis ran it) or an object of parameters:
//!
//! ```json
//! { "decimation": {"magnitude": 2},
//!   "spatial": {"alpha": 0.5, "delta": 20, "iterations": 2, "holes_fill": 0},
//!   "holefilling": {"mode": "farest_from_around"},
//!   "flying_pixels": {"step": 0.02} }
//! ```
//!
//! `flying_pixels` is written only when it is on, so a document without it reads and
//! writes as before.
//!
//! Omitted parameters take librealsense's defaults; out-of-range values are refused
//! with an error naming the field and what it accepts.

use std::fmt;
use std::marker::PhantomData;

use serde::de::{self, MapAccess, Visitor};
use serde::{Deserialize, Deserializer, Serialize};

use super::decimation::Decimation;
use super::disparity::{DepthToDisparity, DisparityToDepth, copy_compact};
use super::flying::FlyingPixels;
use super::hole_fill::{HoleFilling, HoleFillingMode};
use super::spatial::{SpatialFilter, SpatialParams};
use super::{FilterError, FrameFilter as _, check_frame, empty_frame};
use crate::frame::DepthFrame;
use crate::intrinsics::Intrinsics;

/// Parameters of the decimation stage.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct DecimationConfig {
    /// Magnitude 1..=8 (default 2).
    pub magnitude: u8,
}

impl Default for DecimationConfig {
    fn default() -> Self {
        Self {
            magnitude: Decimation::DEFAULT_MAGNITUDE,
        }
    }
}

/// Parameters of the spatial stage (librealsense's spatial filter options).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct SpatialConfig {
    /// Weight of the current pixel, 0.25..=1 (default 0.5).
    pub alpha: f32,
    /// Edge threshold in disparity units (1/32 px), 1..=50 (default 20).
    pub delta: u8,
    /// Passes, 1..=5 (default 2).
    pub iterations: u8,
    /// Holes filling 0..=5: off, radius 2, 4, 8, 16, unlimited (default 0).
    pub holes_fill: u8,
}

impl Default for SpatialConfig {
    fn default() -> Self {
        let p = SpatialParams::default();
        Self {
            alpha: p.alpha,
            delta: p.delta,
            iterations: p.iterations,
            holes_fill: p.holes_fill,
        }
    }
}

impl From<SpatialConfig> for SpatialParams {
    fn from(c: SpatialConfig) -> Self {
        Self {
            alpha: c.alpha,
            delta: c.delta,
            iterations: c.iterations,
            holes_fill: c.holes_fill,
        }
    }
}

/// Parameters of the hole-filling stage.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct HoleFillingConfig {
    /// The mode (default `farest_from_around`, librealsense's default).
    pub mode: HoleFillingMode,
}

impl Default for HoleFillingConfig {
    fn default() -> Self {
        Self {
            mode: HoleFillingMode::FarestFromAround,
        }
    }
}

/// Parameters of the flying-pixel stage.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct FlyingPixelsConfig {
    /// A pixel more than this share of its depth behind a neighbour is dropped, 0.005..=0.5
    /// (default 0.02).
    pub step: f32,
}

impl Default for FlyingPixelsConfig {
    fn default() -> Self {
        Self {
            step: FlyingPixels::DEFAULT_STEP,
        }
    }
}

/// The `postprocessing` section of the application config. `None` = stage off.
#[derive(Debug, Clone, Copy, PartialEq, Default, Deserialize)]
#[serde(try_from = "RawConfig")]
pub struct PostProcessingConfig {
    /// Decimation.
    pub decimation: Option<DecimationConfig>,
    /// Spatial filter (in the disparity domain).
    pub spatial: Option<SpatialConfig>,
    /// Hole filling.
    pub holefilling: Option<HoleFillingConfig>,
    /// The flying-pixel filter (after decimation, before the spatial filter).
    pub flying_pixels: Option<FlyingPixelsConfig>,
}

/// A `postprocessing` document that is not valid.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum PostProcessingError {
    /// Not parseable JSON, or a value of the wrong shape.
    #[error("postprocessing: {0}")]
    Syntax(String),
    /// A value outside what the field accepts.
    #[error("{field} = {found} is not allowed: {allowed}")]
    Invalid {
        /// Dotted path of the field (`postprocessing.spatial.delta`).
        field: &'static str,
        /// The value given.
        found: String,
        /// What the field accepts.
        allowed: &'static str,
    },
}

impl PostProcessingConfig {
    /// Parses and validates a `postprocessing` JSON object.
    pub fn from_json(json: &[u8]) -> Result<Self, PostProcessingError> {
        let raw: RawConfig =
            serde_json::from_slice(json).map_err(|e| PostProcessingError::Syntax(e.to_string()))?;
        Self::try_from(raw)
    }

    /// The JSON form: `0` for an off stage, `1` for a stage with librealsense's
    /// defaults, an object otherwise.
    pub fn to_json(&self) -> String {
        // Numbers and names only: serializing cannot fail.
        serde_json::to_string(self).unwrap_or_default()
    }

    /// Checks every parameter against librealsense's ranges.
    pub fn validate(&self) -> Result<(), PostProcessingError> {
        if let Some(d) = self.decimation {
            check_int(
                "postprocessing.decimation.magnitude",
                i64::from(d.magnitude),
                1,
                8,
                "an integer from 1 to 8",
            )?;
        }
        if let Some(f) = self.flying_pixels
            && !FlyingPixels::STEPS.contains(&f.step)
        {
            return Err(PostProcessingError::Invalid {
                field: "postprocessing.flying_pixels.step",
                found: f.step.to_string(),
                allowed: "a share of the depth from 0.005 to 0.5",
            });
        }
        if let Some(s) = self.spatial {
            if !(0.25..=1.0).contains(&s.alpha) {
                return Err(PostProcessingError::Invalid {
                    field: "postprocessing.spatial.alpha",
                    found: s.alpha.to_string(),
                    allowed: "a number from 0.25 to 1",
                });
            }
            check_int(
                "postprocessing.spatial.delta",
                i64::from(s.delta),
                1,
                50,
                "an integer from 1 to 50",
            )?;
            check_int(
                "postprocessing.spatial.iterations",
                i64::from(s.iterations),
                1,
                5,
                "an integer from 1 to 5",
            )?;
            check_int(
                "postprocessing.spatial.holes_fill",
                i64::from(s.holes_fill),
                0,
                5,
                "an integer from 0 (off) to 5 (unlimited)",
            )?;
        }
        Ok(())
    }
}

/// A stage as the document gives it: `0` off, `1` librealsense's defaults, else its
/// parameters.
#[derive(Serialize)]
#[serde(untagged)]
enum Stage<T> {
    Flag(u8),
    Params(T),
}

fn stage<T: Default + PartialEq>(stage: Option<T>) -> Stage<T> {
    match stage {
        None => Stage::Flag(0),
        Some(p) if p == T::default() => Stage::Flag(1),
        Some(p) => Stage::Params(p),
    }
}

impl Serialize for PostProcessingConfig {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        use serde::ser::SerializeStruct as _;
        let fields = 3 + usize::from(self.flying_pixels.is_some());
        let mut doc = s.serialize_struct("PostProcessingConfig", fields)?;
        // In the names' order, as the document has always been written; the flying-pixel
        // stage only when on, so documents without it stay as they were.
        doc.serialize_field("decimation", &stage(self.decimation))?;
        if self.flying_pixels.is_some() {
            doc.serialize_field("flying_pixels", &stage(self.flying_pixels))?;
        } else {
            doc.skip_field("flying_pixels")?;
        }
        doc.serialize_field("holefilling", &stage(self.holefilling))?;
        doc.serialize_field("spatial", &stage(self.spatial))?;
        doc.end()
    }
}

fn check_int(
    field: &'static str,
    value: i64,
    min: i64,
    max: i64,
    allowed: &'static str,
) -> Result<(), PostProcessingError> {
    if (min..=max).contains(&value) {
        Ok(())
    } else {
        Err(PostProcessingError::Invalid {
            field,
            found: value.to_string(),
            allowed,
        })
    }
}

/// The section as written, before range checks.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawConfig {
    #[serde(default)]
    decimation: RawStage<RawDecimation>,
    #[serde(default)]
    spatial: RawStage<RawSpatial>,
    #[serde(default)]
    holefilling: RawStage<RawHoleFilling>,
    #[serde(default)]
    flying_pixels: RawStage<RawFlyingPixels>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawFlyingPixels {
    step: Option<f64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawDecimation {
    magnitude: Option<i64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawSpatial {
    alpha: Option<f64>,
    delta: Option<i64>,
    iterations: Option<i64>,
    holes_fill: Option<i64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawHoleFilling {
    mode: Option<HoleFillingMode>,
}

/// What a stage's JSON value is: 0, 1 or an object.
#[derive(Default)]
enum RawStage<T> {
    #[default]
    Off,
    Defaults,
    Params(T),
}

/// The name and the accepted object of a stage, for error messages.
trait StageShape {
    const EXPECTING: &'static str;
}

impl StageShape for RawDecimation {
    const EXPECTING: &'static str =
        "postprocessing.decimation: 0 (off), 1 (magnitude 2) or {\"magnitude\": 1..8}";
}

impl StageShape for RawSpatial {
    const EXPECTING: &'static str = "postprocessing.spatial: 0 (off), 1 (librealsense's defaults) \
         or {\"alpha\": 0.25..1, \"delta\": 1..50, \"iterations\": 1..5, \"holes_fill\": 0..5}";
}

impl StageShape for RawFlyingPixels {
    const EXPECTING: &'static str =
        "postprocessing.flying_pixels: 0 (off), 1 (step 0.02) or {\"step\": 0.005..0.5}";
}

impl StageShape for RawHoleFilling {
    const EXPECTING: &'static str = "postprocessing.holefilling: 0 (off), 1 (farest_from_around) \
         or {\"mode\": \"fill_from_left\" | \"farest_from_around\" | \"nearest_from_around\"}";
}

struct StageVisitor<T>(PhantomData<T>);

impl<'de, T: Deserialize<'de> + StageShape> Visitor<'de> for StageVisitor<T> {
    type Value = RawStage<T>;

    fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(T::EXPECTING)
    }

    fn visit_u64<E: de::Error>(self, v: u64) -> Result<Self::Value, E> {
        match v {
            0 => Ok(RawStage::Off),
            1 => Ok(RawStage::Defaults),
            _ => Err(E::invalid_value(de::Unexpected::Unsigned(v), &self)),
        }
    }

    fn visit_i64<E: de::Error>(self, v: i64) -> Result<Self::Value, E> {
        match u64::try_from(v) {
            Ok(u) => self.visit_u64(u),
            Err(_) => Err(E::invalid_value(de::Unexpected::Signed(v), &self)),
        }
    }

    fn visit_map<A: MapAccess<'de>>(self, map: A) -> Result<Self::Value, A::Error> {
        T::deserialize(de::value::MapAccessDeserializer::new(map)).map(RawStage::Params)
    }
}

impl<'de, T: Deserialize<'de> + StageShape> Deserialize<'de> for RawStage<T> {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        deserializer.deserialize_any(StageVisitor(PhantomData))
    }
}

fn narrow(
    field: &'static str,
    value: i64,
    allowed: &'static str,
) -> Result<u8, PostProcessingError> {
    u8::try_from(value).map_err(|_| PostProcessingError::Invalid {
        field,
        found: value.to_string(),
        allowed,
    })
}

impl TryFrom<RawConfig> for PostProcessingConfig {
    type Error = PostProcessingError;

    fn try_from(raw: RawConfig) -> Result<Self, Self::Error> {
        let decimation = match raw.decimation {
            RawStage::Off => None,
            RawStage::Defaults => Some(DecimationConfig::default()),
            RawStage::Params(p) => Some(DecimationConfig {
                magnitude: match p.magnitude {
                    None => Decimation::DEFAULT_MAGNITUDE,
                    Some(m) => narrow(
                        "postprocessing.decimation.magnitude",
                        m,
                        "an integer from 1 to 8",
                    )?,
                },
            }),
        };
        let spatial = match raw.spatial {
            RawStage::Off => None,
            RawStage::Defaults => Some(SpatialConfig::default()),
            RawStage::Params(p) => {
                let d = SpatialConfig::default();
                Some(SpatialConfig {
                    // f64 -> f32 as librealsense's float option; range checked below.
                    alpha: p.alpha.map_or(d.alpha, |a| a as f32),
                    delta: match p.delta {
                        None => d.delta,
                        Some(v) => {
                            narrow("postprocessing.spatial.delta", v, "an integer from 1 to 50")?
                        }
                    },
                    iterations: match p.iterations {
                        None => d.iterations,
                        Some(v) => narrow(
                            "postprocessing.spatial.iterations",
                            v,
                            "an integer from 1 to 5",
                        )?,
                    },
                    holes_fill: match p.holes_fill {
                        None => d.holes_fill,
                        Some(v) => narrow(
                            "postprocessing.spatial.holes_fill",
                            v,
                            "an integer from 0 (off) to 5 (unlimited)",
                        )?,
                    },
                })
            }
        };
        let holefilling = match raw.holefilling {
            RawStage::Off => None,
            RawStage::Defaults => Some(HoleFillingConfig::default()),
            RawStage::Params(p) => Some(HoleFillingConfig {
                mode: p.mode.unwrap_or_else(|| HoleFillingConfig::default().mode),
            }),
        };
        let flying_pixels = match raw.flying_pixels {
            RawStage::Off => None,
            RawStage::Defaults => Some(FlyingPixelsConfig::default()),
            // f64 -> f32 as the filter computes; range checked below.
            RawStage::Params(p) => Some(FlyingPixelsConfig {
                step: p.step.map_or(FlyingPixels::DEFAULT_STEP, |s| s as f32),
            }),
        };
        let config = Self {
            decimation,
            spatial,
            holefilling,
            flying_pixels,
        };
        config.validate()?;
        Ok(config)
    }
}

/// The configured chain with every stage's buffers, reused from frame to frame.
#[derive(Debug, Clone)]
pub struct PostProcessing {
    config: PostProcessingConfig,
    decimation: Option<Decimation>,
    flying_pixels: Option<FlyingPixels>,
    spatial: Option<(DepthToDisparity, SpatialFilter, DisparityToDepth)>,
    hole_filling: Option<HoleFilling>,
    work: DepthFrame,
}

impl PostProcessing {
    /// The chain of `config` for a camera with this stereo baseline (millimetres; the
    /// D415's is 55), used by the depth <-> disparity conversion around the spatial
    /// filter; `None` for a camera without a stereo pair, which cannot have the spatial
    /// filter.
    pub fn new(
        config: &PostProcessingConfig,
        baseline_mm: Option<f32>,
    ) -> Result<Self, FilterError> {
        let decimation = config
            .decimation
            .map(|d| Decimation::new(d.magnitude))
            .transpose()?;
        let flying_pixels = config
            .flying_pixels
            .map(|f| FlyingPixels::new(f.step))
            .transpose()?;
        let spatial = match config.spatial {
            None => None,
            Some(s) => Some((
                DepthToDisparity::new(baseline_mm.ok_or(FilterError::NoStereoPair)?)?,
                SpatialFilter::new(s.into())?,
                DisparityToDepth::new(),
            )),
        };
        Ok(Self {
            config: *config,
            decimation,
            flying_pixels,
            spatial,
            hole_filling: config.holefilling.map(|h| HoleFilling::new(h.mode)),
            work: empty_frame(),
        })
    }

    /// The configuration the chain runs.
    pub fn config(&self) -> &PostProcessingConfig {
        &self.config
    }

    /// Runs the enabled stages on `frame` and returns the result with its intrinsics
    /// (`frame` itself when no stage is on).
    pub fn process<'a>(
        &'a mut self,
        frame: &'a DepthFrame,
        intrinsics: &Intrinsics,
    ) -> Result<(&'a DepthFrame, Intrinsics), FilterError> {
        check_frame(frame, Some(intrinsics))?;
        let Self {
            decimation,
            flying_pixels,
            spatial,
            hole_filling,
            work,
            ..
        } = self;
        let (mut current, mut k) = (frame, *intrinsics);
        if let Some(d) = decimation {
            (current, k) = d.process(current, &k)?;
        }
        if let Some(f) = flying_pixels {
            (current, k) = f.process(current, &k)?;
        }
        let mutable: Option<&'a mut DepthFrame> = match spatial {
            Some((to_disparity, filter, to_depth)) => {
                let disparity = to_disparity.process(current, &k)?;
                filter.apply(disparity)?;
                Some(to_depth.process(disparity))
            }
            None => None,
        };
        let Some(holes) = hole_filling else {
            return Ok((mutable.map_or(current, |m| &*m), k));
        };
        let target = match mutable {
            Some(m) => m,
            None => {
                copy_compact(current, work);
                work
            }
        };
        holes.apply_in_place(target)?;
        Ok((target, k))
    }
}
