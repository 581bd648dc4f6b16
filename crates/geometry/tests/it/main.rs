//! Integration tests of `geometry`: one binary, one module per concern.

mod cloud;
mod dimension;
mod icp;
mod parcels;
mod ply;
mod roi;
mod scene;
mod transform;

use geometry::Point3;

/// Asserts that two points agree within `tol_m` on every axis.
#[track_caller]
fn assert_near(actual: Point3, expected: Point3, tol_m: f32) {
    let d = actual - expected;
    assert!(
        d.x.abs() <= tol_m && d.y.abs() <= tol_m && d.z.abs() <= tol_m,
        "{actual:?} is not within {tol_m} of {expected:?}"
    );
}
