//! Camera backends.

pub mod playback;
pub mod realsense;
pub mod synthetic;

use std::time::{SystemTime, UNIX_EPOCH};

use crate::mode::Stream;

/// Frame numbers per stream and wall-clock timestamps, as every backend stamps
/// grabbed frames.
#[derive(Debug, Default)]
pub(crate) struct FrameClock {
    depth_frames: u64,
    color_frames: u64,
    last_timestamp_us: u64,
}

impl FrameClock {
    /// The next frame number of `stream` (from 1) and a wall-clock timestamp (µs since
    /// the epoch, strictly increasing per clock).
    pub(crate) fn stamp(&mut self, stream: Stream) -> (u64, u64) {
        let counter = match stream {
            Stream::Depth => &mut self.depth_frames,
            Stream::Color => &mut self.color_frames,
        };
        *counter += 1;
        let frame_number = *counter;
        let now_us = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map_or(0, |d| d.as_micros().try_into().unwrap_or(u64::MAX));
        let timestamp_us = now_us.max(self.last_timestamp_us + 1);
        self.last_timestamp_us = timestamp_us;
        (frame_number, timestamp_us)
    }
}
