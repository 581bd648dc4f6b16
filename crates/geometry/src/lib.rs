//! Point-cloud geometry for coapcam.
//!
//! Owns: point clouds in metres, the 3D transformation of thesis Listing A.4 and its JSON
//! document, the 3D region of interest, merging, voxel downsampling, ICP registration and
//! parcel dimensioning (docs/design.md §5, §6), and the binary PLY encoding of clouds.
//!
//! Must not: know about CoAP, cameras or the file system (PLY goes through `io::Write`);
//! read clocks; spawn threads of its own (data-parallel loops run on the caller's rayon
//! pool). Everything here is synchronous and
//! works in metres (`f32` points, `f64` where sums or documents need the precision).

#![forbid(unsafe_code)]

pub mod cloud;
pub mod dimension;
mod grid;
pub mod icp;
mod index;
pub mod parcels;
pub mod plane;
pub mod ply;
pub mod pose;
pub mod roi;
pub mod transform;
pub mod voxel;

pub use cloud::PointCloud;
pub use dimension::{DimensionConfig, DimensionError, Dimensions};
pub use icp::{IcpConfig, IcpError, IcpMethod, IcpOutcome, icp};
pub use parcels::{
    ParcelFit, Parcels, Shape, View, dimension, hidden_bounds, hidden_share, parcels,
};
pub use plane::{Plane, PlaneError, dominant_plane, floor_transformation, plane_near};
pub use ply::{PlyError, decode_ply, encode_ply, write_ply};
pub use pose::{Sighting, planar_pnp, reprojection_rms, rigid_2d};
pub use roi::{Roi3, RoiError};
pub use transform::{Transform, TransformError, Transformation};
pub use voxel::{VoxelError, voxel_downsample};

/// A point in metres.
pub type Point3 = nalgebra::Point3<f32>;
