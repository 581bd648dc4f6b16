//! `[[box]]`: a box standing on the floor, with an optional barcode label on its top.

use std::fmt::Write as _;
use std::sync::Arc;

use serde::Deserialize;

use super::{Object, ObjectKind, placed};
use crate::backend::synthetic::fields::{
    Finish, SceneError, Timeline, TimelineFile, check_place, check_surface, invalid, lower,
    positive, quoted, write_finish, write_timeline,
};
use crate::backend::synthetic::label::{self, Label, LabelTexture};
use crate::backend::synthetic::ray::{Face, Interval, Primitive, V3, slab, to_local};

/// Longest label text, characters.
pub const MAX_LABEL_CHARS: usize = 256;

/// The color of a box that names none.
pub(crate) fn default_color() -> [u8; 3] {
    [180, 140, 90]
}

/// A box standing on the floor.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(from = "BoxFile")]
pub struct SceneBox {
    /// Length (along x before yaw), width, height in metres.
    pub size: [f64; 3],
    /// Footprint centre on the floor, (x, y) metres.
    pub center: [f64; 2],
    /// Rotation about world z, degrees, counter-clockwise seen from above.
    pub yaw_deg: f64,
    /// Color.
    pub color: [u8; 3],
    /// Optional barcode label on the top face.
    pub label: Option<Label>,
    /// How its surface returns the D415's light.
    pub finish: Finish,
    /// When it is there, and whether it slides in.
    pub timeline: Timeline,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct BoxFile {
    size: [f64; 3],
    center: [f64; 2],
    #[serde(default)]
    yaw_deg: f64,
    #[serde(default = "default_color")]
    color: [u8; 3],
    #[serde(default)]
    label: Option<Label>,
    #[serde(flatten)]
    finish: Finish,
    #[serde(flatten)]
    timeline: TimelineFile,
}

impl From<BoxFile> for SceneBox {
    fn from(f: BoxFile) -> Self {
        Self {
            size: f.size,
            center: f.center,
            yaw_deg: f.yaw_deg,
            color: f.color,
            label: f.label,
            finish: f.finish,
            timeline: f.timeline.into(),
        }
    }
}

impl Object for SceneBox {
    fn kind(&self) -> ObjectKind {
        ObjectKind::Box
    }

    fn validate(&self, at: &dyn Fn(&str) -> String) -> Result<(), SceneError> {
        positive(&at("size"), &self.size)?;
        check_place(at, &self.center, Some(self.yaw_deg))?;
        check_surface(at, &self.finish, &self.timeline)?;
        if let Some(label) = &self.label {
            positive(&at("label.size"), &[label.size])?;
            label
                .timeline()
                .validate(&|f: &str| at(&format!("label.{f}")))?;
            let chars = label.text.chars().count();
            if chars > MAX_LABEL_CHARS {
                return Err(invalid(
                    at("label.text"),
                    format!("at most {MAX_LABEL_CHARS} characters, got {chars}"),
                ));
            }
            let (lx, ly) = label.extent_m();
            if lx > self.size[0] || ly > self.size[1] {
                return Err(invalid(
                    at("label.size"),
                    format!(
                        "a {lx} x {ly} m label does not fit on the {} x {} m top face",
                        self.size[0], self.size[1]
                    ),
                ));
            }
            label::encode(label).map_err(|reason| invalid(at("label.text"), reason))?;
        }
        Ok(())
    }

    fn footprint(&self) -> ([f64; 2], f64) {
        ([self.size[0], self.size[1]], self.yaw_deg)
    }

    fn height(&self) -> f64 {
        self.size[2]
    }

    fn center(&self) -> [f64; 2] {
        self.center
    }

    fn color(&self) -> [u8; 3] {
        self.color
    }

    fn finish(&self) -> &Finish {
        &self.finish
    }

    fn timeline(&self) -> &Timeline {
        &self.timeline
    }

    fn label(&self) -> Option<&Label> {
        self.label.as_ref()
    }

    fn place_mut(&mut self) -> (&mut [f64; 2], &mut Timeline) {
        (&mut self.center, &mut self.timeline)
    }

    /// The box where it stands at `t_s`, its label only if stuck on by then (and not
    /// peeled off), neither with a timeline.
    fn at(&self, t_s: f64) -> Option<Self> {
        let mut b = placed(self, t_s)?;
        b.label = b
            .label
            .take()
            .filter(|l| l.timeline().present(t_s))
            .map(|l| Label {
                appear_s: None,
                remove_s: None,
                ..l
            });
        Some(b)
    }

    fn primitive(
        &self,
        floor_z: f32,
        at: &dyn Fn(&str) -> String,
    ) -> Result<Arc<dyn Primitive>, SceneError> {
        let label = match &self.label {
            Some(l) => {
                let texture =
                    label::encode(l).map_err(|reason| invalid(at("label.text"), reason))?;
                let (lx, ly) = l.extent_m();
                Some((Arc::new(texture), [lx as f32, ly as f32]))
            }
            None => None,
        };
        let yaw = (self.yaw_deg as f32).to_radians();
        Ok(Arc::new(BoxPrim {
            center: V3::new(self.center[0] as f32, self.center[1] as f32, floor_z),
            cos: yaw.cos(),
            sin: yaw.sin(),
            half: [self.size[0] as f32 / 2.0, self.size[1] as f32 / 2.0],
            height: self.size[2] as f32,
            label,
        }))
    }

    fn write_toml(&self, out: &mut String) {
        let _ = writeln!(
            out,
            "\n[[box]]\nsize = {:?}\ncenter = {:?}\nyaw_deg = {:?}\ncolor = {:?}",
            self.size, self.center, self.yaw_deg, self.color
        );
        if let Some(l) = &self.label {
            let mut fields = format!(
                "kind = {}, text = {}, size = {:?}",
                quoted(&lower(l.kind)),
                quoted(&l.text),
                l.size
            );
            for (name, value) in [("appear_s", l.appear_s), ("remove_s", l.remove_s)] {
                if let Some(v) = value {
                    let _ = write!(fields, ", {name} = {v:?}");
                }
            }
            let _ = writeln!(out, "label = {{ {fields} }}");
        }
        write_finish(out, &self.finish);
        write_timeline(out, &self.timeline);
    }
}

/// A box as the ray caster sees it.
#[derive(Debug, Clone)]
struct BoxPrim {
    /// Footprint centre on the floor.
    center: V3,
    cos: f32,
    sin: f32,
    half: [f32; 2],
    height: f32,
    label: Option<(Arc<LabelTexture>, [f32; 2])>,
}

impl BoxPrim {
    fn to_local(&self, v: &V3) -> V3 {
        to_local(self.cos, self.sin, v)
    }
}

impl Primitive for BoxPrim {
    fn interval(&self, o: &V3, d: &V3) -> Option<Interval> {
        let lo = self.to_local(&(o - self.center));
        let ld = self.to_local(d);
        let (x0, x1) = slab(lo.x, ld.x, -self.half[0], self.half[0])?;
        let (y0, y1) = slab(lo.y, ld.y, -self.half[1], self.half[1])?;
        let (z0, z1) = slab(lo.z, ld.z, 0.0, self.height)?;
        let near = x0.max(y0).max(z0);
        let far = x1.min(y1).min(z1);
        if near > far {
            return None;
        }
        let face = if near == z0 {
            Face::Z
        } else if near == x0 {
            Face::X
        } else {
            Face::Y
        };
        Some(Interval { near, far, face })
    }

    fn normal(&self, face: Face, _o: &V3, d: &V3, _t: f32) -> V3 {
        let ld = self.to_local(d);
        let (nx, ny) = if face == Face::X {
            (-ld.x.signum(), 0.0)
        } else {
            (0.0, -ld.y.signum())
        };
        V3::new(
            self.cos * nx - self.sin * ny,
            self.sin * nx + self.cos * ny,
            0.0,
        )
    }

    fn center(&self) -> V3 {
        self.center
    }

    fn moved(&self, center: V3) -> Arc<dyn Primitive> {
        Arc::new(Self {
            center,
            ..self.clone()
        })
    }

    fn sphere(&self) -> (V3, f32) {
        let (half, height) = (self.half, self.height);
        (
            self.center + V3::new(0.0, 0.0, height / 2.0),
            (half[0] * half[0] + half[1] * half[1] + height * height / 4.0).sqrt(),
        )
    }

    fn unlabelled(&self) -> Option<Arc<dyn Primitive>> {
        self.label.is_some().then(|| {
            Arc::new(Self {
                label: None,
                ..self.clone()
            }) as Arc<dyn Primitive>
        })
    }

    fn label_dark(&self, p: &V3) -> bool {
        let Some((texture, extent)) = &self.label else {
            return false;
        };
        let l = self.to_local(&(p - self.center));
        let u = (l.x + extent[0] / 2.0) / extent[0];
        let v = (extent[1] / 2.0 - l.y) / extent[1];
        (0.0..1.0).contains(&u) && (0.0..1.0).contains(&v) && texture.is_dark(u, v)
    }

    fn on_label(&self, p: &V3) -> bool {
        let Some((_, extent)) = &self.label else {
            return false;
        };
        let l = self.to_local(&(p - self.center));
        l.x.abs() <= extent[0] / 2.0 && l.y.abs() <= extent[1] / 2.0
    }
}
