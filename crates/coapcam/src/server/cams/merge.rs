//! What the server measures with, once every camera's cloud is grabbed ([`super::grab`]):
//! the clouds merged in the common frame (a camera with `icp` on registered onto those
//! before it), and the table measured from the merged cloud with the cameras' views and
//! their no-depth regions. Part of the legally relevant software
//! ([`crate::identity::sources`]): what is here decides a measured or a refused number.

use geometry::{
    DimensionConfig, DimensionError, IcpConfig, IcpMethod, Point3, PointCloud, Transform,
};
use nalgebra::Isometry3;
use rgbd::Serial;

use crate::report::Table;
use crate::repr::clouds::DepthPart;
use crate::repr::no_depth::NoDepth;

/// Why a camera's cloud was merged without its ICP registration.
#[derive(Debug, thiserror::Error)]
enum IcpSkipped {
    /// A cloud could not be thinned.
    #[error(transparent)]
    Thinning(#[from] geometry::VoxelError),
    /// The registration failed.
    #[error(transparent)]
    Registration(#[from] geometry::IcpError),
}

/// What [`super::Cams::grab_merged`] collected.
pub(super) struct Merged {
    pub(super) cloud: PointCloud,
    pub(super) parts: Vec<DepthPart>,
    /// The cameras in the cloud, in merge order.
    pub(super) serials: Vec<Serial>,
    /// Their frames' timestamps, microseconds since the UNIX epoch.
    pub(super) frames_us: Vec<u64>,
    /// The newest frame's (now, when there is none).
    pub(super) timestamp_us: u64,
    /// Each camera's floor level, seen in its whole view ([`super::grab::Frame::Cloud`]).
    pub(super) floors: Vec<(Option<String>, Option<f32>)>,
    /// Every camera's parts of the table that returned no depth ([`super::grab::Frame::Cloud`]).
    pub(super) no_depth: Vec<NoDepth>,
    /// Why cameras were left out.
    pub(super) failed: Vec<String>,
}

/// ICP finds a camera's correction on clouds thinned to one point per cube of this edge
/// (metres), point-to-plane, then moves the whole cloud. On two 640x480 clouds (600,000
/// points) point-to-point ICP on every point took 13 s and, on a view displaced by 15 mm
/// and 1 degree, stopped 9 mm off after its 30 iterations; thinned and point-to-plane it
/// takes a fraction of a second and ends within 2 mm (the floor dominates these scenes,
/// and point-to-point slides along it).
const ICP_VOXEL_M: f32 = 0.01;

/// Merges clouds already in the common frame; a cloud whose camera has `icp` on is first
/// registered onto the clouds merged before it, and its part keeps that correction.
pub(super) fn register_and_merge(
    clouds: Vec<(Serial, bool, Vec<Point3>, DepthPart)>,
) -> (PointCloud, Vec<DepthPart>) {
    let mut merged = PointCloud::default();
    let mut parts = Vec::with_capacity(clouds.len());
    for (sn, icp, points, mut part) in clouds {
        let mut cloud = PointCloud::from(points);
        if icp && !merged.is_empty() {
            match icp_correction(&cloud, &merged) {
                Ok(correction) => {
                    let correction = Transform::from(correction);
                    correction.apply_in_place(&mut cloud);
                    part.correction = Some(correction);
                }
                Err(e) => tracing::warn!(serial = %sn, "ICP skipped: {e:#}"),
            }
        }
        merged.extend_from(&cloud);
        parts.push(part);
    }
    (merged, parts)
}

/// The transform that registers `cloud` onto `merged`, found on both thinned.
fn icp_correction(cloud: &PointCloud, merged: &PointCloud) -> Result<Isometry3<f32>, IcpSkipped> {
    let source = geometry::voxel_downsample(cloud, ICP_VOXEL_M)?;
    let target = geometry::voxel_downsample(merged, ICP_VOXEL_M)?;
    let config = IcpConfig {
        method: IcpMethod::PointToPlane,
        ..IcpConfig::default()
    };
    Ok(geometry::icp(&source, &target, &Isometry3::identity(), &config)?.transform)
}

impl Merged {
    /// Every parcel on the table of the merged cloud, measured as `config` asks, with the
    /// parts that returned no depth judged against them (blocking: run it off the
    /// executor).
    pub(super) fn table(&self, config: &DimensionConfig) -> Result<Table, DimensionError> {
        let views: Vec<geometry::View> = self.parts.iter().map(DepthPart::view).collect();
        Table::measure(&self.cloud, config, &views).map(|t| t.with_no_depth(&self.no_depth, &views))
    }
}
