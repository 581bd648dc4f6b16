//! The camera backends of a camera server, as one list. A backend is a file of this
//! folder: what it serves as a [`Backend`] (started with the server's camera hub, it puts
//! its cameras in; dropped, it stops), and its flags (a clap `Args` struct, which `serve`
//! takes in through [`Backends`]) with `Args::configured` and `Args::backend`. The
//! synthetic cameras of the scene ([`synthetic`]) serve when no other backend is asked
//! for. Adding one is its file and its name in the `backends!` line below, which declares
//! its module. The backends use `backend.rs`, never this list, which uses them.

mod backend;
pub mod synthetic;

use rgbd::Scene;

pub use backend::{Backend, StartError};

/// Each backend's module (its file, documented by its `//!` lines), and [`Backends`]:
/// every backend's flags, flattened, and the backends they ask for.
macro_rules! backends {
    ($($name:ident),+) => {
        $(pub mod $name;)+

        /// The backends' flags: the `Args` of each.
        #[derive(Debug, Clone, Default, clap::Args)]
        pub struct Backends {
            $(
                #[command(flatten)]
                $name: $name::Args,
            )+
        }

        impl Backends {
            /// Whether any backend other than the scene's synthetic cameras is asked for.
            pub fn any(&self) -> bool {
                $(self.$name.configured())||+
            }

            /// The backends asked for, in this order; the synthetic cameras of `scene`
            /// when none is (the others get `scene` for cameras of their own made from
            /// it, as `--realsense-software`).
            pub fn chosen(&self, scene: Scene) -> Vec<Box<dyn Backend>> {
                let mut chosen = Vec::new();
                $(chosen.extend(self.$name.backend(&scene));)+
                if chosen.is_empty() {
                    chosen.push(Box::new(synthetic::Synthetic(scene)) as Box<dyn Backend>);
                }
                chosen
            }
        }
    };
}

backends!(realsense, recording, depth_pngs);
