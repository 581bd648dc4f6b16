//! How a camera server fails to start ([`StartError`]) or to find an address to send
//! from ([`AddressError`]).

use std::net::{IpAddr, SocketAddr};
use std::path::PathBuf;

use crate::backends;

/// A camera server could not start: what it was doing, and why.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum StartError {
    /// `--static` is not a directory.
    #[error("--static {}: not a directory", .0.display())]
    NotADirectory(PathBuf),
    /// The directory of the cameras' configuration could not be made.
    #[error("creating state directory {}", path.display())]
    StateDir {
        /// The directory.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// The thread that follows the cameras did not start.
    #[error("starting the camera hub listener")]
    HubListener(#[source] std::io::Error),
    /// A backend did not start, or a scene's cameras did not come.
    #[error(transparent)]
    Cameras(#[from] backends::StartError),
    /// The cameras' resources were not routed in time.
    #[error("the cameras' resources did not follow the hub within 10 s")]
    NotRouted,
    /// An address could not be bound.
    #[error("binding {binds:?}")]
    Bind {
        /// The addresses.
        binds: Vec<SocketAddr>,
        /// Why.
        source: std::io::Error,
    },
    /// A `--group` address of a family the server has no address of.
    #[error("--group {ip}: no bound address of its family")]
    NoGroupFamily {
        /// The group's address.
        ip: IpAddr,
    },
    /// A `--group` address that is not a group's.
    #[error("--group {ip}")]
    Group {
        /// The address.
        ip: IpAddr,
        /// Why.
        source: coap::group::Error,
    },
    /// A group could not be joined.
    #[error("joining {ip}")]
    Join {
        /// The group's address.
        ip: IpAddr,
        /// Why.
        source: coap_net::Error,
    },
}

/// A server with no address to send from.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum AddressError {
    /// None of the family of the resource directory to register with.
    #[error("no address of the family of the directory {rd} to register from")]
    ForDirectory {
        /// The directory.
        rd: SocketAddr,
    },
    /// None at all.
    #[error("the server has no address")]
    None,
}
