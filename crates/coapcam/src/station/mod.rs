//! The station: what a camera server does by itself for a parcel lane (docs/station.md).
//! - [`record`]: one recorded measurement and the chain's encoding;
//! - [`log`]: the results log, append-only and hash-chained in SQLite, with retention.

pub mod log;
pub mod record;
