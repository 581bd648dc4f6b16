//! The kinds of object a scene holds, one file each: its parameters and its table in a
//! scene file, their checks, the enclosing footprint and height its truth is made of, and
//! its primitive for the ray caster. [`Object`] is what the scene, the ray caster, the
//! certification set and the scene-file writer ask of every kind; none of them names one.
//!
//! A kind added is a file here with its `mod` line, a variant of [`ObjectKind`], and its
//! table in the scene (a field of `Scene` and `SceneFile`, and a line of `Scene::objects`
//! and `Scene::at`).

mod bag;
mod cylinder;
mod scene_box;
mod tube;

use std::sync::Arc;

pub use bag::{Bag, MAX_SAG, bag_profile};
pub use cylinder::Cylinder;
pub(crate) use scene_box::default_color as default_box_color;
pub use scene_box::{MAX_LABEL_CHARS, SceneBox};
pub use tube::Tube;

use super::fields::{Finish, SceneError, Timeline};
use super::label::Label;
use super::ray::Primitive;

/// What kind of object a [`Truth`](crate::scene::Truth) describes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[non_exhaustive]
pub enum ObjectKind {
    /// A `[[box]]`.
    Box,
    /// A `[[cylinder]]` standing upright.
    Cylinder,
    /// A `[[tube]]` lying on the floor.
    Tube,
    /// A `[[bag]]`, a polybag.
    Bag,
}

impl ObjectKind {
    /// Every kind, in the order of [`Scene`](crate::scene::Scene)'s tables (a kind added goes here too: what
    /// judges the objects lists them from it).
    pub const ALL: [Self; 4] = [Self::Box, Self::Cylinder, Self::Tube, Self::Bag];

    /// The name of the kind's table in a scene file (`box`, `cylinder`, `tube`, `bag`).
    pub fn name(self) -> &'static str {
        match self {
            Self::Box => "box",
            Self::Cylinder => "cylinder",
            Self::Tube => "tube",
            Self::Bag => "bag",
        }
    }
}

/// One object of a scene, whatever its kind.
pub(crate) trait Object {
    /// Its kind.
    fn kind(&self) -> ObjectKind;

    /// Checks its values; `at` names a field (`box[0].size`).
    fn validate(&self, at: &dyn Fn(&str) -> String) -> Result<(), SceneError>;

    /// The length and width of its enclosing footprint on the floor, metres, and the
    /// direction of the length, degrees counter-clockwise from world x.
    fn footprint(&self) -> ([f64; 2], f64);

    /// The height of its highest point above the floor, metres.
    fn height(&self) -> f64;

    /// The centre of its footprint on the floor, where it stands at rest.
    fn center(&self) -> [f64; 2];

    /// Its color.
    fn color(&self) -> [u8; 3];

    /// How its surface returns the D415's light.
    fn finish(&self) -> &Finish;

    /// When it is there, and whether it slides in.
    fn timeline(&self) -> &Timeline;

    /// Its label; only a box has one.
    fn label(&self) -> Option<&Label> {
        None
    }

    /// Its centre and timeline, to be changed.
    fn place_mut(&mut self) -> (&mut [f64; 2], &mut Timeline);

    /// The object as it stands at scene time `t_s`, without a timeline; `None` when it is
    /// not there then.
    fn at(&self, t_s: f64) -> Option<Self>
    where
        Self: Sized + Clone,
    {
        placed(self, t_s)
    }

    /// Its primitive for the ray caster on a floor at height `floor_z`; `at` names a
    /// field, as in [`Object::validate`].
    fn primitive(
        &self,
        floor_z: f32,
        at: &dyn Fn(&str) -> String,
    ) -> Result<Arc<dyn Primitive>, SceneError>;

    /// Its table in a scene file.
    fn write_toml(&self, out: &mut String);
}

/// `object` where it stands at `t_s`, without a timeline; `None` when it is not there.
fn placed<T: Object + Clone>(object: &T, t_s: f64) -> Option<T> {
    let mut o = object.clone();
    let (center, timeline) = o.place_mut();
    *center = timeline.position(*center, t_s)?;
    *timeline = Timeline::default();
    Some(o)
}

#[cfg(test)]
mod tests {
    use crate::scene::{ObjectKind, Scene};

    /// A kind is registered in full: the scene reads its table (by the name
    /// `ObjectKind::name` gives), lists it in `Scene::objects` in the order of
    /// `ObjectKind::ALL`, and writes it back.
    #[test]
    fn every_kind_is_read_listed_in_order_and_written() {
        let table = |kind: ObjectKind| {
            let fields = match kind {
                ObjectKind::Box | ObjectKind::Bag => "size = [0.3, 0.2, 0.1]",
                ObjectKind::Cylinder => "radius = 0.1\nheight = 0.2",
                ObjectKind::Tube => "radius = 0.05\nlength = 0.3",
            };
            format!("[[{}]]\n{fields}\ncenter = [0.0, 0.0]\n", kind.name())
        };
        // Tables in the reverse order: the scene lists them by kind all the same.
        let text: String = ObjectKind::ALL.iter().rev().map(|&k| table(k)).collect();
        let scene = Scene::from_toml(&text).unwrap();
        let kinds: Vec<ObjectKind> = scene.objects().map(|(_, o)| o.kind()).collect();
        assert_eq!(kinds, ObjectKind::ALL);
        assert_eq!(Scene::from_toml(&scene.to_toml()).unwrap(), scene);
    }
}
