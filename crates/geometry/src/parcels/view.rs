//! What a camera sees of the table: its pose and pinhole intrinsics.

use crate::{Point3, Transform};

/// What a camera sees: its pose and pinhole intrinsics (the depth stream's).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct View {
    /// The camera's frame to the common frame.
    pub to_common: Transform,
    /// Focal lengths, pixels.
    pub fx: f32,
    /// See `fx`.
    pub fy: f32,
    /// Principal point, pixels.
    pub ppx: f32,
    /// See `ppx`.
    pub ppy: f32,
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
}

impl View {
    /// A pinhole camera at the pose `to_common` (its frame to the common frame: x right,
    /// y down, z along the view) with focal lengths `fx`, `fy` and principal point
    /// `ppx`, `ppy` (pixels), its image `width` x `height` pixels.
    pub fn pinhole(
        to_common: Transform,
        fx: f32,
        fy: f32,
        ppx: f32,
        ppy: f32,
        width: u32,
        height: u32,
    ) -> Self {
        Self {
            to_common,
            fx,
            fy,
            ppx,
            ppy,
            width,
            height,
        }
    }

    /// Whether `p` (common frame) lies in front of the camera and projects at least
    /// `margin_px` inside the image.
    pub fn sees(&self, p: &Point3, margin_px: f32) -> bool {
        let Some(inverse) = self.to_common.linear.try_inverse() else {
            return false;
        };
        let q = inverse * (p.coords - self.to_common.translation);
        if q.z <= 0.0 {
            return false;
        }
        let u = self.fx * q.x / q.z + self.ppx;
        let v = self.fy * q.y / q.z + self.ppy;
        u >= margin_px
            && v >= margin_px
            && u <= self.width as f32 - margin_px
            && v <= self.height as f32 - margin_px
    }
}

impl View {
    /// The footprint on the horizontal plane through `p` (common frame) of the pixel
    /// that sees `p`: how far the plane's point moves (x, y, metres) from one pixel to
    /// the next along the image's u and along its v. `None` when the camera does not
    /// have `p` in its image.
    pub fn footprint(&self, p: &Point3) -> Option<[[f64; 2]; 2]> {
        if !self.sees(p, 0.0) {
            return None;
        }
        let inverse = self.to_common.linear.try_inverse()?;
        let q = inverse * (p.coords - self.to_common.translation);
        let (u, v) = (
            self.fx * q.x / q.z + self.ppx,
            self.fy * q.y / q.z + self.ppy,
        );
        let on_plane = |u: f32, v: f32| {
            let ray = self.to_common.linear
                * nalgebra::Vector3::new((u - self.ppx) / self.fx, (v - self.ppy) / self.fy, 1.0);
            let t = (p.z - self.to_common.translation.z) / ray.z;
            (t.is_finite() && t > 0.0).then(|| self.to_common.translation + ray * t)
        };
        let (here, right, down) = (
            on_plane(u, v)?,
            on_plane(u + 1.0, v)?,
            on_plane(u, v + 1.0)?,
        );
        let d = |a: nalgebra::Vector3<f32>| [f64::from(a.x - here.x), f64::from(a.y - here.y)];
        Some([d(right), d(down)])
    }
}

/// The share of the axis-aligned rectangle `min`..`max` on the floor (metres) that the
/// upright box of `d` (its footprint, from the floor up to its height) covers or hides
/// from at least one of `views`: every ray of a camera that meets the box, its lid or a
/// wall, would meet the floor within the footprint or the box's shadow from the camera's
/// eye (the top corners projected from the eye onto the floor). A part of the table
/// whose pixels returned no depth and whose rays meet the floor there is explained by the
/// box (a wall at a grazing angle, a glare on the lid), not another parcel.
pub fn hidden_share(d: &crate::Dimensions, views: &[View], min: [f64; 2], max: [f64; 2]) -> f64 {
    use geo::{Area, BooleanOps as _, ConvexHull as _, MultiPoint, MultiPolygon, Rect};
    let rect = Rect::new((min[0], min[1]), (max[0], max[1])).to_polygon();
    let area = rect.unsigned_area();
    let h = d.height_mm / 1e3;
    if area <= 0.0 || h <= 0.0 {
        return 0.0;
    }
    let mut hidden: Option<MultiPolygon<f64>> = None;
    for v in views {
        let Some(corners) = with_shadow(d, v) else {
            continue;
        };
        let hull = MultiPolygon::new(vec![
            MultiPoint::from(corners.map(|c| (c[0], c[1])).to_vec()).convex_hull(),
        ]);
        hidden = Some(match hidden {
            Some(h) => h.union(&hull),
            None => hull,
        });
    }
    hidden.map_or(0.0, |h| h.intersection(&rect).unsigned_area() / area)
}

/// The axis-aligned rectangle (min, max, metres) around what the upright box of `d`
/// covers or hides from `views` (see [`hidden_share`]): every floor point a ray that
/// meets the box would reach lies inside it. `None` without a camera above the box.
pub fn hidden_bounds(d: &crate::Dimensions, views: &[View]) -> Option<([f64; 2], [f64; 2])> {
    let points: Vec<[f64; 2]> = views
        .iter()
        .filter_map(|v| with_shadow(d, v))
        .flatten()
        .collect();
    let first = points.first()?;
    Some(points.iter().fold((*first, *first), |(lo, hi), p| {
        (
            [lo[0].min(p[0]), lo[1].min(p[1])],
            [hi[0].max(p[0]), hi[1].max(p[1])],
        )
    }))
}

/// The footprint's corners of the upright box of `d` and their shadows on the floor
/// from `v`'s eye (the top corners projected from the eye), `None` when the eye is not
/// above the box's top.
fn with_shadow(d: &crate::Dimensions, v: &View) -> Option<[[f64; 2]; 8]> {
    let eye = v.to_common.translation.map(f64::from);
    let h = d.height_mm / 1e3;
    if eye.z <= h {
        return None;
    }
    let scale = eye.z / (eye.z - h);
    let mut out = [[0.0; 2]; 8];
    for (k, c) in d.corners_m.iter().enumerate() {
        out[2 * k] = *c;
        out[2 * k + 1] = [
            eye.x + (c[0] - eye.x) * scale,
            eye.y + (c[1] - eye.y) * scale,
        ];
    }
    Some(out)
}
