//! The outputs of the results log, as one list. An output is a file of this folder with
//! its flags (a clap `Args` struct, which `serve` takes in through [`Outputs`]), how it
//! starts from them (`Args::configured`, and `Args::start`, following the log through
//! [`follow::run`](super::follow::run)) and what it is once started (an [`Output`]). The
//! outputs use `follow`, never this list, which uses them.
//! Adding one is its file and its name in the `outputs!` line below.

use std::convert::Infallible;

use super::follow::{Feed, Output};

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
            ) -> Result<Vec<Box<dyn Output>>, OutputError> {
                let mut started = Vec::new();
                $(started.extend(self.$name.start(feed).await?);)+
                Ok(started)
            }
        }
    };
}

#[cfg(feature = "opcua")]
outputs!(mqtt, line, webhook, postgres, opcua);
#[cfg(not(feature = "opcua"))]
outputs!(mqtt, line, webhook, postgres);

/// An output asked for could not start.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum OutputError {
    /// The line output's address could not be listened on.
    #[error(transparent)]
    Line(#[from] super::line::ListenError),
    /// The station's name cannot be an MQTT topic level.
    #[error("the station's name as an MQTT topic level (--station-name)")]
    Mqtt(#[from] super::mqtt::TargetError),
    /// The webhook's secret or template could not be read.
    #[error(transparent)]
    Webhook(#[from] super::webhook::SetupError),
    /// The OPC UA server could not start.
    #[cfg(feature = "opcua")]
    #[error(transparent)]
    OpcUa(#[from] super::opcua::StartError),
}

/// An output that always starts (PostgreSQL: it connects, and reconnects, as it runs).
impl From<Infallible> for OutputError {
    fn from(never: Infallible) -> Self {
        match never {}
    }
}

impl Outputs {
    /// Refuses a station name an output asked for cannot carry: MQTT topic names allow a
    /// `/` (it separates levels), but the station's name is one level of
    /// `PREFIX/<station>/measurements`, which subscribers match with `+`.
    pub fn check_station(&self, station: &str) -> Result<(), super::mqtt::TargetError> {
        self.mqtt.check_station(station)
    }
}
