//! The memory grabs in progress may take together. Each grab reserves what it will hold
//! at its peak (frames, filtered copies, points, the encoded answer), estimated from the
//! camera's stream modes, before it starts; a grab that would pass the budget answers
//! 5.03 with Max-Age at once instead of growing the process without bound. One grab may
//! always run, whatever it costs, so a camera larger than the budget still works.
//! The representation a grab leaves for its Block2 continuations is bounded separately,
//! by the endpoint's store (`Limits::block2_store_bytes`).

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};

use coap::{Code, OptionNumber, Response};
use rgbd::{ColorSettings, DepthSettings};

use crate::repr::Stream;

/// The default budget (`serve --grab-memory`): 256 MiB, about eight point-cloud grabs of
/// a 1280x720 camera.
pub(crate) const DEFAULT_BYTES: u64 = 256 << 20;

/// Seconds a refused client is told to wait (Max-Age of the 5.03).
const RETRY_SECS: u32 = 1;

/// Bytes held by the grabs in progress, and the limit.
#[derive(Debug)]
pub(super) struct Budget {
    limit: AtomicU64,
    used: Mutex<u64>,
}

/// A reservation, given back when dropped.
#[derive(Debug)]
pub(super) struct Held {
    budget: Arc<Budget>,
    bytes: u64,
}

impl Drop for Held {
    fn drop(&mut self) {
        let mut used = self
            .budget
            .used
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        *used -= self.bytes;
    }
}

impl Budget {
    pub(super) fn new(limit: u64) -> Arc<Self> {
        Arc::new(Self {
            limit: AtomicU64::new(limit),
            used: Mutex::new(0),
        })
    }

    pub(super) fn set_limit(&self, limit: u64) {
        self.limit.store(limit, Ordering::Relaxed);
    }

    /// Reserves `bytes`, or says how full the budget is.
    pub(super) fn take(self: &Arc<Self>, bytes: u64) -> Result<Held, Busy> {
        let limit = self.limit.load(Ordering::Relaxed);
        let mut used = self.used.lock().unwrap_or_else(PoisonError::into_inner);
        if *used > 0 && *used + bytes > limit {
            return Err(Busy { used: *used, limit });
        }
        *used += bytes;
        Ok(Held {
            budget: self.clone(),
            bytes,
        })
    }
}

/// A grab refused: what the grabs in progress hold, and the budget.
#[derive(Debug, thiserror::Error)]
#[error(
    "the grabs in progress hold {} of this server's {} MiB for grabs; try again in {RETRY_SECS} s",
    mib(*.used),
    mib(*.limit)
)]
pub struct Busy {
    used: u64,
    limit: u64,
}

impl Busy {
    /// The 5.03 that refuses the grab, with Max-Age 1.
    pub(super) fn response(&self) -> Response {
        let mut r = Response::diagnostic(Code::SERVICE_UNAVAILABLE, &self.to_string());
        r.options.set_uint(OptionNumber::MAX_AGE, RETRY_SECS);
        r
    }
}

fn mib(bytes: u64) -> String {
    format!("{:.1}", bytes as f64 / f64::from(1 << 20))
}

/// What one grab of `kind` holds at its peak, in bytes: for color the frame, a gray copy
/// and the encoded image; for depth the frame, the filters' copies and the encoding; for
/// a cloud the depth work, the points (12 bytes each) and their encoding.
pub(super) fn cost(kind: Stream, color: &ColorSettings, depth: &DepthSettings) -> u64 {
    let color_px = u64::from(color.width) * u64::from(color.height);
    let depth_px = u64::from(depth.width) * u64::from(depth.height);
    match kind {
        Stream::Color => color_px * 7,
        Stream::Depth => depth_px * 8,
        Stream::Pointcloud => depth_px * (8 + 24),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grabs_past_the_budget_are_refused_until_one_ends() {
        let budget = Budget::new(100);
        let a = budget.take(60).expect("first");
        let refused = budget.take(60).expect_err("past the budget").response();
        assert_eq!(refused.code, Code::SERVICE_UNAVAILABLE);
        assert_eq!(refused.options.uint(OptionNumber::MAX_AGE), Some(1));
        let b = budget.take(40).expect("within");
        drop(a);
        let c = budget.take(60).expect("after the first ended");
        drop((b, c));
        // One grab always runs, even one larger than the whole budget.
        let big = budget.take(1000).expect("alone");
        assert!(budget.take(1).is_err());
        drop(big);
        assert_eq!(*budget.used.lock().expect("lock"), 0);
    }
}
