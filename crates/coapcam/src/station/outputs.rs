//! The outputs of the results log, as one list. An output is a file of this folder with
//! its flags (a clap `Args` struct, which `serve` takes in through [`Outputs`]), how it
//! starts from them (`Args::configured`, and `Args::start`, following the log through
//! [`follow::run`](super::follow::run)) and what it is once started (an [`Output`]).
//! Adding one is its file and its name in the `outputs!` line below.

use std::future::Future;
use std::pin::Pin;

use super::log::ResultsLog;

/// A started output, kept while the station runs.
pub trait Output: Send {
    /// What it does, said once when the station starts (`line output on ADDR`).
    fn describe(&self) -> String;

    /// Ends it within a bounded time; by default it ends when dropped.
    fn stop(self: Box<Self>) -> Pin<Box<dyn Future<Output = ()> + Send>> {
        Box::pin(async {})
    }
}

/// What an output starts from: the results log and the station's name.
pub(super) struct Feed<'a> {
    pub(super) log: &'a ResultsLog,
    pub(super) station: &'a str,
}

/// [`Outputs`]: every output's flags, flattened, and the outputs they ask for started in
/// this order.
macro_rules! outputs {
    ($($name:ident),+) => {
        /// The outputs' flags: the `Args` of each.
        #[derive(Debug, Clone, Default, clap::Args)]
        pub struct Outputs {
            $(
                #[command(flatten)]
                $name: super::$name::Args,
            )+
        }

        impl Outputs {
            /// Whether any output is asked for.
            pub fn any(&self) -> bool {
                $(self.$name.configured())||+
            }

            /// Starts the outputs asked for, following `feed.log`.
            pub(super) async fn start(
                &self,
                feed: &Feed<'_>,
            ) -> anyhow::Result<Vec<Box<dyn Output>>> {
                let mut started = Vec::new();
                $(started.extend(self.$name.start(feed).await?);)+
                Ok(started)
            }
        }
    };
}

outputs!(mqtt, line, webhook);
