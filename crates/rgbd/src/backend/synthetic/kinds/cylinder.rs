//! `[[cylinder]]`: a vertical cylinder standing on the floor.

use std::fmt::Write as _;
use std::sync::Arc;

use serde::Deserialize;

use super::{Object, ObjectKind};
use crate::backend::synthetic::fields::{
    Finish, SceneError, Timeline, TimelineFile, check_place, check_surface, positive, write_finish,
    write_timeline,
};
use crate::backend::synthetic::ray::{Face, Interval, Primitive, V3, across_axis, capped, slab};

/// The color of a cylinder (or a tube) that names none.
pub(crate) fn default_color() -> [u8; 3] {
    [70, 110, 160]
}

/// A vertical cylinder standing on the floor.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(from = "CylinderFile")]
pub struct Cylinder {
    /// Radius, metres.
    pub radius: f64,
    /// Height, metres.
    pub height: f64,
    /// Centre on the floor, (x, y) metres.
    pub center: [f64; 2],
    /// Color.
    pub color: [u8; 3],
    /// How its surface returns the D415's light.
    pub finish: Finish,
    /// When it is there, and whether it slides in.
    pub timeline: Timeline,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct CylinderFile {
    radius: f64,
    height: f64,
    center: [f64; 2],
    #[serde(default = "default_color")]
    color: [u8; 3],
    #[serde(flatten)]
    finish: Finish,
    #[serde(flatten)]
    timeline: TimelineFile,
}

impl From<CylinderFile> for Cylinder {
    fn from(f: CylinderFile) -> Self {
        Self {
            radius: f.radius,
            height: f.height,
            center: f.center,
            color: f.color,
            finish: f.finish,
            timeline: f.timeline.into(),
        }
    }
}

impl Object for Cylinder {
    fn kind(&self) -> ObjectKind {
        ObjectKind::Cylinder
    }

    fn validate(&self, at: &dyn Fn(&str) -> String) -> Result<(), SceneError> {
        positive(&at("radius"), &[self.radius])?;
        positive(&at("height"), &[self.height])?;
        check_place(at, &self.center, None)?;
        check_surface(at, &self.finish, &self.timeline)
    }

    /// A square as wide as the cylinder, along world x.
    fn footprint(&self) -> ([f64; 2], f64) {
        let side = 2.0 * self.radius;
        ([side, side], 0.0)
    }

    fn height(&self) -> f64 {
        self.height
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

    fn place_mut(&mut self) -> (&mut [f64; 2], &mut Timeline) {
        (&mut self.center, &mut self.timeline)
    }

    fn primitive(
        &self,
        floor_z: f32,
        _at: &dyn Fn(&str) -> String,
    ) -> Result<Arc<dyn Primitive>, SceneError> {
        Ok(Arc::new(CylPrim {
            center: V3::new(self.center[0] as f32, self.center[1] as f32, floor_z),
            radius: self.radius as f32,
            height: self.height as f32,
        }))
    }

    fn write_toml(&self, out: &mut String) {
        let _ = writeln!(
            out,
            "\n[[cylinder]]\nradius = {:?}\nheight = {:?}\ncenter = {:?}\ncolor = {:?}",
            self.radius, self.height, self.center, self.color
        );
        write_finish(out, &self.finish);
        write_timeline(out, &self.timeline);
    }
}

/// A cylinder as the ray caster sees it.
#[derive(Debug, Clone)]
struct CylPrim {
    center: V3,
    radius: f32,
    height: f32,
}

impl Primitive for CylPrim {
    fn interval(&self, o: &V3, d: &V3) -> Option<Interval> {
        let p = o - self.center;
        let across = across_axis([p.x, p.y], [d.x, d.y], self.radius)?;
        let along = slab(p.z, d.z, 0.0, self.height)?;
        capped(across, along, Face::Z)
    }

    fn normal(&self, face: Face, o: &V3, d: &V3, t: f32) -> V3 {
        if face == Face::Side {
            let q = o + d * t - self.center;
            V3::new(q.x, q.y, 0.0) / self.radius
        } else {
            V3::new(0.0, 0.0, 1.0)
        }
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
        let (radius, height) = (self.radius, self.height);
        (
            self.center + V3::new(0.0, 0.0, height / 2.0),
            (radius * radius + height * height / 4.0).sqrt(),
        )
    }
}
