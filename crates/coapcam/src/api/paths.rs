//! The resource paths of a camera server: the server registers them, the client asks
//! them, both from here.

/// The server's clock (Server-Time, NTP's four timestamps over CoAP).
pub const TIME: &str = "/time";

/// The cameras (link-format of every camera's resources).
pub const CAMS: &str = "/cams";

/// The live streams (`/cams/<sn>/<stream>/live`): their bounds, and each feed with its
/// observers and counters.
pub const LIVE: &str = "/cams/live";

/// Every camera's cloud, merged (POST grabs).
pub const POINTCLOUDS: &str = "/cams/pointclouds";

/// The server's measurement of the parcel (POST measures).
pub const DIMENSIONS: &str = "/cams/dimensions";

/// The station: its name, its software (version and checksum of the legally relevant
/// part) and the results log's head.
pub const STATION: &str = "/station";

/// The results log's head (newest id and hash), observable: notified once per new record.
pub const HEAD: &str = "/station/head";

/// The results log's list of records.
pub const MEASUREMENTS: &str = "/station/measurements";

/// The results log's events: the changes of legally relevant parameters.
pub const EVENTS: &str = "/station/events";

/// The results log's newest record, observable: notified once per new record (the CoAP
/// server sends no observer the representation it has already).
pub const LATEST: &str = "/station/measurements/latest";

/// The option the station's HTTP-CoAP proxy adds to the requests it forwards: the HTTP
/// client's address (`http://ADDR:PORT`), so that an event of the results log names whom
/// a change came from. Experimental range, elective and safe to forward; a server takes
/// it only from a request that came over loopback (the proxy on its own machine).
pub const FORWARDED_FOR: coap::OptionNumber = coap::OptionNumber(65008);

/// The resource `name` (`color`, `depth-settings`, ...) of the camera `serial`.
pub fn camera(serial: impl std::fmt::Display, name: &str) -> String {
    format!("{CAMS}/{serial}/{name}")
}
