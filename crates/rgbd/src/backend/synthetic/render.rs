//! Rendering of depth and color images from a [`World`], parallel over rows.

use rayon::prelude::*;

use super::d415;
use super::raycast::{Hit, RowCandidate, Surface, Surfacing, V3, View, World, light_direction};
use super::scene::{ColorSensor, Noise};
use crate::frame::ColorFormat;

/// Relative depth step between neighbouring pixels that counts as a discontinuity.
const EDGE_STEP: f32 = 0.02;
/// Sub-pixel rays per axis for pixels at a discontinuity.
const EDGE_SAMPLES: u32 = 4;
/// Dropout threshold on a 16-bit hash: 655 / 65536 ~ 1 % of pixels.
const DROPOUT_THRESHOLD: u64 = 655;

/// How to render one depth frame.
#[derive(Debug, Clone, Copy)]
pub(crate) struct DepthJob {
    pub(crate) noise: Noise,
    /// Hash key of (seed, serial, frame number).
    pub(crate) key: u64,
    /// Metres per Z16 unit.
    pub(crate) depth_scale: f32,
}

/// SplitMix64's finaliser: a cheap, well-mixed 64-bit hash.
pub(crate) fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// Hash key of one frame: every random choice of the frame derives from it and the
/// pixel index, so rendering order (threads) does not matter.
pub(crate) fn frame_key(seed: u64, serial: u64, frame_number: u64) -> u64 {
    mix64(mix64(mix64(seed) ^ serial) ^ frame_number)
}

/// A standard-normal-like sample from the low 48 bits of a hash: the sum of three
/// 16-bit uniforms (Irwin-Hall), centred and scaled to unit variance.
fn gaussian(h: u64) -> f32 {
    let sum = (h & 0xffff) + ((h >> 16) & 0xffff) + ((h >> 32) & 0xffff);
    // Mean of the sum: 3 * 65535 / 2; variance ~ 3 * 65536^2 / 12 = 65536^2 / 4.
    (sum as f32 - 1.5 * 65535.0) * (2.0 / 65536.0)
}

/// A uniform sample in [0, 1) from the top 24 bits of a hash.
fn unit(h: u64) -> f32 {
    (h >> 40) as f32 / (1u32 << 24) as f32
}

/// Side of the square patches, pixels, in which a finish's depth losses cluster.
const PATCH_PX: usize = 4;
/// Hash key of the finish's patches.
const PATCH_KEY: u64 = 0xa076_1d64_78bd_642f;
/// How much a pixel's own draw adds to its patch's (the rest of the clustering).
const PATCH_OWN: f32 = 0.35;
/// Growth of the depth noise with a finish's loss (x 2.5 where the loss is whole).
const WEAK_NOISE_GAIN: f32 = 1.5;
/// Returned light (reflectivity x cos(incidence) / distance^2, metres) at and below which
/// no pixel of a dark surface finds its match ...
const SIGNAL_NONE: f32 = 0.02;
/// ... and from which on every pixel does.
pub(super) const SIGNAL_FULL: f32 = 0.15;
/// Sharpness of the projector's glare on a glossy surface (Blinn-Phong exponent of the
/// half-vector between the projector and an imager).
const GLARE_EXPONENT: f32 = 600.0;
/// Loss at the glare's centre per unit of gloss (capped at 1).
const GLARE_GAIN: f32 = 1.5;

/// Where the light of a depth frame comes from and goes to, world frame.
struct Eyes {
    /// The left imager (the depth origin).
    origin: V3,
    /// The right imager.
    right: V3,
    /// The infrared projector.
    projector: V3,
}

fn smoothstep(lo: f32, hi: f32, x: f32) -> f32 {
    let t = ((x - lo) / (hi - lo)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// Chance that a pixel seeing `hit` along ray `d` loses its depth to the surface's
/// finish: too little light back (dark, far, slanted), or the projector's glare in
/// either imager (glossy).
#[inline(never)]
fn finish_loss(s: Surfacing, hit: &Hit, d: &V3, eyes: &Eyes) -> f32 {
    let p = eyes.origin + d * hit.t;
    let to_eye = eyes.origin - p;
    let distance = to_eye.norm();
    let view = to_eye / distance;
    let n = if hit.normal.dot(&view) < 0.0 {
        -hit.normal
    } else {
        hit.normal
    };
    let mut kept = 1.0;
    if s.reflectivity < 1.0 {
        let signal = s.reflectivity * n.dot(&view).max(0.0) / (distance * distance);
        kept = smoothstep(SIGNAL_NONE, SIGNAL_FULL, signal);
    }
    if s.gloss > 0.0 {
        let light = (eyes.projector - p).normalize();
        let lobe = |eye: V3| {
            n.dot(&(light + eye).normalize())
                .max(0.0)
                .powf(GLARE_EXPONENT)
        };
        let glare = lobe(view).max(lobe((eyes.right - p).normalize()));
        kept *= 1.0 - (GLARE_GAIN * s.gloss * glare).min(1.0);
    }
    1.0 - kept
}

/// The first pass of a depth frame: what each pixel's ray meets.
struct Exact<'a> {
    world: &'a World,
    view: &'a View,
    spheres: &'a [(V3, f32)],
    eyes: &'a Eyes,
    ideal: bool,
}

impl Exact<'_> {
    /// Row `v`: the depth at each pixel centre (negative: hidden from the right imager;
    /// 0: no surface) into `row`, with `FINISHED` also the finish's loss into `loss`.
    fn row<const FINISHED: bool>(
        &self,
        cands: &mut Vec<RowCandidate>,
        v: usize,
        row: &mut [f32],
        loss: &mut [f32],
    ) {
        let (world, view) = (self.world, self.view);
        view.row_candidates(self.spheres, v as u32, cands);
        let (base, step) = view.row(v as f32);
        // The segment from a point seen at column u to the right imager projects onto
        // columns u.. of the left image, so only primitives reaching column u or beyond
        // can hide it from the right imager.
        let shadow_reach = cands.iter().map(|c| c.u_hi).max();
        for (u, out) in row.iter_mut().enumerate() {
            let d = base + step * u as f32;
            let t = match first_seen(world, &view.origin, &d, cands, u) {
                Some(Seen::Floor(t)) => t,
                Some(Seen::Hit(hit)) => {
                    if FINISHED && let Some(s) = world.surfacing(&hit) {
                        loss[u] = finish_loss(s, &hit, &d, self.eyes);
                    }
                    hit.t
                }
                None => continue,
            };
            let shadowed = !self.ideal
                && shadow_reach.is_some_and(|reach| u as i32 <= reach)
                && world.occluded(
                    &(view.origin + d * t),
                    &self.eyes.right,
                    cands.iter().filter(|c| may_shadow(c, u)).map(|c| c.prim),
                );
            *out = if shadowed { -t } else { t };
        }
    }
}

/// Renders the depth image of `view` (the left imager) as Z16 values.
pub(crate) fn render_depth(world: &World, view: &View, job: &DepthJob) -> Vec<u16> {
    let (w, h) = (view.k.width as usize, view.k.height as usize);
    let spheres = world.spheres_in(view);
    let right_imager = view.origin + view.rot.column(0) * d415::BASELINE_M;
    let ideal = job.noise == Noise::Ideal;

    // Pass 1: exact depth at pixel centres; negative = hit but hidden from the right
    // imager (occlusion shadow); 0 = no surface. With D415 noise and any non-default
    // finish in the world, also each pixel's chance to lose its depth to the finish.
    let mut exact = vec![0.0f32; w * h];
    let finished = !ideal && world.finished();
    let mut loss = if finished {
        vec![0.0f32; w * h]
    } else {
        Vec::new()
    };
    let eyes = Eyes {
        origin: view.origin,
        right: right_imager,
        projector: view.origin + view.rot.column(0) * d415::PROJECTOR_X_M,
    };
    let pass = Exact {
        world,
        view,
        spheres: &spheres,
        eyes: &eyes,
        ideal,
    };
    if finished {
        exact
            .par_chunks_mut(w)
            .zip(loss.par_chunks_mut(w))
            .enumerate()
            .for_each_init(Vec::new, |cands, (v, (row, loss))| {
                pass.row::<true>(cands, v, row, loss);
            });
    } else {
        exact
            .par_chunks_mut(w)
            .enumerate()
            .for_each_init(Vec::new, |cands, (v, row)| {
                pass.row::<false>(cands, v, row, &mut []);
            });
    }

    // Pass 2: the sensor model.
    let mut raw = vec![0u16; w * h];
    let inv_scale = 1.0 / job.depth_scale;
    let min_range = d415::min_range_m(view.k.fx);
    // Disparity d = fx B / z gets noise sigma_d g, so z' = fx B / (d + sigma_d g)
    // = z / (1 + noise_per_z * g * z).
    let noise_per_z = d415::SUBPIXEL_RMS_PX / (view.k.fx * d415::BASELINE_M);
    raw.par_chunks_mut(w).enumerate().for_each(|(v, row)| {
        let here = &exact[v * w..(v + 1) * w];
        if ideal {
            for (out, &z) in row.iter_mut().zip(here) {
                *out = quantize(z, inv_scale);
            }
            return;
        }
        let above = (v > 0).then(|| &exact[(v - 1) * w..v * w]);
        let below = (v + 1 < h).then(|| &exact[(v + 1) * w..(v + 2) * w]);
        let row_key = job.key ^ ((v * w) as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15);
        for (u, out) in row.iter_mut().enumerate() {
            let z = here[u];
            if z <= 0.0 {
                continue;
            }
            // Top 16 bits: dropout; low 48 bits: the noise sample.
            let hash = mix64(row_key ^ (u as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15));
            if hash >> 48 < DROPOUT_THRESHOLD {
                continue;
            }
            let neighbours = [
                u.checked_sub(1).map(|l| here[l]),
                here.get(u + 1).copied(),
                above.map(|r| r[u]),
                below.map(|r| r[u]),
            ];
            let z = if at_edge(neighbours, z) {
                supersample(world, view, &right_imager, u, v)
            } else {
                z
            };
            if !(min_range..=d415::MAX_RANGE_M).contains(&z) {
                continue;
            }
            // The finish: a dark or glaring surface loses depth, in patches of
            // `PATCH_PX` pixels (a patch draws one number, each pixel adds a little of
            // its own: still uniform, so the share lost is the loss), and what is left
            // is noisier.
            let lost = if finished { loss[v * w + u] } else { 0.0 };
            if lost > 0.0 {
                let patch = ((v / PATCH_PX) * (w / PATCH_PX + 1) + u / PATCH_PX) as u64;
                let patch_draw = unit(mix64(job.key ^ PATCH_KEY ^ patch.wrapping_mul(PATCH_KEY)));
                let own = unit(mix64(hash ^ PATCH_KEY));
                if (patch_draw + PATCH_OWN * own).fract() < lost {
                    continue;
                }
            }
            let sigma_gain = 1.0 + WEAK_NOISE_GAIN * lost;
            let denominator = 1.0 + noise_per_z * gaussian(hash) * z * sigma_gain;
            if denominator > 0.0 {
                *out = quantize(z / denominator, inv_scale);
            }
        }
    });
    raw
}

fn rounded(c: [f32; 3]) -> [u8; 3] {
    // Channels are >= 0; `as u8` truncates and saturates.
    c.map(|v| (v + 0.5) as u8)
}

fn in_range(c: &RowCandidate, u: usize) -> bool {
    (c.u_lo..=c.u_hi).contains(&(u as i32))
}

/// The first surface on a ray through column `u`.
enum Seen {
    /// The floor at ray parameter `t`; no candidate primitive covers the column.
    Floor(f32),
    /// The nearest hit among the floor and the candidates covering the column.
    Hit(Hit),
}

/// What the ray `origin + t d` through column `u` meets first. Only when one of the
/// row's `cands` covers `u` are primitives traced; otherwise just the floor is.
fn first_seen(
    world: &World,
    origin: &V3,
    d: &V3,
    cands: &[RowCandidate],
    u: usize,
) -> Option<Seen> {
    let mut active = cands
        .iter()
        .filter(|c| in_range(c, u))
        .map(|c| c.prim)
        .peekable();
    if active.peek().is_none() {
        world.floor_t(origin, d).map(Seen::Floor)
    } else {
        world.trace(origin, d, active).map(Seen::Hit)
    }
}

/// Whether the primitive may hide column `u`'s surface point from the right imager.
fn may_shadow(c: &RowCandidate, u: usize) -> bool {
    u as i32 <= c.u_hi
}

/// Depth `z` (metres) in units of `1 / inv_scale` metres, rounded; 0 if it is not
/// positive or does not fit in 16 bits.
fn quantize(z: f32, inv_scale: f32) -> u16 {
    if z <= 0.0 {
        return 0;
    }
    // Round half up by truncating the cast (z > 0); `f32::round` and `f32::trunc`
    // are libm calls on baseline x86-64.
    let units = z * inv_scale + 0.5;
    if (1.0..65536.0).contains(&units) {
        units as u16
    } else {
        0
    }
}

/// Whether a 4-neighbour (`None` outside the image; 0 = no surface; negative =
/// shadowed, depth in the magnitude) sees a surface at a clearly different depth.
fn at_edge(neighbours: [Option<f32>; 4], z: f32) -> bool {
    neighbours
        .into_iter()
        .flatten()
        .any(|n| n != 0.0 && (n.abs() - z).abs() > EDGE_STEP * z)
}

/// Depth a stereo match over the pixel's footprint reports at a discontinuity: the
/// mean depth of the sub-pixel rays that both imagers see (a flying pixel when the
/// footprint straddles two surfaces); 0 if none.
fn supersample(world: &World, view: &View, right_imager: &V3, u: usize, v: usize) -> f32 {
    let n = EDGE_SAMPLES;
    let mut sum = 0.0;
    let mut count = 0u32;
    for j in 0..n {
        for i in 0..n {
            let su = u as f32 + (i as f32 + 0.5) / n as f32 - 0.5;
            let sv = v as f32 + (j as f32 + 0.5) / n as f32 - 0.5;
            let d = view.ray(su, sv);
            let Some(hit) = world.trace(&view.origin, &d, world.all()) else {
                continue;
            };
            let p = view.origin + d * hit.t;
            if !world.occluded(&p, right_imager, world.all()) {
                sum += hit.t;
                count += 1;
            }
        }
    }
    if count == 0 { 0.0 } else { sum / count as f32 }
}

/// Sub-pixel rays per side of a color pixel on a label.
const LABEL_SAMPLES: u32 = 4;

/// A color pixel on a label or a marker, as a sensor integrates the light over the pixel:
/// the mean shade of `LABEL_SAMPLES`² sub-pixel rays. One ray per pixel would draw a bar
/// code's modules a whole pixel wide or not at all (aliasing), which no camera does.
fn label_pixel(world: &World, view: &View, light: &V3, u: usize, v: usize) -> [u8; 3] {
    let n = LABEL_SAMPLES;
    let mut sum = [0.0f32; 3];
    for j in 0..n {
        for i in 0..n {
            let su = u as f32 + (i as f32 + 0.5) / n as f32 - 0.5;
            let sv = v as f32 + (j as f32 + 0.5) / n as f32 - 0.5;
            let d = view.ray(su, sv);
            let rgb = match world.trace(&view.origin, &d, world.all()) {
                Some(hit) => world.shade(&hit, &(view.origin + d * hit.t), &d, light),
                None => BACKGROUND.map(f32::from),
            };
            for (s, c) in sum.iter_mut().zip(rgb) {
                *s += c;
            }
        }
    }
    rounded(sum.map(|s| s / (n * n) as f32))
}

/// Color of rays that hit nothing (above the horizon).
const BACKGROUND: [u8; 3] = [40, 40, 48];

/// Renders the color image of `view` in `format`, rows `stride` bytes apart.
pub(crate) fn render_color(world: &World, view: &View, format: ColorFormat) -> Vec<u8> {
    let (w, h) = (view.k.width as usize, view.k.height as usize);
    let bpp = format.bytes_per_pixel();
    let spheres = world.spheres_in(view);
    let light = light_direction();
    // The floor is flat and evenly lit: one color for rays that come down on it, one
    // for rays that come up (a camera below the floor). Its own color: a marker where
    // it is shaded (at the origin, say) is drawn only where it lies.
    let floor_hit = Hit {
        t: 1.0,
        normal: V3::new(0.0, 0.0, 1.0),
        surface: Surface::Floor,
    };
    let floor_rgb = [V3::new(0.0, 0.0, -1.0), V3::new(0.0, 0.0, 1.0)]
        .map(|ray| rounded(world.shade_bare_floor(&floor_hit, &ray, &light)));
    let mut data = vec![0u8; w * h * bpp];
    data.par_chunks_mut(w * bpp)
        .enumerate()
        .for_each_init(Vec::new, |cands, (v, row)| {
            view.row_candidates(&spheres, v as u32, cands);
            let (base, step) = view.row(v as f32);
            for (u, px) in row.chunks_exact_mut(bpp).enumerate() {
                let d = base + step * u as f32;
                let rgb = match first_seen(world, &view.origin, &d, cands, u) {
                    Some(Seen::Floor(t)) if world.on_marker(&(view.origin + d * t)) => {
                        label_pixel(world, view, &light, u, v)
                    }
                    Some(Seen::Floor(_)) => floor_rgb[usize::from(d.z > 0.0)],
                    Some(Seen::Hit(hit)) => {
                        let p = view.origin + d * hit.t;
                        let on_marker = hit.surface == Surface::Floor && world.on_marker(&p);
                        if on_marker || world.on_label(&hit, &p) {
                            label_pixel(world, view, &light, u, v)
                        } else {
                            rounded(world.shade(&hit, &p, &d, &light))
                        }
                    }
                    None => BACKGROUND,
                };
                format.write_pixel(rgb, px);
            }
        });
    data
}

/// Hash key of the color sensor's noise (beside the depth frame's).
const COLOR_NOISE_KEY: u64 = 0x3c6e_f372_fe94_f82b;

/// What a color sensor does to the image `data` (`format`, `width` x `height`, rows
/// packed) in place: the lens's Gaussian blur, the exposure's gain, then noise growing
/// with the level (see [`ColorSensor`]), rounded and clipped to 0..=255. `key` seeds the
/// noise (a frame's key: different noise each frame). Alpha bytes are left alone.
pub(crate) fn apply_color_sensor(
    data: &mut [u8],
    width: usize,
    height: usize,
    format: ColorFormat,
    sensor: &ColorSensor,
    key: u64,
) {
    let bpp = format.bytes_per_pixel();
    let row_len = width * 3;
    if width == 0 || height == 0 || data.len() < width * height * bpp {
        return;
    }
    // The three color channels as floats (their order does not matter: every channel
    // gets the same treatment).
    let mut img: Vec<f32> = data
        .chunks_exact(bpp)
        .flat_map(|px| [px[0], px[1], px[2]].map(f32::from))
        .collect();
    if sensor.blur_px > 0.0 {
        img = blur(&img, width, height, sensor.blur_px as f32);
    }
    let gain = sensor.exposure as f32;
    let noise = sensor.noise as f32;
    data.par_chunks_mut(width * bpp)
        .zip(img.par_chunks(row_len))
        .enumerate()
        .for_each(|(v, (out, row))| {
            let row_key =
                key ^ COLOR_NOISE_KEY ^ ((v * row_len) as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15);
            for (u, (px, rgb)) in out
                .chunks_exact_mut(bpp)
                .zip(row.chunks_exact(3))
                .enumerate()
            {
                for (c, (byte, &level)) in px.iter_mut().zip(rgb).enumerate() {
                    let mut level = level * gain;
                    if noise > 0.0 {
                        let i = (u * 3 + c) as u64;
                        let h = mix64(row_key ^ i.wrapping_mul(0xd6e8_feb8_6659_fd93));
                        let sigma = noise * ((level.min(255.0) + 16.0) / 144.0).sqrt();
                        level += sigma * gaussian(h);
                    }
                    // `as u8` saturates: clipping at 0 and 255.
                    *byte = (level + 0.5) as u8;
                }
            }
        });
}

/// A separable Gaussian blur of standard deviation `sigma` pixels over an image of
/// three interleaved channels; edges repeat the border pixel.
fn blur(img: &[f32], width: usize, height: usize, sigma: f32) -> Vec<f32> {
    let radius = (3.0 * sigma).ceil() as isize;
    let mut kernel: Vec<f32> = (-radius..=radius)
        .map(|k| (-((k * k) as f32) / (2.0 * sigma * sigma)).exp())
        .collect();
    let total: f32 = kernel.iter().sum();
    kernel.iter_mut().for_each(|k| *k /= total);
    let row_len = width * 3;
    let clamp = |i: isize, n: usize| i.clamp(0, n as isize - 1) as usize;
    // Along rows.
    let mut across = vec![0.0f32; img.len()];
    across
        .par_chunks_mut(row_len)
        .zip(img.par_chunks(row_len))
        .for_each(|(out, row)| {
            for u in 0..width {
                let mut sum = [0.0f32; 3];
                for (k, w) in kernel.iter().enumerate() {
                    let src = clamp(u as isize + k as isize - radius, width) * 3;
                    for c in 0..3 {
                        sum[c] += w * row[src + c];
                    }
                }
                out[u * 3..u * 3 + 3].copy_from_slice(&sum);
            }
        });
    // Along columns: each output row a weighted sum of whole input rows.
    let mut out = vec![0.0f32; img.len()];
    out.par_chunks_mut(row_len)
        .enumerate()
        .for_each(|(v, row)| {
            for (k, w) in kernel.iter().enumerate() {
                let src = clamp(v as isize + k as isize - radius, height) * row_len;
                for (o, s) in row.iter_mut().zip(&across[src..src + row_len]) {
                    *o += w * s;
                }
            }
        });
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gaussian_has_unit_variance_and_zero_mean() {
        let n = 200_000u64;
        let samples: Vec<f64> = (0..n).map(|i| f64::from(gaussian(mix64(i)))).collect();
        let mean = samples.iter().sum::<f64>() / n as f64;
        let var = samples.iter().map(|s| (s - mean).powi(2)).sum::<f64>() / n as f64;
        assert!(mean.abs() < 0.01, "{mean}");
        assert!((var - 1.0).abs() < 0.02, "{var}");
    }

    #[test]
    fn quantize_rounds_and_refuses_what_z16_cannot_hold() {
        assert_eq!(quantize(1.0004, 1000.0), 1000);
        assert_eq!(quantize(1.0006, 1000.0), 1001);
        assert_eq!(quantize(70.0, 1000.0), 0);
        assert_eq!(quantize(-1.0, 1000.0), 0);
    }
}
