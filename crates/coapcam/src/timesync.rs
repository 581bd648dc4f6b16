//! Frames that belong together in time, without IO and without a clock (every call takes
//! the times it needs): the servers' receive and transmit times carried in a CoAP option
//! ([`SERVER_TIME`]), NTP's four-timestamp estimate of a server's clock offset with its
//! clock filter ([`ClockEstimator`]), and the check of a measurement's frames
//! ([`check_frames`]: capture times that, corrected, lie further apart than the allowed
//! skew, and stale cameras). The design and why it is so: docs/design.md, "Frames that
//! belong together".
//!
//! Times are microseconds since the UNIX epoch, signed (an offset or a difference may be
//! negative). A server's times are on its clock, the client's on its own; the offset of a
//! server is its clock minus the client's, so a server's time `t` is `t - offset` on the
//! client's clock.

use std::collections::{HashMap, VecDeque};
use std::net::SocketAddr;

use coap::{OptionNumber, Options};
use serde::{Deserialize, Serialize};

/// The Server-Time option, one of coapcam's numbers in the experimental range (RFC 7252
/// §12.2: 65000-65535). Elective (even) and safe to forward, so a peer that does not know
/// it ignores it. In a request it is empty and asks for the times; in the response it
/// holds the server's receive time of the request and its transmit time of the response,
/// each 8 bytes, big-endian microseconds since the UNIX epoch on the server's clock.
pub const SERVER_TIME: OptionNumber = OptionNumber(65000);

/// Bytes of a Server-Time value in a response.
pub const SERVER_TIME_LEN: usize = 16;

/// The Capture-Time option (experimental range, elective and safe to forward, as
/// [`SERVER_TIME`]): on every notification of a live stream (`/cams/<sn>/<stream>/live`),
/// the frame's capture time, the same `timestamp_us` the frame's CBOR map and compact
/// cloud carry: 8 bytes, big-endian microseconds since the UNIX epoch on the server's
/// clock (correct it by the server's offset, [`ClockEstimator`], to compare it with
/// the client's).
pub const CAPTURE_TIME: OptionNumber = OptionNumber(65012);

/// The Capture-Time option's value of a frame captured at `unix_us`.
pub fn capture_time_value(unix_us: u64) -> [u8; 8] {
    unix_us.to_be_bytes()
}

/// The capture time a response's Capture-Time option carries, µs since the UNIX epoch
/// on the server's clock; `None` without one, or with one that is not 8 bytes or past
/// the range of signed microseconds.
pub fn capture_time(options: &Options) -> Option<i64> {
    let value: [u8; 8] = options.first(CAPTURE_TIME)?.try_into().ok()?;
    i64::try_from(u64::from_be_bytes(value)).ok()
}

/// The window of NTP's clock filter: the last 8 samples of a server are kept.
pub const FILTER_LEN: usize = 8;

/// How fast an estimate is assumed to age: 15 µs per second (NTP's PHI, the frequency
/// tolerance it assumes of a computer's clock), added to a sample's error bound per
/// second since it was taken.
pub const DRIFT_US_PER_S: f64 = 15.0;

/// A server's receive time of a request and transmit time of its response, on its clock.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ServerTimes {
    /// When the request arrived (NTP's T2), µs since the epoch.
    pub received_us: i64,
    /// When the response left (NTP's T3), µs since the epoch.
    pub sent_us: i64,
}

/// Why a Server-Time value was not used.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum TimeError {
    /// Not 16 bytes.
    #[error("a Server-Time option of {0} bytes (16 expected)")]
    Length(usize),
    /// Sent before it was received, or a time past the range of signed microseconds.
    #[error("a Server-Time option whose transmit time precedes its receive time")]
    Order,
    /// The client's times of the exchange: answered before it was asked.
    #[error("an exchange whose answer arrived before its request left")]
    ClientOrder,
}

impl ServerTimes {
    /// The option's value.
    pub fn encode(&self) -> [u8; SERVER_TIME_LEN] {
        let mut out = [0; SERVER_TIME_LEN];
        out[..8].copy_from_slice(&self.received_us.to_be_bytes());
        out[8..].copy_from_slice(&self.sent_us.to_be_bytes());
        out
    }

    /// Reads an option's value.
    pub fn decode(value: &[u8]) -> Result<Self, TimeError> {
        let (Some(received), Some(sent)) = (value.get(..8), value.get(8..)) else {
            return Err(TimeError::Length(value.len()));
        };
        if value.len() != SERVER_TIME_LEN {
            return Err(TimeError::Length(value.len()));
        }
        let word = |b: &[u8]| {
            let mut w = [0; 8];
            w.copy_from_slice(b);
            i64::from_be_bytes(w)
        };
        let times = Self {
            received_us: word(received),
            sent_us: word(sent),
        };
        if times.sent_us < times.received_us || times.received_us < 0 {
            return Err(TimeError::Order);
        }
        Ok(times)
    }

    /// The times in a response's options; `None` when it has no Server-Time option (a
    /// server that does not set it).
    pub fn of(options: &Options) -> Option<Result<Self, TimeError>> {
        options.first(SERVER_TIME).map(Self::decode)
    }
}

/// How far a server's clock may be from the client's before the client stops believing
/// its times (10 minutes): a clock that far off was never synchronised, or the times were
/// forged on the way; its offset is not estimated and its frames' age not judged (said
/// as a warning). Hosts kept by NTP or PTP are within milliseconds.
pub const MAX_BELIEVED_APART_US: i64 = 10 * 60 * 1_000_000;

/// One exchange's four times: NTP's T1 (the request left, client clock), T2 and T3 (the
/// server's), T4 (the answer arrived, client clock).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Sample {
    /// T1, client clock.
    pub sent_us: i64,
    /// T2 and T3, server clock.
    pub server: ServerTimes,
    /// T4, client clock.
    pub received_us: i64,
}

impl Sample {
    /// A sample of an exchange, refused when its client times are out of order.
    pub fn new(sent_us: i64, server: ServerTimes, received_us: i64) -> Result<Self, TimeError> {
        if received_us < sent_us {
            return Err(TimeError::ClientOrder);
        }
        Ok(Self {
            sent_us,
            server,
            received_us,
        })
    }

    /// θ = ((T2 - T1) + (T3 - T4)) / 2: the server's clock minus the client's, exact when
    /// the request and the answer took equally long on the way.
    pub fn offset_us(&self) -> i64 {
        let out = self.server.received_us - self.sent_us;
        let back = self.server.sent_us - self.received_us;
        (out + back).div_euclid(2)
    }

    /// δ = (T4 - T1) - (T3 - T2): the time on the way there and back, without the
    /// server's own time. Never negative (two clocks' rounding can make it so; it is then
    /// 0).
    pub fn delay_us(&self) -> i64 {
        let total = self.received_us - self.sent_us;
        let server = self.server.sent_us - self.server.received_us;
        (total - server).max(0)
    }

    /// The bound on this sample's offset error at client time `now_us`: whatever the
    /// paths' asymmetry, the true offset lies within half the delay of the estimate
    /// (both clocks still), plus what the clocks may have drifted apart since.
    pub fn error_bound_us(&self, now_us: i64) -> i64 {
        let age_s = (now_us - self.received_us).max(0) as f64 / 1e6;
        self.delay_us() / 2 + (age_s * DRIFT_US_PER_S).round() as i64
    }
}

/// A server's clock offset as estimated.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Offset {
    /// The server's clock minus the client's, µs.
    pub offset_us: i64,
    /// The error bound of the estimate, µs (half the chosen sample's delay, plus drift).
    pub error_us: i64,
}

/// NTP's clock filter for one server: the last [`FILTER_LEN`] samples, of which the one
/// with the smallest error bound (the smallest delay, aged) gives the estimate. A sample
/// whose exchange was slowed on one way only (a queue, a retransmission, a body sent in
/// many blocks) has a large delay and loses to a quick one: the filter discards
/// outliers without a threshold.
#[derive(Debug, Clone, Default)]
pub struct ClockEstimator {
    samples: VecDeque<Sample>,
}

impl ClockEstimator {
    /// No samples yet.
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds a sample, dropping the oldest beyond [`FILTER_LEN`].
    pub fn add(&mut self, sample: Sample) {
        if self.samples.len() == FILTER_LEN {
            self.samples.pop_front();
        }
        self.samples.push_back(sample);
    }

    /// Samples kept.
    pub fn len(&self) -> usize {
        self.samples.len()
    }

    /// Whether no sample was added.
    pub fn is_empty(&self) -> bool {
        self.samples.is_empty()
    }

    /// The estimate at client time `now_us`: the offset of the sample with the smallest
    /// error bound then; `None` without samples.
    pub fn estimate(&self, now_us: i64) -> Option<Offset> {
        let best = self
            .samples
            .iter()
            .min_by_key(|s| (s.error_bound_us(now_us), -s.received_us))?;
        Some(Offset {
            offset_us: best.offset_us(),
            error_us: best.error_bound_us(now_us),
        })
    }
}

/// The frame a camera contributed to a measurement, with its time on its server's clock
/// and, where the server's clock offset is known, on the client's.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FrameTime {
    /// The camera's serial.
    pub camera: String,
    /// Its server (the client fills it; the server's own measurement leaves it out).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub server: Option<SocketAddr>,
    /// The depth frame's number (0 when the representation does not carry it).
    pub frame_number: u64,
    /// When the frame was captured, µs since the epoch on its server's clock.
    pub captured_unix_us: i64,
    /// When the server received the grab's request, on its clock (the age of the frame
    /// is measured from it), when known.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub requested_unix_us: Option<i64>,
    /// The server's clock offset, when known (the client's measurements).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub clock: Option<Offset>,
    /// The frame's rate of the camera, frames per second, when known.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fps: Option<u32>,
}

impl FrameTime {
    /// The capture time on the client's clock (on the server's when its offset is
    /// unknown).
    pub fn corrected_us(&self) -> i64 {
        self.captured_unix_us - self.clock.map_or(0, |c| c.offset_us)
    }

    fn who(&self) -> String {
        match self.server {
            Some(s) => format!("camera {} (server {s})", self.camera),
            None => format!("camera {}", self.camera),
        }
    }
}

/// What [`check_frames`] allows.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Limits {
    /// The largest difference of two corrected capture times, µs; `None`: one frame
    /// period at the slowest camera's rate (30 fps when no rate is known).
    pub max_skew_us: Option<i64>,
    /// Whether the capture times are compared with each other (the client's merge of
    /// several servers); `false` checks staleness only (one host's own cameras).
    pub skew: bool,
}

/// The frame period of `fps`, µs.
pub fn frame_period_us(fps: u32) -> i64 {
    (1_000_000 / i64::from(fps.max(1))).max(1)
}

/// The rate assumed where no camera's rate is known: the D415's default depth rate.
pub const DEFAULT_FPS: u32 = 30;

impl Limits {
    /// The allowed skew for `frames`: the given one, or one frame period at the slowest
    /// rate among them.
    pub fn skew_us(&self, frames: &[FrameTime]) -> i64 {
        self.max_skew_us.unwrap_or_else(|| {
            let slowest = frames.iter().filter_map(|f| f.fps).min();
            frame_period_us(slowest.unwrap_or(DEFAULT_FPS))
        })
    }
}

/// Why frames do not belong together.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Problem {
    /// A camera's frame was captured further from the others than the allowed skew.
    Skew {
        /// Who (camera and server).
        camera: String,
        /// The camera whose time it was compared with.
        reference: String,
        /// Corrected capture time of `camera` minus that of `reference`, µs.
        apart_us: i64,
        /// The allowed skew, µs.
        max_us: i64,
    },
    /// A camera serves a frame captured long before the grab asked for a new one.
    Old {
        /// Who.
        camera: String,
        /// How long before the server received the grab's request it was captured, µs.
        age_us: i64,
        /// The age past which a frame is stale, µs.
        max_us: i64,
    },
    /// A camera served the very frame (number and capture time) it served the grab
    /// before.
    Repeated {
        /// Who.
        camera: String,
        /// The frame's number.
        frame_number: u64,
    },
}

impl Problem {
    /// The camera it names, with its server.
    pub fn camera(&self) -> &str {
        match self {
            Self::Skew { camera, .. }
            | Self::Old { camera, .. }
            | Self::Repeated { camera, .. } => camera,
        }
    }
}

impl std::fmt::Display for Problem {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let ms = |us: i64| us as f64 / 1e3;
        match self {
            Self::Skew {
                camera,
                reference,
                apart_us,
                max_us,
            } => write!(
                f,
                "{camera} captured its frame {:.1} ms {} {reference}, more than the {:.1} ms allowed (--max-skew-ms); its clock or its camera is off",
                ms(apart_us.abs()),
                if *apart_us > 0 { "after" } else { "before" },
                ms(*max_us)
            ),
            Self::Old {
                camera,
                age_us,
                max_us,
            } => write!(
                f,
                "{camera} is stale: its frame was captured {:.1} ms before the grab asked for a new one (more than {:.1} ms)",
                ms(*age_us),
                ms(*max_us)
            ),
            Self::Repeated {
                camera,
                frame_number,
            } => write!(
                f,
                "{camera} is stale: it served frame {frame_number} again, captured at the same time as the grab before"
            ),
        }
    }
}

/// The last frame of each camera, by server and serial: a camera that serves the same
/// frame twice has stopped.
#[derive(Debug, Clone, Default)]
pub struct FrameHistory {
    last: HashMap<(Option<SocketAddr>, String), (u64, i64)>,
}

impl FrameHistory {
    /// Nothing seen yet.
    pub fn new() -> Self {
        Self::default()
    }
}

/// Checks the frames of one measurement (and remembers them in `history`): a frame older
/// than the grab that asked for it by more than the allowed skew plus one frame period
/// (at its camera's rate) is stale, as is a frame served again; with `limits.skew`, a
/// frame (of those not stale) whose corrected capture time lies further than the allowed
/// skew from the median frame's names its camera. Every problem found, stale cameras
/// first.
pub fn check_frames(
    frames: &[FrameTime],
    limits: &Limits,
    history: &mut FrameHistory,
) -> Vec<Problem> {
    let max_skew = limits.skew_us(frames);
    let mut problems = Vec::new();
    let mut live = Vec::with_capacity(frames.len());
    for f in frames {
        let period = frame_period_us(f.fps.unwrap_or(DEFAULT_FPS));
        let max_age = max_skew + period;
        if let Some(asked) = f.requested_unix_us {
            let age = asked - f.captured_unix_us;
            if age > max_age {
                problems.push(Problem::Old {
                    camera: f.who(),
                    age_us: age,
                    max_us: max_age,
                });
                continue;
            }
        }
        let key = (f.server, f.camera.clone());
        let now = (f.frame_number, f.captured_unix_us);
        if history.last.insert(key, now) == Some(now) {
            problems.push(Problem::Repeated {
                camera: f.who(),
                frame_number: f.frame_number,
            });
            continue;
        }
        live.push(f);
    }
    // A stale camera is named as such; the others' times are compared among themselves.
    if !limits.skew || live.len() < 2 {
        return problems;
    }
    let mut order = live;
    order.sort_by_key(|f| f.corrected_us());
    let median = order[(order.len() - 1) / 2];
    for f in &order {
        let apart = f.corrected_us() - median.corrected_us();
        if apart.abs() > max_skew {
            problems.push(Problem::Skew {
                camera: f.who(),
                reference: median.who(),
                apart_us: apart,
                max_us: max_skew,
            });
        }
    }
    problems
}

#[cfg(test)]
mod tests {
    use super::*;

    const T0: i64 = 1_790_000_000_000_000;

    fn times(received_us: i64, sent_us: i64) -> ServerTimes {
        ServerTimes {
            received_us,
            sent_us,
        }
    }

    /// An exchange with a server whose clock is `offset` ahead, `out` and `back` µs on
    /// the way, `busy` µs in the server, starting at client time `t1`.
    fn exchange(t1: i64, offset: i64, out: i64, busy: i64, back: i64) -> Sample {
        let t2 = t1 + out + offset;
        let t3 = t2 + busy;
        let t4 = t1 + out + busy + back;
        Sample::new(t1, times(t2, t3), t4).expect("ordered")
    }

    #[test]
    fn the_option_value_round_trips_and_refuses_what_it_cannot_be() {
        let t = times(T0, T0 + 250);
        let value = t.encode();
        assert_eq!(value.len(), 16);
        assert_eq!(ServerTimes::decode(&value), Ok(t));
        assert_eq!(
            ServerTimes::decode(&value[..15]),
            Err(TimeError::Length(15))
        );
        assert_eq!(ServerTimes::decode(&[0; 17]), Err(TimeError::Length(17)));
        assert_eq!(
            ServerTimes::decode(&times(T0, T0 - 1).encode()),
            Err(TimeError::Order)
        );
        let mut options = Options::new();
        assert!(ServerTimes::of(&options).is_none());
        options.set(SERVER_TIME, &value[..]);
        assert_eq!(ServerTimes::of(&options), Some(Ok(t)));
        assert!(SERVER_TIME.0 >= 65000 && !SERVER_TIME.is_critical() && !SERVER_TIME.is_unsafe());
    }

    #[test]
    fn a_symmetric_exchange_gives_the_exact_offset_and_its_delay() {
        // 400 ms ahead, 300 µs each way, 80 ms grabbing.
        let s = exchange(T0, 400_000, 300, 80_000, 300);
        assert_eq!(s.offset_us(), 400_000);
        assert_eq!(s.delay_us(), 600);
        assert_eq!(s.error_bound_us(s.received_us), 300);
        // 10 s later the bound has grown by 150 µs of drift.
        assert_eq!(s.error_bound_us(s.received_us + 10_000_000), 450);
        // Behind the client.
        assert_eq!(exchange(T0, -2_500, 100, 10, 100).offset_us(), -2_500);
    }

    #[test]
    fn an_asymmetric_exchange_errs_by_half_the_difference_within_its_bound() {
        // 100 µs there, 2.1 ms back (the answer queued): the estimate is 1 ms early.
        let s = exchange(T0, 400_000, 100, 5_000, 2_100);
        assert_eq!(s.offset_us(), 400_000 - 1_000);
        assert_eq!(s.delay_us(), 2_200);
        assert!((s.offset_us() - 400_000).abs() <= s.error_bound_us(s.received_us));
    }

    #[test]
    fn client_times_out_of_order_are_refused() {
        assert_eq!(
            Sample::new(T0, times(T0, T0), T0 - 1),
            Err(TimeError::ClientOrder)
        );
    }

    #[test]
    fn the_filter_takes_the_sample_of_smallest_delay_and_so_drops_outliers() {
        let mut e = ClockEstimator::new();
        assert_eq!(e.estimate(T0), None);
        // A large body's grab: 40 ms back in blocks, badly asymmetric.
        e.add(exchange(T0, 400_000, 200, 90_000, 40_000));
        let first = e.estimate(T0 + 200_000).expect("estimate");
        assert_eq!(first.offset_us, 400_000 - 19_900);
        assert_eq!(first.error_us, 20_100 + 1);
        // A small exchange: 250 µs each way.
        e.add(exchange(T0 + 1_000_000, 400_000, 250, 50, 250));
        // A spike: a retransmission after 2 s.
        e.add(exchange(T0 + 2_000_000, 400_000, 2_000_000, 50, 250));
        let best = e.estimate(T0 + 3_000_000).expect("estimate");
        assert_eq!(best.offset_us, 400_000);
        assert_eq!(best.error_us, 250 + 30);
        assert_eq!(e.len(), 3);
    }

    #[test]
    fn the_filter_keeps_the_last_eight_and_prefers_young_samples_of_equal_delay() {
        let mut e = ClockEstimator::new();
        // A very quick sample, then eight slower ones: it leaves the window.
        e.add(exchange(T0, 1_000, 10, 0, 10));
        for i in 1..=8 {
            e.add(exchange(T0 + i * 1_000_000, 2_000 + i, 500, 0, 500));
        }
        assert_eq!(e.len(), FILTER_LEN);
        let now = T0 + 9_000_000;
        let best = e.estimate(now).expect("estimate");
        // Equal delays: the youngest has aged least.
        assert_eq!(best.offset_us, 2_008);
        assert!(!e.is_empty());
    }

    fn frame(camera: &str, server: u16, captured: i64, offset: Option<i64>) -> FrameTime {
        FrameTime {
            camera: camera.into(),
            server: Some(SocketAddr::from(([127, 0, 0, 1], server))),
            frame_number: 7,
            captured_unix_us: captured,
            requested_unix_us: Some(captured - 2_000),
            clock: offset.map(|offset_us| Offset {
                offset_us,
                error_us: 300,
            }),
            fps: Some(30),
        }
    }

    #[test]
    fn frames_of_a_clock_400_ms_ahead_belong_together_once_corrected() {
        let frames = [
            frame("A", 1, T0 + 1_000, Some(0)),
            frame("B", 2, T0 + 401_500, Some(400_000)),
        ];
        let limits = Limits {
            max_skew_us: None,
            skew: true,
        };
        assert_eq!(limits.skew_us(&frames), 33_333);
        let found = check_frames(&frames, &limits, &mut FrameHistory::new());
        assert!(found.is_empty(), "{found:?}");
        // Uncorrected they are 400 ms apart: the later one is named.
        let mut wrong = frames;
        wrong[1].clock = Some(Offset {
            offset_us: 0,
            error_us: 300,
        });
        let found = check_frames(&wrong, &limits, &mut FrameHistory::new());
        assert_eq!(found.len(), 1, "{found:?}");
        let Problem::Skew {
            camera, apart_us, ..
        } = &found[0]
        else {
            panic!("{found:?}");
        };
        assert_eq!(camera, "camera B (server 127.0.0.1:2)");
        assert_eq!(*apart_us, 400_500);
        assert!(found[0].to_string().contains("400.5 ms after camera A"));
    }

    #[test]
    fn the_skew_allowed_is_one_period_of_the_slowest_camera_or_as_given() {
        let mut frames = [
            frame("A", 1, T0, Some(0)),
            frame("B", 2, T0 + 100_000, Some(0)),
        ];
        frames[1].fps = Some(6);
        let mut limits = Limits {
            max_skew_us: None,
            skew: true,
        };
        assert_eq!(limits.skew_us(&frames), 166_666);
        assert!(check_frames(&frames, &limits, &mut FrameHistory::new()).is_empty());
        limits.max_skew_us = Some(50_000);
        assert_eq!(
            check_frames(&frames, &limits, &mut FrameHistory::new()).len(),
            1
        );
        // Without skew checks (one host) only staleness counts.
        limits.skew = false;
        assert!(check_frames(&frames, &limits, &mut FrameHistory::new()).is_empty());
    }

    #[test]
    fn a_frame_older_than_its_grab_is_stale_and_named() {
        let mut old = frame("C", 3, T0, Some(0));
        old.requested_unix_us = Some(T0 + 5_000_000);
        let fresh = frame("A", 1, T0 + 5_000_100, Some(0));
        let limits = Limits {
            max_skew_us: None,
            skew: false,
        };
        let found = check_frames(&[fresh, old], &limits, &mut FrameHistory::new());
        assert_eq!(
            found,
            vec![Problem::Old {
                camera: "camera C (server 127.0.0.1:3)".into(),
                age_us: 5_000_000,
                max_us: 66_666,
            }]
        );
        assert!(found[0].to_string().contains("stale"));
    }

    #[test]
    fn a_frame_served_twice_is_stale_the_second_time() {
        let limits = Limits {
            max_skew_us: None,
            skew: false,
        };
        let mut history = FrameHistory::new();
        let mut f = frame("A", 1, T0, None);
        f.requested_unix_us = None;
        assert!(check_frames(std::slice::from_ref(&f), &limits, &mut history).is_empty());
        let found = check_frames(std::slice::from_ref(&f), &limits, &mut history);
        assert_eq!(
            found,
            vec![Problem::Repeated {
                camera: "camera A (server 127.0.0.1:1)".into(),
                frame_number: 7
            }]
        );
        // A new frame is fine again.
        f.frame_number = 8;
        f.captured_unix_us += 33_000;
        assert!(check_frames(&[f], &limits, &mut history).is_empty());
    }
}
