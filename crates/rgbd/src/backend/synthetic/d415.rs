//! The Intel RealSense D415 as a model: optics per stream mode, stereo geometry and
//! noise (facts from Intel's datasheet and tuning white paper, and from librealsense's
//! D400 code; each constant says where it comes from).

use crate::intrinsics::{DistortionModel, Extrinsics, Intrinsics};

/// Product name as librealsense reports it.
pub const MODEL_NAME: &str = "Intel RealSense D415";

/// Stereo baseline between the left and the right imager, metres (55 mm).
pub const BASELINE_M: f32 = 0.055;

/// Where the synthetic D415's infrared projector sits: between the two imagers, taken
/// as midway along the baseline (metres along +x from the left imager). Only the
/// specular glare of glossy surfaces depends on it.
pub const PROJECTOR_X_M: f32 = BASELINE_M / 2.0;

/// Typical subpixel accuracy of the D415's disparity, pixels (Intel tuning paper: ~0.08).
pub const SUBPIXEL_RMS_PX: f32 = 0.08;

/// Disparity search range of the D400 ASIC, pixels; it sets the minimum range.
pub const DISPARITY_SEARCH_PX: f32 = 126.0;

/// Farthest depth the synthetic D415 reports, metres.
pub const MAX_RANGE_M: f32 = 10.0;

/// Depth focal length at 1280x720, pixels (a D415 calibration dump: 896.1).
const DEPTH_FX_720P: f32 = 896.1;
/// Depth principal point at 1280x720 relative to the image centre, pixels.
const DEPTH_PP_OFFSET_720P: [f32; 2] = [-3.0, 3.9];
/// Color focal lengths at 1280x720, pixels (same dump: 912.5, 911.2).
const COLOR_F_720P: [f32; 2] = [912.5, 911.2];
/// Color principal point at 1280x720 relative to the image centre, pixels.
const COLOR_PP_OFFSET_720P: [f32; 2] = [8.4, -3.6];

/// Distance of the color camera's optical centre from the left imager along x,
/// metres, as librealsense's depth->color extrinsics report it for a D415
/// (translation +15 mm along x; a unit's dump reads 15.006 mm). With
/// `p_color = p_depth + t`, the color centre sits at x = -15 mm in the depth frame,
/// on the side away from the right imager (+55 mm).
pub const DEPTH_TO_COLOR_X_M: f32 = 0.015;

/// How a mode maps onto the sensor: 16:9 modes scale the full 1280x720 field of view
/// with the width; narrower modes (640x480) crop the sides of a frame scaled to their
/// height, which is why a D415 reports fx ~ 597 at 640x480 (= 896 * 480 / 720).
fn mode_scale(width: u32, height: u32) -> f32 {
    (width as f32 / 1280.0).max(height as f32 / 720.0)
}

/// Depth intrinsics of a D415 at `width`x`height`: pinhole (librealsense labels D400
/// depth Brown-Conrady with all coefficients zero), principal point near the centre.
pub fn depth_intrinsics(width: u32, height: u32) -> Intrinsics {
    let s = mode_scale(width, height);
    Intrinsics {
        width,
        height,
        ppx: width as f32 / 2.0 + DEPTH_PP_OFFSET_720P[0] * s,
        ppy: height as f32 / 2.0 + DEPTH_PP_OFFSET_720P[1] * s,
        fx: DEPTH_FX_720P * s,
        fy: DEPTH_FX_720P * s,
        model: DistortionModel::BrownConrady,
        coeffs: [0.0; 5],
    }
}

/// Color intrinsics of a D415 at `width`x`height`. librealsense labels D400 color
/// Inverse Brown-Conrady; the synthetic camera renders a distortion-free image, so
/// the coefficients are zero.
pub fn color_intrinsics(width: u32, height: u32) -> Intrinsics {
    let s = mode_scale(width, height);
    Intrinsics {
        width,
        height,
        ppx: width as f32 / 2.0 + COLOR_PP_OFFSET_720P[0] * s,
        ppy: height as f32 / 2.0 + COLOR_PP_OFFSET_720P[1] * s,
        fx: COLOR_F_720P[0] * s,
        fy: COLOR_F_720P[1] * s,
        model: DistortionModel::InverseBrownConrady,
        coeffs: [0.0; 5],
    }
}

/// Depth -> color extrinsics: no rotation, +15 mm along x.
pub fn depth_to_color() -> Extrinsics {
    Extrinsics {
        translation: [DEPTH_TO_COLOR_X_M, 0.0, 0.0],
        ..Extrinsics::IDENTITY
    }
}

/// Nearest measurable depth for a depth focal length `fx` (pixels): the depth whose
/// disparity fills the 126-pixel search range, fx * B / 126 (~0.39 m at 1280x720).
pub fn min_range_m(fx: f32) -> f32 {
    fx * BASELINE_M / DISPARITY_SEARCH_PX
}

/// Expected RMS depth error at depth `z_m` for focal length `fx` (Intel's formula):
/// z^2 * subpixel / (fx * baseline).
pub fn depth_rms_m(z_m: f32, fx: f32) -> f32 {
    z_m * z_m * SUBPIXEL_RMS_PX / (fx * BASELINE_M)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn intrinsics_follow_the_d415_dumps() {
        let k = depth_intrinsics(1280, 720);
        assert_eq!((k.fx, k.ppx, k.ppy), (896.1, 637.0, 363.9));
        assert!((depth_intrinsics(640, 480).fx - 597.4).abs() < 0.1);
        assert!((depth_intrinsics(848, 480).fx - 597.4).abs() < 0.1);
        assert!((depth_intrinsics(640, 360).fx - 448.05).abs() < 0.01);
        assert!((color_intrinsics(1920, 1080).fx - 1368.75).abs() < 0.01);
    }

    #[test]
    fn minimum_range_is_0_39_m_at_720p() {
        assert!((min_range_m(depth_intrinsics(1280, 720).fx) - 0.391).abs() < 0.001);
    }

    #[test]
    fn rms_at_one_metre_is_1_6_mm() {
        assert!((depth_rms_m(1.0, 896.0) - 0.001_623).abs() < 1e-5);
    }
}
