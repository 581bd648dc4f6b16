//! What a camera server and its clients agree on, written once: the resource paths
//! ([`paths`]), the record of a measurement ([`record`]) and the results log's query
//! ([`results`]). The client, the server and the station use this module, not each other
//! (ARCHITECTURE.md, "Architecture Invariant").

pub mod paths;
pub mod record;
pub mod results;
