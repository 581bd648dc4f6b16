//! The `Camera` trait every backend implements (what every depth camera has), the
//! capabilities only some cameras have ([`AdvancedMode`], a D400's), and the `CameraHub`
//! that tracks which cameras are connected (hot-plug).

use std::collections::BTreeMap;
use std::fmt;
use std::sync::mpsc::{self, Receiver, Sender};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::time::Duration;

use crate::advanced::{AdvancedConfig, AdvancedError};
use crate::frame::{ColorFrame, DepthFrame};
use crate::intrinsics::{Extrinsics, Intrinsics, Pose};
use crate::mode::{ModeError, ModeTable};
use crate::settings::{ColorSettings, DepthSettings};

/// A camera serial number: 1 to [`Serial::MAX_LEN`] ASCII letters, digits, `-` and `_`,
/// the first a letter or a digit. A D400's is 12 digits (thesis §3.3.3); another backend
/// names its cameras as it likes within these bounds, which keep a serial usable as it is
/// in a URI path (`/cams/<serial>/color`), a file name (the state directory) and a
/// command-line value.
#[derive(Clone, Copy, PartialEq, Eq, Hash)]
pub struct Serial {
    /// The text, then zeros.
    bytes: [u8; Self::MAX_LEN],
    len: u8,
}

/// Why a text is not a serial number.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error(
    "a serial number is 1 to {max} ASCII letters, digits, '-' and '_', the first a letter or digit; got {:?}",
    crate::echo(.0),
    max = Serial::MAX_LEN
)]
pub struct SerialError(pub String);

impl Serial {
    /// The longest serial number, characters.
    pub const MAX_LEN: usize = 32;

    /// Parses a serial number (no surrounding whitespace; see [`Serial`]).
    pub fn parse(text: &str) -> Result<Self, SerialError> {
        let b = text.as_bytes();
        let first_ok = b.first().is_some_and(u8::is_ascii_alphanumeric);
        let rest_ok = b
            .iter()
            .all(|&c| c.is_ascii_alphanumeric() || c == b'-' || c == b'_');
        if !(first_ok && rest_ok && b.len() <= Self::MAX_LEN) {
            return Err(SerialError(text.to_owned()));
        }
        let mut bytes = [0; Self::MAX_LEN];
        bytes[..b.len()].copy_from_slice(b);
        Ok(Self {
            bytes,
            // At most MAX_LEN (32), checked above.
            len: b.len() as u8,
        })
    }

    /// A D400-style serial from digits the caller knows are ASCII digits (built-in
    /// scenes).
    pub(crate) const fn from_digits(digits: [u8; 12]) -> Self {
        let mut bytes = [0; Self::MAX_LEN];
        let mut i = 0;
        while i < digits.len() {
            bytes[i] = digits[i];
            i += 1;
        }
        Self { bytes, len: 12 }
    }

    /// The serial's text.
    pub fn as_str(&self) -> &str {
        // The bytes are ASCII (checked in `parse`), so this never falls back.
        std::str::from_utf8(&self.bytes[..usize::from(self.len)]).unwrap_or_default()
    }

    /// The serial as a number, for seeding and hashing: a serial of 12 digits (a D400's)
    /// is its value; any other, the 64-bit FNV-1a hash of its text.
    pub fn as_u64(&self) -> u64 {
        let text = self.as_str().as_bytes();
        if text.len() == 12 && text.iter().all(u8::is_ascii_digit) {
            return text.iter().fold(0, |acc, d| acc * 10 + u64::from(d - b'0'));
        }
        text.iter().fold(0xcbf2_9ce4_8422_2325, |h, &c| {
            (h ^ u64::from(c)).wrapping_mul(0x0000_0100_0000_01b3)
        })
    }
}

impl PartialOrd for Serial {
    fn partial_cmp(&self, other: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(other))
    }
}

/// In the order of their text: the order a client sorting the serials it discovers has.
impl Ord for Serial {
    fn cmp(&self, other: &Self) -> std::cmp::Ordering {
        self.as_str().cmp(other.as_str())
    }
}

impl fmt::Debug for Serial {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_tuple("Serial").field(&self.as_str()).finish()
    }
}

impl fmt::Display for Serial {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

impl std::str::FromStr for Serial {
    type Err = SerialError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Self::parse(s)
    }
}

/// A setting the camera refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum SettingError {
    /// A color or depth mode outside the camera's table.
    #[error(transparent)]
    Mode(#[from] ModeError),
    /// An advanced-config document the camera cannot load.
    #[error(transparent)]
    Advanced(#[from] AdvancedError),
}

/// Errors of camera operations.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum CameraError {
    /// No frame arrived within the timeout.
    #[error("no frame within {timeout_ms} ms")]
    Timeout {
        /// The timeout that passed.
        timeout_ms: u64,
    },
    /// The camera is gone.
    #[error("camera {serial} is disconnected")]
    Disconnected {
        /// Its serial number.
        serial: Serial,
    },
    /// A setting was refused; nothing was changed.
    #[error("invalid setting: {0}")]
    InvalidSetting(#[from] SettingError),
    /// The device or its driver library failed (e.g. a librealsense call).
    #[error("device error: {0}")]
    Device(String),
    /// The advanced config ([`AdvancedMode`]) needs the D400's advanced mode, which this
    /// device has disabled.
    #[error("camera {serial} has no advanced mode enabled (needed for the advanced config)")]
    AdvancedModeUnavailable {
        /// Its serial number.
        serial: Serial,
    },
}

impl From<ModeError> for CameraError {
    fn from(e: ModeError) -> Self {
        Self::InvalidSetting(SettingError::Mode(e))
    }
}

impl From<AdvancedError> for CameraError {
    fn from(e: AdvancedError) -> Self {
        Self::InvalidSetting(SettingError::Advanced(e))
    }
}

/// An RGB-D camera: what every depth camera has. What only some have, a camera hands out
/// as a capability (`None` when it has not got it): [`Camera::advanced_mode`].
/// Object-safe; shared as `Arc<dyn Camera>` between threads. Methods block (a grab waits
/// for a frame); call them off async executors.
pub trait Camera: Send + Sync {
    /// Serial number.
    fn serial(&self) -> Serial;

    /// Product name, e.g. "Intel RealSense D415".
    fn model(&self) -> &str;

    /// The stream modes the camera offers.
    fn stream_modes(&self) -> &ModeTable;

    /// Current color settings.
    fn color_settings(&self) -> ColorSettings;

    /// Changes the color settings after checking them against the mode table.
    fn set_color_settings(&self, settings: ColorSettings) -> Result<(), CameraError>;

    /// Current depth settings.
    fn depth_settings(&self) -> DepthSettings;

    /// Changes the depth settings after checking them against the mode table.
    fn set_depth_settings(&self, settings: DepthSettings) -> Result<(), CameraError>;

    /// Waits at most `timeout` for a new color frame.
    fn grab_color(&self, timeout: Duration) -> Result<ColorFrame, CameraError>;

    /// Waits at most `timeout` for a new depth frame.
    fn grab_depth(&self, timeout: Duration) -> Result<DepthFrame, CameraError>;

    /// Intrinsics of the depth stream in its current mode.
    fn depth_intrinsics(&self) -> Result<Intrinsics, CameraError>;

    /// Intrinsics of the color stream in its current mode.
    fn color_intrinsics(&self) -> Result<Intrinsics, CameraError>;

    /// Transform from the depth frame to the color frame.
    fn depth_to_color(&self) -> Result<Extrinsics, CameraError>;

    /// Metres per raw depth unit.
    fn depth_scale(&self) -> f32;

    /// The distance between the two imagers of the depth stereo pair, metres (55 mm on a
    /// D415, 50 mm on a D435), or `None` for a camera that measures depth without a
    /// stereo pair (time of flight, one imager and a projected pattern). What works on
    /// disparity needs it: the spatial filter, and telling stereo shadows from surfaces
    /// that return no depth.
    fn stereo_baseline_m(&self) -> Option<f32>;

    /// The D400's advanced mode, when the camera has it; `None` (the default) otherwise.
    fn advanced_mode(&self) -> Option<&dyn AdvancedMode> {
        None
    }

    /// The calibrated pose of the depth frame in the world, when the camera knows it
    /// (a synthetic camera with `calibrated = true`), so a server can preload its
    /// 3d-transformation; `None` otherwise.
    fn true_pose(&self) -> Option<Pose>;
}

/// The advanced mode of an Intel RealSense D400 camera: the depth unit, the stereo
/// matcher's thresholds and the rest of the advanced-config document (thesis Listing
/// A.5). A camera that has it hands it out through [`Camera::advanced_mode`].
pub trait AdvancedMode: Send + Sync {
    /// The complete advanced-config document (Listing A.5).
    fn advanced_config(&self) -> Result<AdvancedConfig, CameraError>;

    /// Loads an advanced-config document (possibly partial, as `rs2_load_json`).
    fn set_advanced_config(&self, config: &AdvancedConfig) -> Result<(), CameraError>;
}

/// A camera appeared or disappeared.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum HubEvent {
    /// A camera with this serial is now in the hub.
    Added(Serial),
    /// The camera with this serial left the hub.
    Removed(Serial),
}

/// Errors of hub operations.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum HubError {
    /// A camera with the same serial is already in the hub.
    #[error("a camera with serial {0} is already connected")]
    Duplicate(Serial),
}

#[derive(Default)]
struct HubInner {
    cameras: BTreeMap<Serial, Arc<dyn Camera>>,
    subscribers: Vec<Sender<HubEvent>>,
}

impl HubInner {
    fn publish(&mut self, event: HubEvent) {
        self.subscribers.retain(|s| s.send(event).is_ok());
    }
}

/// The connected cameras, by serial. Backends add and remove cameras as they come and
/// go; subscribers receive [`HubEvent`]s in order.
#[derive(Default)]
pub struct CameraHub {
    inner: Mutex<HubInner>,
}

impl fmt::Debug for CameraHub {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("CameraHub")
            .field("serials", &self.serials())
            .finish()
    }
}

impl CameraHub {
    /// An empty hub.
    pub fn new() -> Self {
        Self::default()
    }

    fn lock(&self) -> MutexGuard<'_, HubInner> {
        // The map stays consistent even if a holder panicked: every update is one insert
        // or remove.
        self.inner.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Adds a camera and tells subscribers.
    pub fn add(&self, camera: Arc<dyn Camera>) -> Result<(), HubError> {
        let serial = camera.serial();
        let mut inner = self.lock();
        if inner.cameras.contains_key(&serial) {
            return Err(HubError::Duplicate(serial));
        }
        inner.cameras.insert(serial, camera);
        inner.publish(HubEvent::Added(serial));
        Ok(())
    }

    /// Removes a camera and tells subscribers; returns it, or `None` if it was not here.
    pub fn remove(&self, serial: &Serial) -> Option<Arc<dyn Camera>> {
        let mut inner = self.lock();
        let camera = inner.cameras.remove(serial)?;
        inner.publish(HubEvent::Removed(*serial));
        Some(camera)
    }

    /// The camera with this serial.
    pub fn get(&self, serial: &Serial) -> Option<Arc<dyn Camera>> {
        self.lock().cameras.get(serial).cloned()
    }

    /// Serials of the connected cameras, ascending.
    pub fn serials(&self) -> Vec<Serial> {
        self.lock().cameras.keys().copied().collect()
    }

    /// A receiver of hub events. It first receives `Added` for every camera already
    /// connected, then every later change, so a subscriber never misses a camera.
    /// Dropping the receiver unsubscribes.
    pub fn subscribe(&self) -> Receiver<HubEvent> {
        let (tx, rx) = mpsc::channel();
        let mut inner = self.lock();
        for serial in inner.cameras.keys() {
            // The receiver is alive: it is returned below.
            let _ = tx.send(HubEvent::Added(*serial));
        }
        inner.subscribers.push(tx);
        rx
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn serial_takes_a_d400_s_twelve_digits_and_other_backends_names() {
        assert_eq!(
            Serial::parse("840412060746").unwrap().as_str(),
            "840412060746"
        );
        assert_eq!(
            Serial::parse("840412060746").unwrap().as_u64(),
            840_412_060_746
        );
        assert_eq!(
            Serial::from_digits(*b"840412060746"),
            Serial::parse("840412060746").unwrap()
        );
        let longest = "a".repeat(Serial::MAX_LEN);
        for good in ["rec-01", "cam_2", "A", "84041206074", longest.as_str()] {
            assert_eq!(Serial::parse(good).unwrap().as_str(), good);
        }
        let too_long = "a".repeat(Serial::MAX_LEN + 1);
        for bad in [
            "",
            " 84041206074",
            "-rec",
            "_rec",
            "rec.01",
            "rec/01",
            "rec 01",
            "..",
            "kamera-ä",
            too_long.as_str(),
        ] {
            assert!(Serial::parse(bad).is_err(), "{bad:?}");
        }
        // Other serials seed by their text; they differ from one another and from the
        // 12-digit numbers.
        let seeds = ["rec-01", "rec-02", "84041206074"].map(|t| Serial::parse(t).unwrap().as_u64());
        assert!(seeds[0] != seeds[1] && seeds[1] != seeds[2] && seeds[0] != seeds[2]);
        // Ordered as text, whatever the lengths.
        let mut serials =
            ["rec-01", "840412060746", "b", "840412060745"].map(|t| Serial::parse(t).unwrap());
        serials.sort();
        assert_eq!(
            serials.map(|s| s.to_string()),
            ["840412060745", "840412060746", "b", "rec-01"]
        );
    }
}
