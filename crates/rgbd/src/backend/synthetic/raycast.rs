//! Ray casting of a scene: the floor plane, markers printed on it, and each object's
//! primitive (its kind's file in `kinds/` intersects it, behind [`Primitive`]); per-row
//! culling of primitives by their bounding spheres.
//! A [`Stage`] holds a scene prepared once (labels encoded, marker patterns read) and
//! gives the [`World`] of any moment of its timeline.

use std::sync::{Arc, Mutex, PoisonError};

use nalgebra::Matrix3;

use super::fields::{Finish, SceneError, Timeline};
pub(crate) use super::ray::V3;
use super::ray::{Face, Interval, Primitive, T_EPS};
use super::scene::Scene;
use crate::intrinsics::{Intrinsics, Pose};

/// Which surface a ray hit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum Surface {
    Floor,
    /// A primitive (index into `World::prims`); `top` when its upward face was hit.
    Prim {
        index: usize,
        top: bool,
    },
}

/// The nearest intersection of a ray.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Hit {
    /// Ray parameter; for camera rays `(a, b, 1)` rotated into the world this is the
    /// depth along the camera's z axis.
    pub(crate) t: f32,
    /// Unit normal at the hit, world frame (not oriented towards the ray).
    pub(crate) normal: V3,
    pub(crate) surface: Surface,
}

#[derive(Debug, Clone)]
struct Prim {
    shape: Arc<dyn Primitive>,
    color: [f32; 3],
    /// The surface's finish; `None` for the default (matte, always enough light).
    finish: Option<Surfacing>,
    sphere_center: V3,
    sphere_radius: f32,
}

/// A non-default finish, as the renderer uses it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Surfacing {
    /// Share of the infrared light sent back, 0..=1.
    pub(crate) reflectivity: f32,
    /// How mirror-like, 0..=1.
    pub(crate) gloss: f32,
}

impl Surfacing {
    fn of(finish: &Finish) -> Option<Self> {
        (!finish.is_default()).then_some(Self {
            reflectivity: finish.reflectivity as f32,
            gloss: finish.gloss as f32,
        })
    }
}

impl Prim {
    /// Unit normal (world) where the ray `o + t d` enters through `face` at `t`, and
    /// whether that is an upward face.
    fn normal(&self, face: Face, o: &V3, d: &V3, t: f32) -> (V3, bool) {
        if face == Face::Z {
            (V3::new(0.0, 0.0, -d.z.signum()), d.z < 0.0)
        } else {
            (self.shape.normal(face, o, d, t), false)
        }
    }
}

/// A marker on the floor, its pattern read from the family's table.
#[derive(Debug, Clone)]
struct FloorMarker {
    center: [f32; 2],
    cos: f32,
    sin: f32,
    /// Side of one pattern cell, metres.
    cell: f32,
    pattern: Arc<markers::Pattern>,
}

impl FloorMarker {
    /// The pattern cell under a floor point, as (column, row) from the top-left; `None`
    /// off the marker.
    fn cell_at(&self, p: &V3) -> Option<(usize, usize)> {
        let (dx, dy) = (p.x - self.center[0], p.y - self.center[1]);
        // Into the marker frame: x along the rows, y towards the top row.
        let x = self.cos * dx + self.sin * dy;
        let y = -self.sin * dx + self.cos * dy;
        let half = self.cell * self.pattern.cells as f32 / 2.0;
        let col = ((x + half) / self.cell).floor();
        let row = ((half - y) / self.cell).floor();
        let n = self.pattern.cells as f32;
        ((0.0..n).contains(&col) && (0.0..n).contains(&row)).then_some((col as usize, row as usize))
    }
}

/// A scene at one moment, prepared for ray casting (f32, labels encoded).
#[derive(Debug)]
pub(crate) struct World {
    floor_z: f32,
    floor_color: [f32; 3],
    prims: Vec<Prim>,
    markers: Vec<FloorMarker>,
    /// Whether any primitive has a finish other than the default.
    finished: bool,
}

fn rgb(c: [u8; 3]) -> [f32; 3] {
    c.map(f32::from)
}

/// An object of a stage: prepared at its centre, placed on the timeline.
#[derive(Debug)]
struct Staged<T> {
    item: T,
    center: [f64; 2],
    timeline: Timeline,
    /// A box's label's own timeline (the label is part of `item`).
    label: Option<Timeline>,
}

/// Where each object of a stage is at one moment: its position (`None`: absent) and
/// whether its label is on. Equal placements make the same world.
#[derive(Debug, Clone, PartialEq)]
struct Placement {
    at: Option<[f64; 2]>,
    label: bool,
}

/// A scene prepared once for every moment of its timeline. A scene without timelines
/// has one world; otherwise the world of a moment is built from the prepared objects
/// (moved, left out) when it differs from the last one asked for, so a scene where
/// nothing moves costs no rebuilding per frame.
#[derive(Debug)]
pub(crate) struct Stage {
    floor_z: f32,
    floor_color: [f32; 3],
    prims: Vec<Staged<Prim>>,
    markers: Vec<Staged<FloorMarker>>,
    /// The world for the placements of the last moment asked for.
    posed: Mutex<(Vec<Placement>, Arc<World>)>,
    timed: bool,
}

impl Stage {
    pub(crate) fn new(scene: &Scene) -> Result<Self, SceneError> {
        scene.validate()?;
        let floor_z = scene.floor.z as f32;
        let mut prims = Vec::new();
        for (i, o) in scene.objects() {
            let shape = o.primitive(floor_z, &|f: &str| format!("{}[{i}].{f}", o.kind().name()))?;
            let (sphere_center, sphere_radius) = shape.sphere();
            prims.push(Staged {
                item: Prim {
                    shape,
                    color: rgb(o.color()),
                    finish: Surfacing::of(o.finish()),
                    sphere_center,
                    sphere_radius,
                },
                center: o.center(),
                timeline: *o.timeline(),
                label: o.label().map(|l| l.timeline()),
            });
        }
        let mut markers = Vec::with_capacity(scene.markers.len());
        for (i, m) in scene.markers.iter().enumerate() {
            let invalid = |reason: String| SceneError::Invalid {
                field: format!("marker[{i}]"),
                reason,
            };
            let family: markers::Family = m.family.parse().map_err(|e| invalid(format!("{e}")))?;
            let pattern = family
                .pattern(m.id)
                .ok_or_else(|| invalid(format!("{family} has no id {}", m.id)))?;
            let yaw = (m.yaw_deg as f32).to_radians();
            markers.push(Staged {
                item: FloorMarker {
                    center: [m.center[0] as f32, m.center[1] as f32],
                    cos: yaw.cos(),
                    sin: yaw.sin(),
                    cell: m.size as f32 / pattern.black_cells as f32,
                    pattern: Arc::new(pattern),
                },
                center: m.center,
                timeline: m.timeline,
                label: None,
            });
        }
        let mut stage = Self {
            floor_z,
            floor_color: rgb(scene.floor.color),
            prims,
            markers,
            posed: Mutex::new((Vec::new(), Arc::new(World::empty()))),
            timed: scene.is_timed(),
        };
        let placements = stage.placements(0.0);
        let world = stage.build(&placements);
        stage.posed = Mutex::new((placements, Arc::new(world)));
        Ok(stage)
    }

    /// The world at scene time `t_s` (seconds).
    pub(crate) fn world_at(&self, t_s: f64) -> Arc<World> {
        let mut posed = self.posed.lock().unwrap_or_else(PoisonError::into_inner);
        if !self.timed {
            return Arc::clone(&posed.1);
        }
        let placements = self.placements(t_s);
        if posed.0 != placements {
            let world = Arc::new(self.build(&placements));
            *posed = (placements, world);
        }
        Arc::clone(&posed.1)
    }

    /// The world with every object where the scene puts it, whatever its timeline, and
    /// no labels: primitive `i` is the object of [`Scene::truths`]`[i]`.
    pub(crate) fn every_object(&self) -> World {
        let placements: Vec<Placement> = self
            .prims
            .iter()
            .map(|p| p.center)
            .chain(self.markers.iter().map(|m| m.center))
            .map(|at| Placement {
                at: Some(at),
                label: false,
            })
            .collect();
        self.build(&placements)
    }

    /// Where every object (prims, then markers) is at `t_s`.
    fn placements(&self, t_s: f64) -> Vec<Placement> {
        self.prims
            .iter()
            .map(|p| p.placement(t_s))
            .chain(self.markers.iter().map(|m| m.placement(t_s)))
            .collect()
    }

    /// The world of `placements` (as [`Stage::placements`] gives them).
    fn build(&self, placements: &[Placement]) -> World {
        let (of_prims, of_markers) = placements.split_at(self.prims.len());
        let prims: Vec<Prim> = self
            .prims
            .iter()
            .zip(of_prims)
            .filter_map(|(p, place)| {
                let at = place.at?;
                let mut prim = p.item.clone();
                if at != p.center {
                    let to = V3::new(at[0] as f32, at[1] as f32, self.floor_z);
                    prim.sphere_center += to - prim.shape.center();
                    prim.shape = prim.shape.moved(to);
                }
                if !place.label
                    && let Some(bare) = prim.shape.unlabelled()
                {
                    prim.shape = bare;
                }
                Some(prim)
            })
            .collect();
        let markers = self
            .markers
            .iter()
            .zip(of_markers)
            .filter_map(|(m, place)| {
                let at = place.at?;
                let mut marker = m.item.clone();
                marker.center = [at[0] as f32, at[1] as f32];
                Some(marker)
            })
            .collect();
        World {
            floor_z: self.floor_z,
            floor_color: self.floor_color,
            finished: prims.iter().any(|p| p.finish.is_some()),
            prims,
            markers,
        }
    }
}

impl<T> Staged<T> {
    fn placement(&self, t_s: f64) -> Placement {
        let at = self.timeline.position(self.center, t_s);
        Placement {
            at,
            label: at.is_some() && self.label.is_some_and(|l| l.present(t_s)),
        }
    }
}

impl World {
    fn empty() -> Self {
        Self {
            floor_z: 0.0,
            floor_color: [0.0; 3],
            prims: Vec::new(),
            markers: Vec::new(),
            finished: false,
        }
    }

    /// Whether any primitive has a finish other than the default.
    pub(crate) fn finished(&self) -> bool {
        self.finished
    }

    /// The finish of what `hit` hit; `None` for the floor and default finishes.
    pub(crate) fn surfacing(&self, hit: &Hit) -> Option<Surfacing> {
        match hit.surface {
            Surface::Prim { index, .. } => self.prims[index].finish,
            Surface::Floor => None,
        }
    }

    /// Ray parameter at which `o + t d` meets the floor, if ahead.
    pub(crate) fn floor_t(&self, o: &V3, d: &V3) -> Option<f32> {
        if d.z.abs() < 1e-12 {
            return None;
        }
        let t = (self.floor_z - o.z) / d.z;
        (t > T_EPS).then_some(t)
    }

    /// Nearest hit of the ray `o + t d` among the floor and the primitives `candidates`.
    pub(crate) fn trace(
        &self,
        o: &V3,
        d: &V3,
        candidates: impl Iterator<Item = usize>,
    ) -> Option<Hit> {
        let mut best = self.floor_t(o, d).map(|t| Hit {
            t,
            normal: V3::new(0.0, 0.0, 1.0),
            surface: Surface::Floor,
        });
        let mut nearest: Option<(usize, Interval)> = None;
        for index in candidates {
            let Some(iv) = self.prims[index].shape.interval(o, d) else {
                continue;
            };
            let ahead_of_floor = best.is_none_or(|b| iv.near < b.t);
            let ahead_of_prims = nearest.as_ref().is_none_or(|(_, n)| iv.near < n.near);
            if iv.near > T_EPS && ahead_of_floor && ahead_of_prims {
                nearest = Some((index, iv));
            }
        }
        if let Some((index, iv)) = nearest {
            let (normal, top) = self.prims[index].normal(iv.face, o, d, iv.near);
            best = Some(Hit {
                t: iv.near,
                normal,
                surface: Surface::Prim { index, top },
            });
        }
        best
    }

    /// All primitive indices.
    pub(crate) fn all(&self) -> std::ops::Range<usize> {
        0..self.prims.len()
    }

    /// Whether the segment from `from` to `to` passes through the floor or a primitive
    /// of `candidates` (the start point itself does not count, nor does leaving a
    /// surface the start point lies on).
    pub(crate) fn occluded(
        &self,
        from: &V3,
        to: &V3,
        candidates: impl Iterator<Item = usize>,
    ) -> bool {
        let d = to - from;
        if self.floor_t(from, &d).is_some_and(|t| t < 1.0 - T_EPS) {
            return true;
        }
        candidates.into_iter().any(|i| {
            self.prims[i]
                .shape
                .interval(from, &d)
                .is_some_and(|iv| iv.far > T_EPS && iv.near < 1.0 - T_EPS)
        })
    }

    /// Where a ray straight down through the floor point (`x`, `y`) first meets primitive
    /// `index` alone (its top over that point); `None` when it misses it.
    pub(crate) fn top_of(&self, index: usize, x: f32, y: f32) -> Option<V3> {
        let prim = &self.prims[index];
        prim.shape
            .top_over(x, y, prim.sphere_center.z + prim.sphere_radius + 1.0)
    }

    /// Whether a hit at `point` lies on a label (whose modules need more than one ray
    /// per pixel to be drawn as a camera sees them).
    pub(crate) fn on_label(&self, hit: &Hit, point: &V3) -> bool {
        match hit.surface {
            Surface::Prim { index, top: true } => self.prims[index].shape.on_label(point),
            _ => false,
        }
    }

    /// The marker under a floor point and its cell there.
    fn marker_at(&self, point: &V3) -> Option<(&FloorMarker, (usize, usize))> {
        self.markers
            .iter()
            .find_map(|m| m.cell_at(point).map(|cell| (m, cell)))
    }

    /// Whether a floor point lies on a marker (drawn, like labels, with more than one
    /// ray per pixel).
    pub(crate) fn on_marker(&self, point: &V3) -> bool {
        self.marker_at(point).is_some()
    }

    /// Shaded color of a hit, 0..=255 per channel (not rounded); `light` is the unit
    /// direction towards the light.
    pub(crate) fn shade(&self, hit: &Hit, point: &V3, ray: &V3, light: &V3) -> [f32; 3] {
        let base = match hit.surface {
            Surface::Floor => match self.marker_at(point) {
                Some((m, (col, row))) if m.pattern.is_white(col, row) => LABEL_WHITE,
                Some(_) => LABEL_BLACK,
                None => self.floor_color,
            },
            Surface::Prim { index, top } => {
                let prim = &self.prims[index];
                if top && prim.shape.on_label(point) {
                    if prim.shape.label_dark(point) {
                        LABEL_BLACK
                    } else {
                        LABEL_WHITE
                    }
                } else {
                    prim.color
                }
            }
        };
        self.lit(hit, base, ray, light)
    }

    /// The floor's own color (where no marker lies) shaded for a floor `hit` seen along
    /// `ray`: the same everywhere, as the floor is flat and evenly lit.
    pub(crate) fn shade_bare_floor(&self, hit: &Hit, ray: &V3, light: &V3) -> [f32; 3] {
        self.lit(hit, self.floor_color, ray, light)
    }

    /// `base` as `hit` shows it along `ray` with the light from `light`.
    fn lit(&self, hit: &Hit, base: [f32; 3], ray: &V3, light: &V3) -> [f32; 3] {
        // Face the normal towards the viewer, then Lambert from a fixed light.
        let n = if hit.normal.dot(ray) > 0.0 {
            -hit.normal
        } else {
            hit.normal
        };
        let lambert = n.dot(light).max(0.0);
        let f = AMBIENT + (1.0 - AMBIENT) * lambert;
        if self.finished {
            let spec = self.highlight(hit, &n, ray, light);
            base.map(|c| (c * f + spec).min(255.0))
        } else {
            base.map(|c| (c * f).min(255.0))
        }
    }

    /// The highlight of the light on a glossy surface (Blinn-Phong), 8-bit levels; 0 on
    /// a matte one. `n` is the normal facing the viewer.
    #[inline(never)]
    fn highlight(&self, hit: &Hit, n: &V3, ray: &V3, light: &V3) -> f32 {
        match self.surfacing(hit) {
            Some(s) if s.gloss > 0.0 => {
                let half = (light - ray.normalize()).normalize();
                s.gloss * HIGHLIGHT * n.dot(&half).max(0.0).powf(HIGHLIGHT_EXPONENT)
            }
            _ => 0.0,
        }
    }

    /// Bounding spheres in a camera's frame (centre, radius), for row culling.
    pub(crate) fn spheres_in(&self, view: &View) -> Vec<(V3, f32)> {
        self.prims
            .iter()
            .map(|p| {
                (
                    view.rot.transpose() * (p.sphere_center - view.origin),
                    p.sphere_radius,
                )
            })
            .collect()
    }
}

/// Labels are printed black on white.
const LABEL_BLACK: [f32; 3] = [25.0, 25.0, 25.0];
const LABEL_WHITE: [f32; 3] = [245.0, 245.0, 245.0];
/// Share of light that reaches every surface.
const AMBIENT: f32 = 0.35;
/// Brightest highlight of a fully glossy surface in the color image, 8-bit levels.
const HIGHLIGHT: f32 = 200.0;
/// Sharpness of the color image's highlight (Blinn-Phong exponent).
const HIGHLIGHT_EXPONENT: f32 = 150.0;

/// Direction towards the light, world frame: high, from +x and -y.
pub(crate) fn light_direction() -> V3 {
    V3::new(0.35, -0.25, 1.0).normalize()
}

/// A pinhole camera placed in the world.
#[derive(Debug, Clone, Copy)]
pub(crate) struct View {
    /// Optical centre, world.
    pub(crate) origin: V3,
    /// Camera -> world rotation (columns: camera x, y, z in the world).
    pub(crate) rot: Matrix3<f32>,
    pub(crate) k: Intrinsics,
}

/// One primitive that a row of rays may hit, with the columns that may hit it.
#[derive(Debug, Clone, Copy)]
pub(crate) struct RowCandidate {
    pub(crate) prim: usize,
    /// First column whose ray may hit the primitive (-1: left of the image).
    pub(crate) u_lo: i32,
    /// Last column whose ray may hit the primitive (`width`: right of the image).
    pub(crate) u_hi: i32,
}

impl View {
    /// The view of a camera with pose `pose` (camera->world), moved by `offset`
    /// (camera frame, metres), with intrinsics `k`.
    pub(crate) fn new(pose: &Pose, offset: [f32; 3], k: Intrinsics) -> Self {
        let r = &pose.rotation;
        let rot = Matrix3::new(
            r[0][0] as f32,
            r[0][1] as f32,
            r[0][2] as f32,
            r[1][0] as f32,
            r[1][1] as f32,
            r[1][2] as f32,
            r[2][0] as f32,
            r[2][1] as f32,
            r[2][2] as f32,
        );
        let t = &pose.translation;
        let origin = V3::new(t[0] as f32, t[1] as f32, t[2] as f32)
            + rot * V3::new(offset[0], offset[1], offset[2]);
        Self { origin, rot, k }
    }

    /// World direction of the ray through (`u`, `v`) with unit camera-z component.
    pub(crate) fn ray(&self, u: f32, v: f32) -> V3 {
        let a = (u - self.k.ppx) / self.k.fx;
        let b = (v - self.k.ppy) / self.k.fy;
        self.rot * V3::new(a, b, 1.0)
    }

    /// (ray at column 0, change per column) for row `v`: ray(u) = base + u * step.
    pub(crate) fn row(&self, v: f32) -> (V3, V3) {
        (self.ray(0.0, v), self.rot.column(0) / self.k.fx)
    }

    /// The primitives that rays of row `v` may hit, with conservative column ranges.
    pub(crate) fn row_candidates(
        &self,
        spheres: &[(V3, f32)],
        v: u32,
        out: &mut Vec<RowCandidate>,
    ) {
        out.clear();
        let w = self.k.width;
        let b = (v as f32 - self.k.ppy) / self.k.fy;
        for (prim, (p, r)) in spheres.iter().enumerate() {
            let all = RowCandidate {
                prim,
                u_lo: -1,
                u_hi: w as i32,
            };
            // Rays (a, b, 1); the sphere is hit iff (p.d)^2 >= (|p|^2 - r^2) |d|^2 with p.d > 0.
            let k = p.norm_squared() - r * r;
            if k <= 0.0 {
                out.push(all);
                continue;
            }
            let q = b * p.y + p.z;
            let qa = p.x * p.x - k;
            if qa >= 0.0 {
                out.push(all);
                continue;
            }
            let half_b = p.x * q;
            let c = q * q - k * (b * b + 1.0);
            let disc = half_b * half_b - qa * c;
            if disc < 0.0 {
                continue;
            }
            let sq = disc.sqrt();
            let (a0, a1) = ((-half_b + sq) / qa, (-half_b - sq) / qa);
            let (a_lo, a_hi) = if a0 < a1 { (a0, a1) } else { (a1, a0) };
            if (a_lo + a_hi) / 2.0 * p.x + q <= 0.0 {
                continue; // behind the camera
            }
            let to_u = |a: f32| a * self.k.fx + self.k.ppx;
            // Columns just outside the image (-1 and `w`) stand for "left of it" and
            // "right of it": a sphere right of the image can still shadow points in it.
            let u_lo = (to_u(a_lo).floor() - 1.0).clamp(-1.0, w as f32) as i32;
            let u_hi = (to_u(a_hi).ceil() + 1.0).clamp(-1.0, w as f32) as i32;
            if u_hi >= 0 {
                out.push(RowCandidate { prim, u_lo, u_hi });
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sliding() -> Scene {
        Scene::from_toml(
            r#"[[box]]
size = [0.2, 0.1, 0.15]
center = [0.0, 0.0]
appear_s = 1.0
from = [0.3, 0.0]
still_s = 2.0
remove_s = 4.0"#,
        )
        .expect("scene")
    }

    #[test]
    fn a_scene_without_timelines_has_one_world() {
        let stage = Stage::new(&Scene::default_demo()).expect("stage");
        let first = stage.world_at(0.0);
        assert!(Arc::ptr_eq(&first, &stage.world_at(1.0e6)));
        assert_eq!(first.prims.len(), 1);
    }

    #[test]
    fn a_world_is_built_again_only_when_something_changed() {
        let stage = Stage::new(&sliding()).expect("stage");
        let before = stage.world_at(0.2);
        assert!(before.prims.is_empty());
        assert!(Arc::ptr_eq(&before, &stage.world_at(0.9)), "nothing there");
        let a = stage.world_at(1.25);
        let b = stage.world_at(1.5);
        assert!(!Arc::ptr_eq(&a, &b), "it slides");
        assert!((a.prims[0].shape.center().x - 0.225).abs() < 1e-6);
        assert!((a.prims[0].sphere_center.x - 0.225).abs() < 1e-6);
        let still = stage.world_at(2.0);
        assert!(Arc::ptr_eq(&still, &stage.world_at(3.5)), "standing still");
        assert_eq!(still.prims[0].shape.center(), V3::zeros());
        assert!(stage.world_at(4.0).prims.is_empty());
    }
}
