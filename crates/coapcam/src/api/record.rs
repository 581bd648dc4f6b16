//! One entry of the results log: what a measurement path hands the log ([`NewRecord`]),
//! what the log keeps and serves ([`Record`]), and the chain's encoding: the canonical
//! bytes a record's SHA-256 is taken over (docs/station.md).

use std::fmt;
use std::time::{SystemTime, UNIX_EPOCH};

use geometry::Transformation;
use serde::{Deserialize, Serialize};
use serde_json::{Map, Value};
use sha2::{Digest as _, Sha256};

use crate::report::Measurement;

/// The `prev_hash` of the first record: 64 zeros.
pub const GENESIS: &str = "0000000000000000000000000000000000000000000000000000000000000000";

/// What the hashed bytes of a record start with: the encoding's name and version.
const DOMAIN: &[u8] = b"coapcam-record-v1\n";

/// Fields of a record's JSON that are not hashed: the hash itself, the station's
/// signature (made over the hashed bytes), and whether the pictures are still kept
/// (retention prunes them; their SHA-256s stay hashed).
const UNHASHED: [&str; 4] = ["hash", "signature", "has_photo", "has_annotated"];

/// What made a measurement.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Trigger {
    /// The station itself: a parcel was placed and stood still (`serve --auto-measure`).
    Auto,
    /// A client's `POST /cams/dimensions`.
    Request,
}

impl Trigger {
    /// `auto` or `request`.
    pub fn name(self) -> &'static str {
        match self {
            Self::Auto => "auto",
            Self::Request => "request",
        }
    }
}

/// A camera that took part in a measurement, and where it stood.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CameraPose {
    /// The camera's serial number.
    pub serial: String,
    /// Its 3d-transformation document at the time of the measurement.
    pub transformation: Transformation,
}

/// A measurement to record: what a measurement path hands the station's
/// results log (`ResultsLog::append` in `station::log`).
#[derive(Debug, Clone)]
pub struct NewRecord {
    /// When it was measured.
    pub time: UtcTime,
    /// The station's name (`serve --station-name`).
    pub station: String,
    /// What made it.
    pub trigger: Trigger,
    /// The measurement (the dimensions, volume, volumetric weight with its divisor,
    /// codes, warnings), as `POST /cams/dimensions` answers it.
    pub measurement: Measurement,
    /// Each camera's serial and 3d-transformation.
    pub cameras: Vec<CameraPose>,
    /// The software's version (`coapcam` crate version).
    pub version: String,
    /// SHA-256 (hex) of the legally relevant software that measured it
    /// ([`crate::identity::SOFTWARE_SHA256`] of this build).
    pub software_sha256: String,
    /// The photo, JPEG.
    pub photo_jpeg: Option<Vec<u8>>,
    /// The annotated picture, PNG.
    pub annotated_png: Option<Vec<u8>>,
    /// SHA-256 (hex) of the legally relevant parameters in force when it was measured
    /// ([`parameters_sha256`]); `None` where the measuring path does not know them.
    pub parameters_sha256: Option<String>,
}

impl NewRecord {
    /// The software version this build records.
    pub const VERSION: &'static str = env!("CARGO_PKG_VERSION");
}

/// A recorded measurement, as the log keeps it and as `/station/measurements`, MQTT and
/// `coapcam results` give it (JSON or CBOR, pictures by their SHA-256 only).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Record {
    /// Monotonic id: 1 for the first record, one more for each next.
    pub id: u64,
    /// When it was measured.
    pub time: UtcTime,
    /// The station's name.
    pub station: String,
    /// What made it.
    pub trigger: Trigger,
    /// The measurement, as `POST /cams/dimensions` answers it.
    pub measurement: Measurement,
    /// Each camera's serial and 3d-transformation.
    pub cameras: Vec<CameraPose>,
    /// The software's version.
    pub version: String,
    /// SHA-256 (hex) of the legally relevant software that measured it; `None` in records
    /// made before builds carried it (absent from their JSON, so their hashes stand).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub software_sha256: Option<String>,
    /// How many parameter events the log held before this record: the counter of the
    /// changes to legally relevant parameters; `None` in records made before the log
    /// kept events (absent from their JSON, so their hashes stand).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub events: Option<u64>,
    /// SHA-256 (hex) of the legally relevant parameters it was measured with
    /// ([`parameters_sha256`]); `None` in records made before (absent from their JSON).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub parameters_sha256: Option<String>,
    /// Whether the kernel said the station's clock was synchronised when the record was
    /// appended; `None` in records made before (absent from their JSON).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub clock_synced: Option<bool>,
    /// SHA-256 (hex) of the photo (JPEG), if one was taken; kept after the photo is
    /// pruned.
    pub photo_sha256: Option<String>,
    /// SHA-256 (hex) of the annotated picture (PNG), if one was made.
    pub annotated_sha256: Option<String>,
    /// The previous record's `hash` ([`GENESIS`] for the first).
    pub prev_hash: String,
    /// SHA-256 (hex) of this record's canonical bytes ([`Record::compute_hash`]).
    pub hash: String,
    /// The station key's Ed25519 signature (hex) of the bytes [`Record::hash_of`] hashes
    /// ([`Record::hashed_bytes`]); `None` when the station signs nothing (absent from
    /// the JSON). Not hashed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub signature: Option<String>,
    /// Whether the photo is still kept (not hashed: retention prunes pictures).
    #[serde(default)]
    pub has_photo: bool,
    /// Whether the annotated picture is still kept (not hashed).
    #[serde(default)]
    pub has_annotated: bool,
}

impl Record {
    /// The record `new` becomes with `id` after `prev_hash`, the log holding `events`
    /// events before it, its hash computed (without `clock_synced`: see
    /// [`Record::chain_synced`]).
    pub fn chain(new: &NewRecord, id: u64, prev_hash: &str, events: u64) -> Self {
        Self::chain_synced(new, id, prev_hash, events, None)
    }

    /// [`Record::chain`] with `clock_synced`.
    pub fn chain_synced(
        new: &NewRecord,
        id: u64,
        prev_hash: &str,
        events: u64,
        clock_synced: Option<bool>,
    ) -> Self {
        let mut record = Self {
            id,
            time: new.time,
            station: new.station.clone(),
            trigger: new.trigger,
            measurement: new.measurement.clone(),
            cameras: new.cameras.clone(),
            version: new.version.clone(),
            software_sha256: Some(new.software_sha256.clone()),
            events: Some(events),
            parameters_sha256: new.parameters_sha256.clone(),
            clock_synced,
            photo_sha256: new.photo_jpeg.as_deref().map(sha256_hex),
            annotated_sha256: new.annotated_png.as_deref().map(sha256_hex),
            prev_hash: prev_hash.to_owned(),
            hash: String::new(),
            signature: None,
            has_photo: new.photo_jpeg.is_some(),
            has_annotated: new.annotated_png.is_some(),
        };
        record.hash = Self::compute_hash(&record.content());
        record
    }

    /// The hashed content: the record's JSON without `hash`, `has_photo` and
    /// `has_annotated`.
    pub fn content(&self) -> Value {
        let mut v = serde_json::to_value(self).unwrap_or(Value::Null);
        if let Value::Object(map) = &mut v {
            for key in UNHASHED {
                map.remove(key);
            }
        }
        v
    }

    /// SHA-256 (hex) over the record-encoding tag and the canonical bytes of `content`
    /// ([`canonical_bytes`]).
    pub fn compute_hash(content: &Value) -> String {
        Self::hash_of(&canonical_bytes(content))
    }

    /// SHA-256 (hex) over the record-encoding tag and `canonical` (a record's canonical
    /// bytes, as the log stores them).
    pub fn hash_of(canonical: &[u8]) -> String {
        let mut h = Sha256::new();
        h.update(DOMAIN);
        h.update(canonical);
        hex(&h.finalize())
    }

    /// The bytes a record's hash is taken over, and its signature made over: the
    /// record-encoding tag and `canonical`.
    pub fn hashed_bytes(canonical: &[u8]) -> Vec<u8> {
        [DOMAIN, canonical].concat()
    }

    /// The record's content as stored: its canonical bytes.
    pub fn stored_body(&self) -> Vec<u8> {
        canonical_bytes(&self.content())
    }

    /// A record from its stored body, its hash and whether its pictures are kept.
    pub fn from_stored(
        body: &[u8],
        hash: String,
        has_photo: bool,
        has_annotated: bool,
    ) -> Result<Self, serde_json::Error> {
        let mut v: Value = serde_json::from_slice(body)?;
        if let Value::Object(map) = &mut v {
            map.insert("hash".into(), hash.into());
            map.insert("has_photo".into(), has_photo.into());
            map.insert("has_annotated".into(), has_annotated.into());
        }
        serde_json::from_value(v)
    }

    /// The texts of the codes read (the measurement's `codes`), in its order.
    pub fn code_texts(&self) -> Vec<String> {
        self.measurement
            .codes
            .iter()
            .flatten()
            .map(|seen| seen.code.text.clone())
            .collect()
    }
}

/// What was done to a parameter document.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Change {
    /// A new document (`PUT`).
    Put,
    /// Back to the camera's own (`DELETE`).
    Delete,
}

impl Change {
    /// `PUT` or `DELETE`, the method that made it.
    pub fn method(self) -> &'static str {
        match self {
            Self::Put => "PUT",
            Self::Delete => "DELETE",
        }
    }
}

/// A change of a legally relevant parameter: which document, its content's SHA-256
/// before and after, who changed it, and the parameters in force after it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Event {
    /// The document: its CoAP path (`/cams/840412060746/3d-transformation`).
    pub document: String,
    /// `put` or `delete`.
    pub change: Change,
    /// SHA-256 (hex) of the document before the change, as `GET` served it.
    pub old_sha256: String,
    /// SHA-256 (hex) of the document after the change, as `GET` serves it.
    pub new_sha256: String,
    /// Who changed it: `coap://ADDR`, with its DTLS PSK identity when it had one
    /// (`coaps://ADDR psk-identity NAME`).
    pub by: String,
    /// SHA-256 (hex) of the legally relevant parameters in force after the change
    /// ([`parameters_sha256`]): what the next measurement records.
    pub parameters_sha256: String,
}

/// An event to record: what the camera server hands the results log to append (the
/// station's `ResultsLog::append_event`; `api` names no module above it).
#[derive(Debug, Clone)]
pub struct NewEvent {
    /// When the change was made.
    pub time: UtcTime,
    /// The station's name.
    pub station: String,
    /// What changed.
    pub event: Event,
}

/// A recorded event: a row of the results log in the same chain (and id sequence) as
/// the measurements, told apart by its `event` field.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct EventRecord {
    /// Its id, from the same sequence as the measurements'.
    pub id: u64,
    /// When the change was made.
    pub time: UtcTime,
    /// The station's name.
    pub station: String,
    /// The event counter: 1 for the log's first event, one more for each next (the
    /// `events` of the measurements after it).
    pub counter: u64,
    /// What changed.
    pub event: Event,
    /// The software's version.
    pub version: String,
    /// SHA-256 (hex) of the legally relevant software that recorded it.
    pub software_sha256: String,
    /// Whether the kernel said the station's clock was synchronised when it was
    /// appended; `None` in events made before (absent from their JSON).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub clock_synced: Option<bool>,
    /// The previous record's `hash`.
    pub prev_hash: String,
    /// SHA-256 (hex) of its canonical bytes, as a measurement's.
    pub hash: String,
    /// The station key's signature, as a measurement's; not hashed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub signature: Option<String>,
}

impl EventRecord {
    /// The record `new` becomes with `id` after `prev_hash` as event number `counter`,
    /// the kernel having said `clock_synced`, its hash computed.
    pub fn chain(
        new: &NewEvent,
        id: u64,
        prev_hash: &str,
        counter: u64,
        clock_synced: Option<bool>,
    ) -> Self {
        Self {
            id,
            time: new.time,
            station: new.station.clone(),
            counter,
            event: new.event.clone(),
            version: NewRecord::VERSION.to_owned(),
            software_sha256: crate::identity::SOFTWARE_SHA256.to_owned(),
            clock_synced,
            prev_hash: prev_hash.to_owned(),
            hash: String::new(),
            signature: None,
        }
        .chained()
    }

    /// An event from its stored body and hash.
    pub fn from_stored(body: &[u8], hash: String) -> Result<Self, serde_json::Error> {
        let mut v: Value = serde_json::from_slice(body)?;
        if let Value::Object(map) = &mut v {
            map.insert("hash".into(), hash.into());
        }
        serde_json::from_value(v)
    }
}

impl Row for EventRecord {
    fn hash_mut(&mut self) -> &mut String {
        &mut self.hash
    }
}

/// A jump of the station's wall clock, as the log noted it: the wall clock's time at the
/// record before and now, and the monotonic time between them.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ClockJump {
    /// `back` (the wall clock is earlier than at the record before, or moved on less
    /// than the monotonic clock did) or `forward` (it moved on more).
    pub jump: String,
    /// The wall clock when the record before was appended (after a restart: that
    /// record's `time`).
    pub previous: UtcTime,
    /// The wall clock now.
    pub now: UtcTime,
    /// The monotonic clock's time since the record before, ms; `None` after a restart
    /// (the station's monotonic clock started anew).
    pub monotonic_elapsed_ms: Option<u64>,
}

/// The chain fields of a row of the results log that notes something about the log itself
/// (a jump of the clock, ids skipped) rather than a measurement: the same in every such
/// row, flattened into its JSON beside the row's own note and time.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct NoteHeader {
    /// Its id, from the same sequence as the measurements'.
    pub id: u64,
    /// The station's name.
    pub station: String,
    /// Whether the kernel said the clock was synchronised.
    pub clock_synced: bool,
    /// The software's version.
    pub version: String,
    /// SHA-256 (hex) of the legally relevant software that recorded it.
    pub software_sha256: String,
    /// The previous record's `hash`.
    pub prev_hash: String,
    /// SHA-256 (hex) of its canonical bytes, as a measurement's.
    pub hash: String,
    /// The station key's signature, as a measurement's; not hashed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub signature: Option<String>,
}

impl NoteHeader {
    /// The header of row `id` of `station` after `prev_hash`, made by this build, the
    /// kernel having said `clock_synced`; its hash still to compute ([`Row::chained`]).
    fn new(station: &str, id: u64, prev_hash: &str, clock_synced: bool) -> Self {
        Self {
            id,
            station: station.to_owned(),
            clock_synced,
            version: NewRecord::VERSION.to_owned(),
            software_sha256: crate::identity::SOFTWARE_SHA256.to_owned(),
            prev_hash: prev_hash.to_owned(),
            hash: String::new(),
            signature: None,
        }
    }
}

/// A row of the results log that is not a measurement: an event ([`EventRecord`]) or a
/// note about the log ([`ClockRecord`], [`GapRecord`], their [`NoteHeader`] flattened
/// beside their own fields). Its hash is taken over all of it but `hash` and `signature`.
pub trait Row: Serialize + Sized {
    /// Its hash, to set.
    fn hash_mut(&mut self) -> &mut String;

    /// The row with its hash computed over its stored body.
    fn chained(mut self) -> Self {
        *self.hash_mut() = Record::hash_of(&self.stored_body());
        self
    }

    /// The row's content as stored: its canonical bytes (without `hash` and `signature`).
    fn stored_body(&self) -> Vec<u8> {
        canonical_bytes(&unhashed(self))
    }
}

/// A row of the results log that notes a jump of the station's wall clock, in the same
/// chain (and id sequence) as the measurements, told apart by its `clock` field; appended
/// just before the record whose time showed the jump.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ClockRecord {
    /// Its id, station, software, place in the chain, hash and signature.
    #[serde(flatten)]
    pub header: NoteHeader,
    /// The wall clock's time now (as `clock.now`).
    pub time: UtcTime,
    /// The jump.
    pub clock: ClockJump,
}

impl ClockRecord {
    /// The row noting `jump` with `id` after `prev_hash`, its hash computed.
    pub fn chain(
        station: &str,
        jump: ClockJump,
        clock_synced: bool,
        id: u64,
        prev_hash: &str,
    ) -> Self {
        Self {
            header: NoteHeader::new(station, id, prev_hash, clock_synced),
            time: jump.now,
            clock: jump,
        }
        .chained()
    }
}

impl Row for ClockRecord {
    fn hash_mut(&mut self) -> &mut String {
        &mut self.header.hash
    }
}

/// Ids a log skipped because a log that is gone (or an older state of the file) had
/// issued them, as the log noted them in its chain.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct SkippedIds {
    /// The first id skipped.
    pub from: u64,
    /// The last id skipped (the last the station had issued).
    pub to: u64,
    /// The hash of record `to` as the station kept it.
    pub last_hash: String,
}

/// A row of the results log that notes the ids skipped just before it (the log's table
/// `gaps` says the same, for counting ids), in the same chain (and id sequence) as the
/// measurements, told apart by its `gap` field; appended with the first record after the
/// gap, so its time is read from the same clock, in the same transaction. Its id is one
/// past the last id skipped, its `prev_hash` the newest record's before the gap.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct GapRecord {
    /// Its id, station, software, place in the chain, hash and signature.
    #[serde(flatten)]
    pub header: NoteHeader,
    /// When the gap was recorded.
    pub time: UtcTime,
    /// The ids skipped.
    pub gap: SkippedIds,
}

impl GapRecord {
    /// The row noting `gap` at `time` with `id` after `prev_hash`, its hash computed.
    pub fn chain(
        station: &str,
        gap: SkippedIds,
        time: UtcTime,
        clock_synced: bool,
        id: u64,
        prev_hash: &str,
    ) -> Self {
        Self {
            header: NoteHeader::new(station, id, prev_hash, clock_synced),
            time,
            gap,
        }
        .chained()
    }
}

impl Row for GapRecord {
    fn hash_mut(&mut self) -> &mut String {
        &mut self.header.hash
    }
}

impl fmt::Display for ClockJump {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "the wall clock jumped {} from {} to {}",
            self.jump, self.previous, self.now
        )?;
        match self.monotonic_elapsed_ms {
            Some(ms) => write!(f, " while the monotonic clock moved on {ms} ms"),
            None => f.write_str(" (across a restart of the station)"),
        }
    }
}

/// SHA-256 (hex) of a set of legally relevant parameters: over the canonical bytes
/// ([`canonical_bytes`]) of the JSON object that maps each document's path to the
/// SHA-256 (hex) of its content. `documents` gives each path with its content.
pub fn parameters_sha256<'a>(documents: impl IntoIterator<Item = (String, &'a [u8])>) -> String {
    let map: Map<String, Value> = documents
        .into_iter()
        .map(|(path, content)| (path, Value::String(sha256_hex(content))))
        .collect();
    sha256_hex(&canonical_bytes(&Value::Object(map)))
}

/// A results log's head: its newest record's id and hash (id 0 and [`GENESIS`] before the
/// first), as the station publishes it (`/api/log/head`, CoAP `/station/head`, MQTT
/// `PREFIX/<station>/head`) and `results verify --head` checks a log against it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Head {
    /// The record's id.
    pub id: u64,
    /// Its hash.
    pub hash: String,
}

impl Head {
    /// Reads `ID:HASH`, or the JSON object `{"id":ID,"hash":HASH}` the station publishes.
    pub fn parse(text: &str) -> Result<Self, String> {
        let text = text.trim();
        let bad = || {
            format!(
                "{text:?} is not a head: ID:HASH (HASH 64 hex digits), or {{\"id\":ID,\"hash\":HASH}}"
            )
        };
        let head = if text.starts_with('{') {
            serde_json::from_str::<Self>(text).map_err(|_| bad())?
        } else {
            let (id, hash) = text.split_once(':').ok_or_else(bad)?;
            Self {
                id: id.trim().parse().map_err(|_| bad())?,
                hash: hash.trim().to_owned(),
            }
        };
        if head.hash.len() != 64 || !head.hash.bytes().all(|b| b.is_ascii_hexdigit()) {
            return Err(bad());
        }
        Ok(Self {
            hash: head.hash.to_ascii_lowercase(),
            ..head
        })
    }
}

impl fmt::Display for Head {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}:{}", self.id, self.hash)
    }
}

/// `row` as JSON without its `hash` and `signature`: what a chained row's hash is taken
/// over (an event's, a clock jump's, a gap's).
fn unhashed(row: &impl Serialize) -> Value {
    let mut v = serde_json::to_value(row).unwrap_or(Value::Null);
    if let Value::Object(map) = &mut v {
        map.remove("hash");
        map.remove("signature");
    }
    v
}

/// The canonical bytes of a JSON value: compact (no whitespace), object keys sorted by
/// their UTF-8 bytes at every level, strings escaped and numbers written as serde_json
/// writes them (integers as integers, other numbers in the shortest form that reads back
/// to the same f64).
pub fn canonical_bytes(v: &Value) -> Vec<u8> {
    serde_json::to_vec(&sorted(v)).unwrap_or_default()
}

/// `v` with the keys of every object inserted in sorted order (serde_json's map keeps
/// them sorted or in insertion order, depending on its features: both give sorted).
fn sorted(v: &Value) -> Value {
    match v {
        Value::Object(map) => {
            let mut keys: Vec<&String> = map.keys().collect();
            keys.sort();
            let mut out = Map::new();
            for k in keys {
                out.insert(k.clone(), sorted(&map[k]));
            }
            Value::Object(out)
        }
        Value::Array(items) => Value::Array(items.iter().map(sorted).collect()),
        other => other.clone(),
    }
}

/// SHA-256 of `bytes`, lower-case hex.
pub fn sha256_hex(bytes: &[u8]) -> String {
    hex(&Sha256::digest(bytes))
}

fn hex(bytes: &[u8]) -> String {
    use fmt::Write as _;
    let mut out = String::with_capacity(bytes.len() * 2);
    for b in bytes {
        let _ = write!(out, "{b:02x}");
    }
    out
}

/// A UTC time to the millisecond, written as RFC 3339 (`2026-11-26T23:17:09.123Z`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct UtcTime {
    /// Milliseconds since the UNIX epoch.
    pub unix_ms: i64,
}

impl UtcTime {
    /// The system clock's time now.
    pub fn now() -> Self {
        let unix_ms = match SystemTime::now().duration_since(UNIX_EPOCH) {
            Ok(d) => i64::try_from(d.as_millis()).unwrap_or(i64::MAX),
            Err(before) => -i64::try_from(before.duration().as_millis()).unwrap_or(i64::MAX),
        };
        Self { unix_ms }
    }

    /// Reads `YYYY-MM-DDTHH:MM:SS[.fff]Z` (RFC 3339 in UTC; up to 9 fraction digits, kept
    /// to the millisecond).
    pub fn parse(text: &str) -> Result<Self, String> {
        let bad = || format!("{text:?} is not a UTC time as 2026-11-26T23:17:09.123Z");
        let b = text.as_bytes();
        if b.len() < 20 || b[4] != b'-' || b[7] != b'-' || !matches!(b[10], b'T' | b't') {
            return Err(bad());
        }
        if b[13] != b':' || b[16] != b':' || !matches!(b[b.len() - 1], b'Z' | b'z') {
            return Err(bad());
        }
        let num = |r: std::ops::Range<usize>| -> Result<i64, String> {
            let s = text.get(r).ok_or_else(bad)?;
            if !s.bytes().all(|c| c.is_ascii_digit()) {
                return Err(bad());
            }
            s.parse().map_err(|_| bad())
        };
        let (year, month, day) = (num(0..4)?, num(5..7)?, num(8..10)?);
        let (hour, minute, second) = (num(11..13)?, num(14..16)?, num(17..19)?);
        let mut ms = 0;
        let rest = &text[19..text.len() - 1];
        if !rest.is_empty() {
            let digits = rest.strip_prefix('.').ok_or_else(bad)?;
            if digits.is_empty() || digits.len() > 9 || !digits.bytes().all(|c| c.is_ascii_digit())
            {
                return Err(bad());
            }
            let padded = format!("{digits:0<3}");
            ms = padded[..3].parse::<i64>().map_err(|_| bad())?;
        }
        if !(1..=12).contains(&month)
            || day < 1
            || day > days_in_month(year, month)
            || hour > 23
            || minute > 59
            || second > 59
        {
            return Err(bad());
        }
        let days = days_from_civil(year, month, day);
        Ok(Self {
            unix_ms: ((days * 24 + hour) * 60 + minute) * 60_000 + second * 1000 + ms,
        })
    }
}

impl fmt::Display for UtcTime {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let days = self.unix_ms.div_euclid(86_400_000);
        let ms_of_day = self.unix_ms.rem_euclid(86_400_000);
        let (y, m, d) = civil_from_days(days);
        write!(
            f,
            "{y:04}-{m:02}-{d:02}T{:02}:{:02}:{:02}.{:03}Z",
            ms_of_day / 3_600_000,
            ms_of_day / 60_000 % 60,
            ms_of_day / 1000 % 60,
            ms_of_day % 1000
        )
    }
}

impl Serialize for UtcTime {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.collect_str(self)
    }
}

impl<'de> Deserialize<'de> for UtcTime {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let text = String::deserialize(d)?;
        Self::parse(&text).map_err(serde::de::Error::custom)
    }
}

fn is_leap(year: i64) -> bool {
    (year % 4 == 0 && year % 100 != 0) || year % 400 == 0
}

fn days_in_month(year: i64, month: i64) -> i64 {
    match month {
        2 if is_leap(year) => 29,
        2 => 28,
        4 | 6 | 9 | 11 => 30,
        _ => 31,
    }
}

/// Days since 1970-01-01 of a proleptic Gregorian date (the era arithmetic: 400-year
/// cycles of 146097 days, years starting in March so the leap day comes last).
fn days_from_civil(year: i64, month: i64, day: i64) -> i64 {
    let y = if month <= 2 { year - 1 } else { year };
    let era = y.div_euclid(400);
    let yoe = y - era * 400;
    let mp = (month + 9) % 12;
    let doy = (153 * mp + 2) / 5 + day - 1;
    let doe = yoe * 365 + yoe / 4 - yoe / 100 + doy;
    era * 146_097 + doe - 719_468
}

/// The date of a day count since 1970-01-01 (the inverse of [`days_from_civil`]).
fn civil_from_days(days: i64) -> (i64, i64, i64) {
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    (year, month, day)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    #[test]
    fn utc_times_read_back_as_written() {
        for (ms, text) in [
            (0, "1970-01-01T00:00:00.000Z"),
            (951_782_400_000, "2000-02-29T00:00:00.000Z"),
            (1_795_734_229_123, "2026-11-26T23:03:49.123Z"),
            (-1, "1969-12-31T23:59:59.999Z"),
            (4_107_542_399_999, "2100-02-28T23:59:59.999Z"),
        ] {
            let t = UtcTime { unix_ms: ms };
            assert_eq!(t.to_string(), text);
            assert_eq!(UtcTime::parse(text), Ok(t));
        }
        assert_eq!(
            UtcTime::parse("2026-11-26T23:03:49Z").map(|t| t.unix_ms),
            Ok(1_795_734_229_000)
        );
        assert_eq!(
            UtcTime::parse("2026-11-26T23:03:49.12345Z").map(|t| t.unix_ms),
            Ok(1_795_734_229_123)
        );
        for bad in [
            "",
            "2026-11-26 19:43:49Z",
            "2026-02-29T00:00:00Z",
            "2026-11-26T24:00:00Z",
            "2026-11-26T23:03:49.Z",
            "2026-11-26T23:03:49+01:00",
            "２026-11-26T19:43:49Z",
        ] {
            assert!(UtcTime::parse(bad).is_err(), "{bad}");
        }
    }

    /// A measurement of a parcel `length_mm` long with a QR code `code`.
    pub(crate) fn measurement(length_mm: f64, code: &str) -> Measurement {
        serde_json::from_value(serde_json::json!({
            "v": 1, "parcel": "measured", "length_mm": length_mm, "width_mm": 200.0,
            "height_mm": 150.0, "division_mm": null, "yaw_deg": 0.0,
            "corners_m": [[0.1, 0.1], [-0.1, 0.1], [-0.1, -0.1], [0.1, -0.1]],
            "volume_l": length_mm * 0.03, "volumetric_weight_kg": length_mm * 0.000_006,
            "volumetric_divisor_cm3_per_kg": 5000.0, "parcel_points": 1000,
            "cloud_points": 5000, "cameras": ["840412060746"], "frames_unix_us": [1],
            "grab_ms": 10.0, "warnings": [],
            "codes": [{"kind": "qr", "text": code, "cameras": ["840412060746"]}],
        }))
        .expect("a measurement")
    }

    /// Record `n` of a lane's tests: taken `n` ms after a fixed time, of a parcel 300 + `n`
    /// mm long with the QR code `code`, no cameras and no pictures.
    pub(crate) fn numbered_record(n: u64, code: &str) -> NewRecord {
        NewRecord {
            time: UtcTime {
                unix_ms: 1_795_734_229_000 + i64::try_from(n).unwrap_or(0),
            },
            station: "lane-1".into(),
            trigger: Trigger::Request,
            measurement: measurement(300.0 + n as f64, code),
            cameras: Vec::new(),
            version: NewRecord::VERSION.into(),
            software_sha256: crate::identity::SOFTWARE_SHA256.into(),
            photo_jpeg: None,
            annotated_png: None,
            parameters_sha256: None,
        }
    }

    /// The record of issue 51, item 4: a parcel measured 322.6 x 241.3 x 99.8 mm, billed
    /// at the default 5 mm division, with a code.
    pub(crate) fn billed_record() -> Record {
        let fit = geometry::ParcelFit::whole_box(geometry::Dimensions {
            length_mm: 322.6,
            width_mm: 241.3,
            height_mm: 99.8,
            yaw_deg: 0.0,
            corners_m: [[0.0, 0.0], [0.3226, 0.0], [0.3226, 0.2413], [0.0, 0.2413]],
            volume_l: 0.3226 * 0.2413 * 0.0998 * 1e3,
            points: 4000,
        });
        let table = crate::report::Table {
            fits: vec![fit],
            largest_points: 4000,
        };
        let mut new = new_record();
        new.measurement = Measurement::of_table(
            &table,
            &crate::report::Billing::default(),
            0.8,
            5000,
            vec!["840412060746".into()],
            vec![1],
            std::time::Duration::ZERO,
        );
        Record::chain(&new, 7, GENESIS, 0)
    }

    fn new_record() -> NewRecord {
        NewRecord {
            time: UtcTime {
                unix_ms: 1_795_734_229_123,
            },
            station: "lane-1".into(),
            trigger: Trigger::Request,
            measurement: measurement(300.1, "PKG-1"),
            cameras: vec![CameraPose {
                serial: "840412060746".into(),
                transformation: Transformation::identity(),
            }],
            version: NewRecord::VERSION.into(),
            software_sha256: crate::identity::SOFTWARE_SHA256.into(),
            photo_jpeg: Some(vec![1, 2, 3]),
            annotated_png: None,
            parameters_sha256: None,
        }
    }

    #[test]
    fn the_hash_covers_the_content_and_not_the_pictures_kept() {
        let r = Record::chain(&new_record(), 1, GENESIS, 0);
        assert_eq!(r.hash.len(), 64);
        assert_eq!(
            r.photo_sha256.as_deref(),
            Some(sha256_hex(&[1, 2, 3]).as_str())
        );
        assert_eq!(r.annotated_sha256, None);
        assert_eq!(Record::compute_hash(&r.content()), r.hash);
        let mut pruned = r.clone();
        pruned.has_photo = false;
        assert_eq!(Record::compute_hash(&pruned.content()), r.hash);
        let mut altered = r.clone();
        altered.measurement = measurement(300.2, "PKG-1");
        assert_ne!(Record::compute_hash(&altered.content()), r.hash);
        let next = Record::chain(&new_record(), 2, &r.hash, 0);
        assert_ne!(next.hash, r.hash);
        let body = r.stored_body();
        let back = Record::from_stored(&body, r.hash.clone(), true, false).expect("reads");
        assert_eq!(back, r);
        assert_eq!(back.code_texts(), ["PKG-1"]);
    }

    #[test]
    fn records_carry_the_software_checksum_and_older_ones_still_verify() {
        let r = Record::chain(&new_record(), 1, GENESIS, 0);
        assert_eq!(
            r.software_sha256.as_deref(),
            Some(crate::identity::SOFTWARE_SHA256)
        );
        let mut other = r.clone();
        other.software_sha256 = Some("0".repeat(64));
        assert_ne!(
            Record::compute_hash(&other.content()),
            r.hash,
            "it is hashed"
        );
        // A record from before the fields (the software's checksum, the events and the
        // parameters): its body has no such keys, and reads back to the same canonical
        // bytes and hash.
        let mut old = r.content();
        for key in ["software_sha256", "events", "parameters_sha256"] {
            old.as_object_mut().expect("an object").remove(key);
        }
        let body = canonical_bytes(&old);
        let hash = Record::hash_of(&body);
        let back = Record::from_stored(&body, hash.clone(), true, false).expect("reads");
        assert_eq!(back.software_sha256, None);
        assert_eq!(
            (back.events, back.parameters_sha256.as_deref()),
            (None, None)
        );
        assert_eq!(back.stored_body(), body);
        assert_eq!(Record::compute_hash(&back.content()), hash);
    }

    #[test]
    fn a_head_reads_as_id_colon_hash_or_as_the_json_the_station_publishes() {
        let hash = "AB".repeat(32);
        let head = Head::parse(&format!("20:{hash}")).expect("ID:HASH");
        assert_eq!(
            (head.id, head.hash.as_str()),
            (20, "ab".repeat(32).as_str())
        );
        assert_eq!(head.to_string(), format!("20:{}", "ab".repeat(32)));
        let json = serde_json::to_string(&head).expect("JSON");
        assert_eq!(Head::parse(&json), Ok(head));
        for bad in [
            "",
            "20",
            "x:ab",
            "20:abc",
            &format!("20:{}", "g".repeat(64)),
        ] {
            assert!(Head::parse(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn stored_records_read_back_bit_for_bit() {
        // Numbers whose shortest decimal form a fast float parser reads 1 ulp off: the
        // log must give back exactly what it recorded, and its bytes stay canonical.
        for k in 0..2000u32 {
            let length = 300.0 + f64::from(k) * 0.000_006_1;
            let mut new = new_record();
            new.measurement = measurement(length, "PKG-1");
            let r = Record::chain(&new, u64::from(k) + 1, GENESIS, 0);
            let body = r.stored_body();
            let back = Record::from_stored(&body, r.hash.clone(), true, false).expect("reads");
            assert_eq!(back, r, "{length}");
            let value: Value = serde_json::from_slice(&body).expect("JSON");
            assert_eq!(canonical_bytes(&value), body, "{length}");
            assert_eq!(Record::hash_of(&body), r.hash);
        }
    }

    #[test]
    fn clock_and_gap_notes_keep_their_stored_bytes() {
        // The bodies these rows were stored with before they shared their chain fields:
        // a log written then verifies now.
        let at = |unix_ms| UtcTime { unix_ms };
        let jump = ClockJump {
            jump: "back".into(),
            previous: at(1_795_734_229_123),
            now: at(1_795_734_228_000),
            monotonic_elapsed_ms: Some(1200),
        };
        let clock = ClockRecord::chain("lane-1", jump, true, 5, &"ab".repeat(32));
        let gap = SkippedIds {
            from: 3,
            to: 8,
            last_hash: "cd".repeat(32),
        };
        let gap = GapRecord::chain("lane-1", gap, at(1_795_734_230_456), false, 9, GENESIS);
        let ours = |text: &str| {
            text.replace("VERSION", NewRecord::VERSION)
                .replace("SOFTWARE", crate::identity::SOFTWARE_SHA256)
        };
        for (body, hash, old) in [
            (clock.stored_body(), &clock.header.hash, ours(CLOCK_ROW)),
            (gap.stored_body(), &gap.header.hash, ours(GAP_ROW)),
        ] {
            assert_eq!(String::from_utf8_lossy(&body), old);
            assert_eq!(*hash, Record::hash_of(old.as_bytes()));
        }
        let json = serde_json::to_value(&clock).expect("JSON");
        assert_eq!(json["hash"], clock.header.hash.as_str(), "flattened");
        assert_eq!(
            serde_json::from_value::<ClockRecord>(json).ok(),
            Some(clock)
        );
        let json = serde_json::to_value(&gap).expect("JSON");
        assert_eq!(serde_json::from_value::<GapRecord>(json).ok(), Some(gap));
    }

    #[test]
    fn events_keep_their_stored_bytes() {
        // The bodies events were stored with before they shared the clock and gap rows'
        // hashing (`Row`): a log written then verifies now. An event from before
        // `clock_synced` has none.
        let new = NewEvent {
            time: UtcTime {
                unix_ms: 1_795_734_231_789,
            },
            station: "lane-1".into(),
            event: Event {
                document: "/cams/840412060746/3d-transformation".into(),
                change: Change::Put,
                old_sha256: "01".repeat(32),
                new_sha256: "02".repeat(32),
                by: "coaps://127.0.0.1:40000 psk-identity lane".into(),
                parameters_sha256: "03".repeat(32),
            },
        };
        let ours = |text: &str| {
            text.replace("VERSION", NewRecord::VERSION)
                .replace("SOFTWARE", crate::identity::SOFTWARE_SHA256)
        };
        let unsynced = EVENT_ROW.replace(r#""clock_synced":false,"#, "");
        assert_ne!(unsynced, EVENT_ROW);
        for (synced, row) in [(Some(false), EVENT_ROW), (None, &unsynced)] {
            let mut event = EventRecord::chain(&new, 11, &"ef".repeat(32), 2, synced);
            let body = event.stored_body();
            let old = ours(row);
            assert_eq!(String::from_utf8_lossy(&body), old);
            assert_eq!(event.hash, Record::hash_of(old.as_bytes()));
            event.signature = Some("signed".into());
            assert_eq!(event.stored_body(), body, "the signature is not stored");
            assert_eq!(
                EventRecord::from_stored(&body, event.hash.clone()).ok(),
                Some(EventRecord {
                    signature: None,
                    ..event
                })
            );
        }
    }

    const EVENT_ROW: &str = concat!(
        r#"{"clock_synced":false,"counter":2,"event":{"#,
        r#""by":"coaps://127.0.0.1:40000 psk-identity lane","change":"put","#,
        r#""document":"/cams/840412060746/3d-transformation","#,
        r#""new_sha256":"0202020202020202020202020202020202020202020202020202020202020202","#,
        r#""old_sha256":"0101010101010101010101010101010101010101010101010101010101010101","#,
        r#""parameters_sha256":"0303030303030303030303030303030303030303030303030303030303030303"},"#,
        r#""id":11,"prev_hash":"efefefefefefefefefefefefefefefefefefefefefefefefefefefefefefefef","#,
        r#""software_sha256":"SOFTWARE","station":"lane-1","time":"2026-11-26T23:03:51.789Z","#,
        r#""version":"VERSION"}"#
    );

    const CLOCK_ROW: &str = concat!(
        r#"{"clock":{"jump":"back","monotonic_elapsed_ms":1200,"now":"2026-11-26T23:03:48.000Z","#,
        r#""previous":"2026-11-26T23:03:49.123Z"},"clock_synced":true,"id":5,"#,
        r#""prev_hash":"abababababababababababababababababababababababababababababababab","#,
        r#""software_sha256":"SOFTWARE","station":"lane-1","time":"2026-11-26T23:03:48.000Z","#,
        r#""version":"VERSION"}"#
    );
    const GAP_ROW: &str = concat!(
        r#"{"clock_synced":false,"gap":{"from":3,"#,
        r#""last_hash":"cdcdcdcdcdcdcdcdcdcdcdcdcdcdcdcdcdcdcdcdcdcdcdcdcdcdcdcdcdcdcdcd","to":8},"#,
        r#""id":9,"prev_hash":"0000000000000000000000000000000000000000000000000000000000000000","#,
        r#""software_sha256":"SOFTWARE","station":"lane-1","time":"2026-11-26T23:03:50.456Z","#,
        r#""version":"VERSION"}"#
    );

    #[test]
    fn canonical_bytes_sort_keys_at_every_level_and_have_no_whitespace() {
        let v: Value =
            serde_json::from_str(r#"{ "b": 1, "a": {"z": [ {"y": 2, "x": 1.5} ], "c": null} }"#)
                .expect("json");
        assert_eq!(
            canonical_bytes(&v),
            br#"{"a":{"c":null,"z":[{"x":1.5,"y":2}]},"b":1}"#
        );
    }
}
