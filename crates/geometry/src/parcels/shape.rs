//! The shape seam: what a shape rule sees of one object ([`Object`]) and what it answers
//! ([`ShapeFit`]). The rules are listed in `fit.rs`'s `SHAPES`.

use geo::Polygon;

use super::height_map::HeightMap;
use super::view::View;
use crate::Point3;

/// How well a cuboid describes the object.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Shape {
    /// A box: its lid fills its rectangle and nothing reaches beyond it.
    Cuboid,
    /// A tube lying on the floor or a standing cylinder: its footprint from the circle
    /// its top describes, measured as the smallest enclosing cuboid.
    Round,
    /// Anything else (bags, pillows, several parcels together), measured as the smallest
    /// enclosing cuboid. Its sides curve down under its top, out of a camera's sight
    /// above, so its length and width are known less well than a box's.
    Irregular,
}

/// One object as `fit.rs`'s `measure` has read it before deciding its shape: what the
/// shape rules (tried on an object with one top) and the cuboid and irregular fallbacks
/// look at.
#[derive(Clone, Copy)]
pub(super) struct Object<'a> {
    /// Its points.
    pub(super) cluster: &'a [Point3],
    /// Its dense points (cells of the height map with at least 15 % of the median
    /// cell's points).
    pub(super) dense: &'a [Point3],
    /// Its height map.
    pub(super) map: &'a HeightMap,
    /// The lid's height (the median of its band), metres.
    pub(super) height_m: f32,
    /// The lid band's depth, metres.
    pub(super) band_m: f32,
    /// The lid's flattest points: within `slab` of `height_m`.
    pub(super) flat: &'a [Point3],
    /// See `flat`, metres.
    pub(super) slab: f32,
    /// The lid points' convex hull.
    pub(super) lid_hull: &'a Polygon<f64>,
    /// The minimum-area rectangle around `lid_hull`.
    pub(super) hull_rect: [[f64; 2]; 4],
    /// The lid's rectangle: `hull_rect`'s edges placed by the lid's density, then moved
    /// out by what the cameras' pixels hide or to the walls.
    pub(super) lid_rect: [[f64; 2]; 4],
    /// The lid band's depth and 3 mm, metres: the edges are counted from a line this far
    /// inside the rectangle's ends (see `edges::refine`).
    pub(super) margin: f64,
    /// An edge moves at most this far inside the hull's rectangle (three quarters of the
    /// lid band, at least 1.5 mm), metres.
    pub(super) inward: f64,
    /// The cameras.
    pub(super) views: &'a [View],
    /// A pixel's size at the lid, metres (0 without cameras).
    pub(super) pixel: f64,
    /// It passes the box test: its lid and its flattest points fill their rectangle, the
    /// lid is level, and nothing of it reaches beyond it (the cuboid fallback).
    pub(super) box_like: bool,
}

/// A shape rule's answer: the object's shape, its footprint, its top and its coverage.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct ShapeFit {
    /// Its shape, as records name it and billing divides it.
    pub(super) shape: Shape,
    /// Its footprint's corners, in order around it.
    pub(super) footprint: [[f64; 2]; 4],
    /// Its top's height, metres.
    pub(super) top_m: f32,
    /// The share of the height map's cells within the area the shape is seen over (a
    /// box's footprint, the strip a lying tube's circle was seen over) that hold points
    /// (see `HeightMap::coverage`).
    pub(super) coverage: f64,
    /// Where a side meets the floor no camera sees, in a band wider than
    /// `shoulders::BAND_MAX_M` (a soft parcel's side facing away from every camera): more
    /// of it may lie there, unseen.
    pub(super) foot_unseen: bool,
}

/// A shape rule: `Some` when the object is of its shape, measured; `None` to leave it to
/// the next rule.
pub(super) type ShapeRule = fn(&Object<'_>) -> Option<ShapeFit>;
