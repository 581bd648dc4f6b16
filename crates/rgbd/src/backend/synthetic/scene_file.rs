//! A scene written back as a scene file ([`Scene::to_toml`]), so a generated scene (the
//! lane or the certification set) can be served, looked at and changed by hand.

use std::fmt::Write as _;

use super::fields::{lower, quoted, write_timeline};
use super::scene::Scene;

impl Scene {
    /// The scene as a scene file: [`Scene::from_toml`] of it gives the same scene (a
    /// `seed` above `i64::MAX`, which TOML's integers cannot hold, excepted).
    pub fn to_toml(&self) -> String {
        let mut out = String::new();
        let _ = writeln!(out, "seed = {}", self.seed);
        let _ = writeln!(
            out,
            "\n[floor]\nz = {:?}\ncolor = {:?}",
            self.floor.z, self.floor.color
        );
        for c in &self.cameras {
            let _ = writeln!(
                out,
                "\n[[camera]]\nserial = {}\nposition = {:?}\nlook_at = {:?}",
                quoted(&c.serial.to_string()),
                c.position,
                c.look_at
            );
            if let Some(up) = c.up {
                let _ = writeln!(out, "up = {up:?}");
            }
            let _ = writeln!(
                out,
                "noise = {}\ncalibrated = {}",
                quoted(&lower(c.noise)),
                c.calibrated
            );
            if let Some(s) = c.stall_s {
                let _ = writeln!(out, "stall_s = {s:?}");
            }
            let s = &c.color_sensor;
            let _ = writeln!(
                out,
                "color_sensor = {{ noise = {:?}, blur_px = {:?}, exposure = {:?} }}",
                s.noise, s.blur_px, s.exposure
            );
        }
        for (_, o) in self.objects() {
            o.write_toml(&mut out);
        }
        for m in &self.markers {
            let _ = writeln!(
                out,
                "\n[[marker]]\nfamily = {}\nid = {}\nsize = {:?}\ncenter = {:?}\nyaw_deg = {:?}",
                quoted(&m.family),
                m.id,
                m.size,
                m.center,
                m.yaw_deg
            );
            write_timeline(&mut out, &m.timeline);
        }
        out
    }
}
