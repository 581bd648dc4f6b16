//! A scene written back as a scene file ([`Scene::to_toml`]), so a generated scene (the
//! lane or the certification set) can be served, looked at and changed by hand.

use std::fmt::Write as _;

use super::scene::{Finish, Scene, Timeline};

/// `text` as a TOML basic string.
fn quoted(text: &str) -> String {
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
fn lower(value: impl std::fmt::Debug) -> String {
    format!("{value:?}").to_lowercase()
}

fn finish(out: &mut String, f: &Finish) {
    let _ = writeln!(
        out,
        "reflectivity = {:?}\ngloss = {:?}",
        f.reflectivity, f.gloss
    );
}

fn timeline(out: &mut String, t: &Timeline) {
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
        for b in &self.boxes {
            let _ = writeln!(
                out,
                "\n[[box]]\nsize = {:?}\ncenter = {:?}\nyaw_deg = {:?}\ncolor = {:?}",
                b.size, b.center, b.yaw_deg, b.color
            );
            if let Some(l) = &b.label {
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
            finish(&mut out, &b.finish);
            timeline(&mut out, &b.timeline);
        }
        for c in &self.cylinders {
            let _ = writeln!(
                out,
                "\n[[cylinder]]\nradius = {:?}\nheight = {:?}\ncenter = {:?}\ncolor = {:?}",
                c.radius, c.height, c.center, c.color
            );
            finish(&mut out, &c.finish);
            timeline(&mut out, &c.timeline);
        }
        for t in &self.tubes {
            let _ = writeln!(
                out,
                "\n[[tube]]\nradius = {:?}\nlength = {:?}\ncenter = {:?}\nyaw_deg = {:?}\ncolor = {:?}",
                t.radius, t.length, t.center, t.yaw_deg, t.color
            );
            finish(&mut out, &t.finish);
            timeline(&mut out, &t.timeline);
        }
        for b in &self.bags {
            let _ = writeln!(
                out,
                "\n[[bag]]\nsize = {:?}\ncenter = {:?}\nyaw_deg = {:?}\nsag = {:?}\ncolor = {:?}",
                b.size, b.center, b.yaw_deg, b.sag, b.color
            );
            finish(&mut out, &b.finish);
            timeline(&mut out, &b.timeline);
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
            timeline(&mut out, &m.timeline);
        }
        out
    }
}
