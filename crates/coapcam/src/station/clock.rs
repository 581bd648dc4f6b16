//! The station's clock, as the results log reads it: the wall clock a record's `time`
//! comes from, a monotonic clock beside it (which nobody sets, so a jump of the wall
//! clock shows against it), and whether the kernel says the wall clock is synchronised.
//! The log reads it through [`Clock`], so a test sets its time back ([`ManualClock`]).
//! docs/station.md, "The clock", says what is recorded.

use std::sync::{Mutex, PoisonError};
use std::time::{Duration, Instant};

use crate::api::record::UtcTime;

/// One reading of the clocks.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Reading {
    /// The wall clock (UTC).
    pub wall: UtcTime,
    /// The monotonic clock: time since some fixed start, never set back or forward.
    pub monotonic: Duration,
    /// Whether the kernel says the wall clock is synchronised (by NTP, PTP, ...).
    pub synced: bool,
}

/// Where the results log reads the time.
pub trait Clock: Send + Sync + std::fmt::Debug {
    /// The clocks now.
    fn read(&self) -> Reading;
}

/// The system's clocks: `CLOCK_REALTIME` (through `SystemTime`), `CLOCK_MONOTONIC`
/// (through `Instant`) and the kernel's synchronisation status
/// ([`kernel_clock::synchronised`]: `adjtimex(2)`'s `STA_UNSYNC`).
#[derive(Debug)]
pub struct SystemClock {
    start: Instant,
}

impl Default for SystemClock {
    fn default() -> Self {
        Self {
            start: Instant::now(),
        }
    }
}

impl Clock for SystemClock {
    fn read(&self) -> Reading {
        Reading {
            wall: UtcTime::now(),
            monotonic: self.start.elapsed(),
            synced: kernel_clock::synchronised(),
        }
    }
}

/// A clock a test sets: its wall clock moved by hand, its monotonic clock advanced by
/// hand, its synchronisation as told.
#[derive(Debug)]
pub struct ManualClock {
    now: Mutex<Reading>,
}

impl ManualClock {
    /// A clock at `wall`, monotonic 0, synchronised.
    pub fn new(wall: UtcTime) -> Self {
        Self {
            now: Mutex::new(Reading {
                wall,
                monotonic: Duration::ZERO,
                synced: true,
            }),
        }
    }

    fn with(&self, f: impl FnOnce(&mut Reading)) {
        f(&mut self.now.lock().unwrap_or_else(PoisonError::into_inner));
    }

    /// Time passes: both clocks move on by `by`.
    pub fn advance(&self, by: Duration) {
        let ms = i64::try_from(by.as_millis()).unwrap_or(i64::MAX);
        self.with(|r| {
            r.wall.unix_ms = r.wall.unix_ms.saturating_add(ms);
            r.monotonic += by;
        });
    }

    /// The wall clock is set, by `by_ms` milliseconds (negative: back); the monotonic
    /// clock does not move.
    pub fn set_wall_by(&self, by_ms: i64) {
        self.with(|r| r.wall.unix_ms = r.wall.unix_ms.saturating_add(by_ms));
    }

    /// The kernel says the clock is (or is not) synchronised.
    pub fn set_synced(&self, synced: bool) {
        self.with(|r| r.synced = synced);
    }
}

impl Clock for ManualClock {
    fn read(&self) -> Reading {
        *self.now.lock().unwrap_or_else(PoisonError::into_inner)
    }
}
