//! `[[tube]]`: a cylinder lying on the floor, its axis horizontal.

use std::fmt::Write as _;
use std::sync::Arc;

use serde::Deserialize;

use super::cylinder::default_color;
use super::{Object, ObjectKind};
use crate::backend::synthetic::fields::{
    Finish, SceneError, Timeline, TimelineFile, check_place, check_surface, positive, write_finish,
    write_timeline,
};
use crate::backend::synthetic::ray::{
    Face, Interval, Primitive, V3, across_axis, capped, from_local, slab, to_local,
};

/// A tube lying on the floor: a cylinder whose axis is horizontal.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(from = "TubeFile")]
pub struct Tube {
    /// Radius, metres.
    pub radius: f64,
    /// Length along its axis, metres.
    pub length: f64,
    /// Centre of its footprint on the floor, (x, y) metres.
    pub center: [f64; 2],
    /// Direction of its axis, degrees counter-clockwise from world x.
    pub yaw_deg: f64,
    /// Color.
    pub color: [u8; 3],
    /// How its surface returns the D415's light.
    pub finish: Finish,
    /// When it is there, and whether it slides in.
    pub timeline: Timeline,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct TubeFile {
    radius: f64,
    length: f64,
    center: [f64; 2],
    #[serde(default)]
    yaw_deg: f64,
    #[serde(default = "default_color")]
    color: [u8; 3],
    #[serde(flatten)]
    finish: Finish,
    #[serde(flatten)]
    timeline: TimelineFile,
}

impl From<TubeFile> for Tube {
    fn from(f: TubeFile) -> Self {
        Self {
            radius: f.radius,
            length: f.length,
            center: f.center,
            yaw_deg: f.yaw_deg,
            color: f.color,
            finish: f.finish,
            timeline: f.timeline.into(),
        }
    }
}

impl Object for Tube {
    fn kind(&self) -> ObjectKind {
        ObjectKind::Tube
    }

    fn validate(&self, at: &dyn Fn(&str) -> String) -> Result<(), SceneError> {
        positive(&at("radius"), &[self.radius])?;
        positive(&at("length"), &[self.length])?;
        check_place(at, &self.center, Some(self.yaw_deg))?;
        check_surface(at, &self.finish, &self.timeline)
    }

    fn footprint(&self) -> ([f64; 2], f64) {
        ([self.length, 2.0 * self.radius], self.yaw_deg)
    }

    fn height(&self) -> f64 {
        2.0 * self.radius
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
        let yaw = (self.yaw_deg as f32).to_radians();
        Ok(Arc::new(TubePrim {
            center: V3::new(self.center[0] as f32, self.center[1] as f32, floor_z),
            cos: yaw.cos(),
            sin: yaw.sin(),
            half: self.length as f32 / 2.0,
            radius: self.radius as f32,
        }))
    }

    fn write_toml(&self, out: &mut String) {
        let _ = writeln!(
            out,
            "\n[[tube]]\nradius = {:?}\nlength = {:?}\ncenter = {:?}\nyaw_deg = {:?}\ncolor = {:?}",
            self.radius, self.length, self.center, self.yaw_deg, self.color
        );
        write_finish(out, &self.finish);
        write_timeline(out, &self.timeline);
    }
}

/// A tube as the ray caster sees it, its axis along local x.
#[derive(Debug, Clone)]
struct TubePrim {
    /// Footprint centre on the floor.
    center: V3,
    cos: f32,
    sin: f32,
    /// Half its length.
    half: f32,
    radius: f32,
}

impl Primitive for TubePrim {
    #[inline(never)]
    fn interval(&self, o: &V3, d: &V3) -> Option<Interval> {
        let p = to_local(self.cos, self.sin, &(o - self.center)) - V3::new(0.0, 0.0, self.radius);
        let ld = to_local(self.cos, self.sin, d);
        let across = across_axis([p.y, p.z], [ld.y, ld.z], self.radius)?;
        let along = slab(p.x, ld.x, -self.half, self.half)?;
        capped(across, along, Face::X)
    }

    fn normal(&self, face: Face, o: &V3, d: &V3, t: f32) -> V3 {
        if face == Face::Side {
            let q = to_local(self.cos, self.sin, &(o + d * t - self.center));
            let n = V3::new(0.0, q.y, q.z - self.radius) / self.radius;
            from_local(self.cos, self.sin, &n)
        } else {
            // An end cap, across the axis.
            let nx = -to_local(self.cos, self.sin, d).x.signum();
            from_local(self.cos, self.sin, &V3::new(nx, 0.0, 0.0))
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
        let (half, radius) = (self.half, self.radius);
        (
            self.center + V3::new(0.0, 0.0, radius),
            (half * half + radius * radius).sqrt(),
        )
    }
}
