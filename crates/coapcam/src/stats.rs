//! Statistics of repeated measurements, one definition of each for every command that
//! reports them (`monitor`, the benchmarks):
//! - order statistics of a sample: [`median`] (of an even count, the mean of the middle
//!   two), [`percentile`] (nearest rank), [`Spread`] (median, minimum and maximum) and
//!   [`AbsSummary`] (mean, 95th percentile and maximum of absolute values);
//! - running moments: [`Welford`] (mean and standard deviation in one pass, exact for
//!   values far larger than their spread), and [`TransferStats`], the columns of the
//!   thesis's Tables 4.1-4.11 over any number of transfer times;
//! - [`LiveStats`]: a live stream's frames per second and capture-to-client latency.
//!
//! Every function of a sample leaves out values that are not finite (a failed run's NaN).

use std::collections::VecDeque;
use std::time::Duration;

/// The finite values of `values`, in ascending order.
pub fn sorted(values: impl IntoIterator<Item = f64>) -> Vec<f64> {
    let mut v: Vec<f64> = values.into_iter().filter(|x| x.is_finite()).collect();
    v.sort_by(f64::total_cmp);
    v
}

/// The median of an ascending slice (of an even count, the mean of the middle two);
/// `None` if it is empty.
fn median_of_sorted(sorted: &[f64]) -> Option<f64> {
    let n = sorted.len();
    match n {
        0 => None,
        _ if n % 2 == 1 => Some(sorted[n / 2]),
        _ => Some((sorted[n / 2 - 1] + sorted[n / 2]) / 2.0),
    }
}

/// The nearest-rank `p` percentile (`p` in 0..=1) of an ascending slice: the smallest
/// value with at least `p` of the values at or below it; `None` if it is empty.
fn percentile_of_sorted(sorted: &[f64], p: f64) -> Option<f64> {
    let n = sorted.len();
    if n == 0 {
        return None;
    }
    let rank = ((p * n as f64).ceil() as usize).clamp(1, n);
    Some(sorted[rank - 1])
}

/// The median of the finite `values` (of an even count, the mean of the middle two);
/// `None` if there is none.
pub fn median(values: &[f64]) -> Option<f64> {
    median_of_sorted(&sorted(values.iter().copied()))
}

/// The nearest-rank `p` percentile (`p` in 0..=1) of the finite `values`; `None` if there
/// is none.
pub fn percentile(values: &[f64], p: f64) -> Option<f64> {
    percentile_of_sorted(&sorted(values.iter().copied()), p)
}

/// Median, minimum and maximum of a sample.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Spread {
    /// Of an even count, the mean of the middle two.
    pub median: f64,
    /// The smallest value.
    pub min: f64,
    /// The largest value.
    pub max: f64,
}

impl Spread {
    /// Of the finite `values`; `None` if there is none.
    pub fn of(values: &[f64]) -> Option<Self> {
        let v = sorted(values.iter().copied());
        Some(Self {
            median: median_of_sorted(&v)?,
            min: v[0],
            max: v[v.len() - 1],
        })
    }
}

/// Mean, 95th percentile (nearest rank) and maximum of the absolute values of a sample:
/// how large errors are, whichever their sign.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AbsSummary {
    /// The mean absolute value.
    pub mean: f64,
    /// The nearest-rank 95th percentile of the absolute values.
    pub p95: f64,
    /// The largest absolute value.
    pub max: f64,
}

impl AbsSummary {
    /// Of the finite `values`; every field NaN if there is none.
    pub fn of(values: &[f64]) -> Self {
        let abs = sorted(values.iter().map(|v| v.abs()));
        let Some(p95) = percentile_of_sorted(&abs, 0.95) else {
            return Self {
                mean: f64::NAN,
                p95: f64::NAN,
                max: f64::NAN,
            };
        };
        Self {
            mean: abs.iter().sum::<f64>() / abs.len() as f64,
            p95,
            max: abs[abs.len() - 1],
        }
    }
}

/// Welford's running mean and sum of squared deviations: one pass, no sum of squares
/// that would lose a small spread of large values.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Welford {
    count: u64,
    mean: f64,
    m2: f64,
}

impl Welford {
    /// Adds one value.
    pub fn push(&mut self, x: f64) {
        self.count += 1;
        let delta = x - self.mean;
        self.mean += delta / self.count as f64;
        self.m2 += delta * (x - self.mean);
    }

    /// How many values were added.
    pub fn count(&self) -> u64 {
        self.count
    }

    /// The mean; `None` before the first value.
    pub fn mean(&self) -> Option<f64> {
        (self.count > 0).then_some(self.mean)
    }

    /// The population standard deviation (divided by n); `None` before the first value.
    pub fn population_sd(&self) -> Option<f64> {
        (self.count > 0).then(|| (self.m2 / self.count as f64).max(0.0).sqrt())
    }
}

/// Transfer times kept for the median: the last 2^20 (8 MiB). Minimum, maximum, mean and
/// standard deviation cover every result however long the statistics run.
const MEDIAN_WINDOW: usize = 1 << 20;

/// Running statistics of transfer times, the columns of the thesis's Tables 4.1-4.11.
///
/// The standard deviation is the population one (divide by n). The thesis does not say
/// which it used, but its tables admit only this one: in Table 4.1 (32 transfers, one of
/// 597.5 ms, mean 137.9 ms) that single outlier contributes (597.5 - 123.1)^2 + 31 x
/// (137.9 - 123.1)^2 = 2.18e5 ms^2 to the sum of squares, more than the 31 x 82.8^2 =
/// 2.12e5 ms^2 a sample deviation of 82.8 ms would allow, while 32 x 82.8^2 = 2.19e5 ms^2
/// leaves the other 31 transfers a spread of 6.6 ms, as the text describes (0.11-0.14 s).
/// Table 4.2 gives the same verdict.
#[derive(Debug, Clone)]
pub struct TransferStats {
    failed: u64,
    min_ns: u64,
    max_ns: u64,
    /// Mean and spread, in nanoseconds.
    moments: Welford,
    recent_ns: VecDeque<u64>,
    window: usize,
}

/// What the statistics say about the results so far.
#[derive(Debug, Clone, PartialEq)]
pub struct TransferSummary {
    /// Successful results.
    pub count: u64,
    /// Failed results.
    pub failed: u64,
    /// The transfer times of the successful results; `None` before the first.
    pub times: Option<Times>,
}

impl TransferSummary {
    /// The statistics as the last line of `--json`: times in nanoseconds as the thesis gives
    /// them.
    pub fn to_json(&self) -> serde_json::Value {
        let mut stats = serde_json::json!({
            "count": self.count,
            "failed": self.failed,
            "sd": "population",
        });
        if let Some(t) = &self.times {
            stats["min_ns"] = t.min_ns.into();
            stats["median_ns"] = (t.median_ns.round() as u64).into();
            stats["max_ns"] = t.max_ns.into();
            stats["mean_ns"] = (t.mean_ns.round() as u64).into();
            stats["sd_ns"] = (t.sd_ns.round() as u64).into();
            stats["cv"] = ((t.cv * 1e4).round() / 1e4).into();
        }
        serde_json::json!({ "statistics": stats })
    }

    /// The statistics as a table, times in milliseconds.
    pub fn text(&self, what: &str) -> String {
        let mut out = format!(
            "{what} of {} result(s), {} failed (population standard deviation):\n",
            self.count, self.failed
        );
        out += &format!(
            "{:>7} {:>11} {:>11} {:>11} {:>11} {:>11} {:>6}\n",
            "count", "min ms", "median ms", "max ms", "mean ms", "sd ms", "cv"
        );
        match &self.times {
            Some(t) => {
                let ms = |ns: f64| ns / 1e6;
                out += &format!(
                    "{:>7} {:>11.3} {:>11.3} {:>11.3} {:>11.3} {:>11.3} {:>6.2}\n",
                    self.count,
                    ms(t.min_ns as f64),
                    ms(t.median_ns),
                    ms(t.max_ns as f64),
                    ms(t.mean_ns),
                    ms(t.sd_ns),
                    t.cv
                );
            }
            None => out += &format!("{:>7} {:>11}\n", 0, "-"),
        }
        out
    }
}

/// Transfer-time statistics, nanoseconds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Times {
    /// The shortest.
    pub min_ns: u64,
    /// Median of the last 2^20 results (of all while there are fewer).
    pub median_ns: f64,
    /// The longest.
    pub max_ns: u64,
    /// The mean.
    pub mean_ns: f64,
    /// Population standard deviation.
    pub sd_ns: f64,
    /// Standard deviation over mean.
    pub cv: f64,
}

impl Default for TransferStats {
    fn default() -> Self {
        Self::new()
    }
}

impl TransferStats {
    /// No results yet.
    pub fn new() -> Self {
        Self::with_median_window(MEDIAN_WINDOW)
    }

    /// No results yet; the median covers the last `window` transfer times.
    fn with_median_window(window: usize) -> Self {
        Self {
            failed: 0,
            min_ns: 0,
            max_ns: 0,
            moments: Welford::default(),
            recent_ns: VecDeque::new(),
            window: window.max(1),
        }
    }

    /// A successful result's transfer time.
    pub fn record(&mut self, time: Duration) {
        let ns = u64::try_from(time.as_nanos()).unwrap_or(u64::MAX);
        if self.moments.count() == 0 {
            (self.min_ns, self.max_ns) = (ns, ns);
        } else {
            self.min_ns = self.min_ns.min(ns);
            self.max_ns = self.max_ns.max(ns);
        }
        self.moments.push(ns as f64);
        if self.recent_ns.len() == self.window {
            self.recent_ns.pop_front();
        }
        self.recent_ns.push_back(ns);
    }

    /// A failed result.
    pub fn record_failure(&mut self) {
        self.failed += 1;
    }

    /// The mean transfer time so far.
    pub fn mean(&self) -> Option<Duration> {
        self.moments
            .mean()
            .map(|ns| Duration::from_nanos(ns.round() as u64))
    }

    /// Every column at once.
    pub fn summary(&self) -> TransferSummary {
        let times = (|| {
            let mean_ns = self.moments.mean()?;
            let sd_ns = self.moments.population_sd()?;
            let recent: Vec<f64> = self.recent_ns.iter().map(|&ns| ns as f64).collect();
            Some(Times {
                min_ns: self.min_ns,
                median_ns: median(&recent)?,
                max_ns: self.max_ns,
                mean_ns,
                sd_ns,
                cv: if mean_ns > 0.0 { sd_ns / mean_ns } else { 0.0 },
            })
        })();
        TransferSummary {
            count: self.moments.count(),
            failed: self.failed,
            times,
        }
    }
}

/// A live stream's frames as they arrived (`monitor --live`): the frame rate between the
/// first frame and the last, and the capture-to-client latency of the last 2^20 frames.
#[derive(Debug, Clone, Default)]
pub struct LiveStats {
    /// Frames skipped for a newer one that arrived meanwhile (as the stream counts them).
    pub skipped: u64,
    frames: u64,
    first: Option<std::time::Instant>,
    last: Option<std::time::Instant>,
    latencies_ms: VecDeque<f64>,
}

/// What [`LiveStats`] says.
#[derive(Debug, Clone, PartialEq)]
pub struct LiveSummary {
    /// Frames received.
    pub frames: u64,
    /// Frames a second from the first to the last (`None` before the second frame).
    pub fps: Option<f64>,
    /// Median, 95th percentile (nearest rank) and maximum latency, ms (`None` without a
    /// capture time).
    pub latency_ms: Option<[f64; 3]>,
    /// Frames skipped for a newer one that arrived meanwhile.
    pub skipped: u64,
}

impl LiveStats {
    /// A frame arrived `at`, `latency` after it was captured (if known: frames without a
    /// capture time count for the rate only).
    pub fn record(&mut self, at: std::time::Instant, latency: Option<Duration>) {
        self.frames += 1;
        self.first.get_or_insert(at);
        self.last = Some(at);
        if let Some(latency) = latency {
            if self.latencies_ms.len() == MEDIAN_WINDOW {
                self.latencies_ms.pop_front();
            }
            self.latencies_ms.push_back(latency.as_secs_f64() * 1e3);
        }
    }

    /// The rate, the latencies and the frames skipped so far.
    pub fn summary(&self) -> LiveSummary {
        let fps = match (self.first, self.last) {
            (Some(first), Some(last)) if self.frames > 1 && last > first => {
                Some((self.frames - 1) as f64 / (last - first).as_secs_f64())
            }
            _ => None,
        };
        let all = sorted(self.latencies_ms.iter().copied());
        let latency_ms = (|| {
            Some([
                percentile_of_sorted(&all, 0.5)?,
                percentile_of_sorted(&all, 0.95)?,
                *all.last()?,
            ])
        })();
        LiveSummary {
            frames: self.frames,
            fps,
            latency_ms,
            skipped: self.skipped,
        }
    }
}

impl LiveSummary {
    /// As a JSON object: `frames`, `fps`, `latency_p50_ms`, `latency_p95_ms`,
    /// `latency_max_ms`, `skipped`.
    pub fn to_json(&self) -> serde_json::Value {
        let round = |x: f64| (x * 1e3).round() / 1e3;
        let mut out = serde_json::json!({ "frames": self.frames, "skipped": self.skipped });
        if let Some(fps) = self.fps {
            out["fps"] = round(fps).into();
        }
        if let Some([p50, p95, max]) = self.latency_ms {
            out["latency_p50_ms"] = round(p50).into();
            out["latency_p95_ms"] = round(p95).into();
            out["latency_max_ms"] = round(max).into();
        }
        out
    }

    /// One line of text.
    pub fn text(&self) -> String {
        let fps = self
            .fps
            .map_or_else(|| "-".to_owned(), |f| format!("{f:.1}"));
        let latency = self.latency_ms.map_or_else(
            || "no capture times".to_owned(),
            |[p50, p95, max]| format!("p50 {p50:.1} ms, p95 {p95:.1} ms, max {max:.1} ms"),
        );
        format!(
            "live: {} frame(s), {fps} frames/s, {} skipped for newer ones; capture-to-client latency {latency}\n",
            self.frames, self.skipped
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn stats_of_ms(values: &[u64]) -> TransferStats {
        let mut s = TransferStats::new();
        for v in values {
            s.record(Duration::from_millis(*v));
        }
        s
    }

    #[test]
    fn a_summary_names_every_column_in_json_and_text() {
        let s = stats_of_ms(&[100, 200, 300]).summary();
        let json = s.to_json();
        let st = &json["statistics"];
        for key in [
            "count",
            "failed",
            "min_ns",
            "median_ns",
            "max_ns",
            "mean_ns",
            "sd_ns",
            "cv",
        ] {
            assert!(st.get(key).is_some(), "{key} missing in {json}");
        }
        assert_eq!(st["median_ns"], 200_000_000);
        assert_eq!(st["sd"], "population");
        let text = s.text("transfer times");
        assert!(text.contains("median ms"), "{text}");
        assert!(text.contains("200.000"), "{text}");
        assert!(text.contains("0.41"), "{text}");
        let mut failures = TransferStats::new();
        failures.record_failure();
        failures.record_failure();
        let json = failures.summary().to_json();
        assert_eq!(json["statistics"]["failed"], 2);
        assert!(json["statistics"].get("mean_ns").is_none());
    }

    #[test]
    fn the_median_of_an_even_count_is_the_mean_of_the_middle_two() {
        assert_eq!(median(&[3.0, 1.0, 2.0]), Some(2.0));
        assert_eq!(median(&[4.0, 1.0, 2.0, 3.0]), Some(2.5));
        assert_eq!(median(&[f64::NAN, 5.0]), Some(5.0));
        assert_eq!(median(&[]), None);
    }

    #[test]
    fn spread_is_median_min_max_of_finite_values() {
        let s = |median, min, max| Some(Spread { median, min, max });
        assert_eq!(Spread::of(&[3.0, 1.0, 2.0]), s(2.0, 1.0, 3.0));
        assert_eq!(Spread::of(&[4.0, 1.0, 2.0, 3.0]), s(2.5, 1.0, 4.0));
        assert_eq!(Spread::of(&[f64::NAN, 5.0]), s(5.0, 5.0, 5.0));
        assert_eq!(Spread::of(&[]), None);
    }

    #[test]
    fn percentiles_are_by_nearest_rank() {
        let v: Vec<f64> = (1..=20).map(f64::from).collect();
        assert_eq!(percentile(&v, 0.95), Some(19.0));
        assert_eq!(percentile(&v, 0.5), Some(10.0));
        assert_eq!(percentile(&v, 0.99), Some(20.0));
        assert_eq!(percentile(&v, 0.0), Some(1.0));
        assert_eq!(percentile(&[7.0], 0.99), Some(7.0));
        assert_eq!(percentile(&[], 0.5), None);
    }

    #[test]
    fn abs_summary_is_mean_p95_and_max_of_absolute_values() {
        let v: Vec<f64> = (1..=20)
            .map(|i| if i % 2 == 0 { i as f64 } else { -(i as f64) })
            .collect();
        let s = AbsSummary::of(&v);
        assert_eq!([s.mean, s.p95, s.max], [10.5, 19.0, 20.0]);
        assert!(AbsSummary::of(&[]).mean.is_nan());
    }

    fn ms(values: &[u64]) -> TransferStats {
        let mut s = TransferStats::new();
        for v in values {
            s.record(Duration::from_millis(*v));
        }
        s
    }

    #[test]
    fn known_samples_give_known_columns_with_the_population_deviation() {
        // Population variance 4 (sample variance 32/7, sd 2.14).
        let s = ms(&[2, 4, 4, 4, 5, 5, 7, 9]).summary();
        let t = s.times.unwrap();
        assert_eq!((s.count, s.failed), (8, 0));
        assert_eq!((t.min_ns, t.max_ns), (2_000_000, 9_000_000));
        assert_eq!(t.median_ns, 4_500_000.0);
        assert!((t.mean_ns - 5e6).abs() < 1e-3, "{}", t.mean_ns);
        assert!((t.sd_ns - 2e6).abs() < 1e-3, "{}", t.sd_ns);
        assert!((t.cv - 0.4).abs() < 1e-12, "{}", t.cv);
    }

    #[test]
    fn an_odd_count_has_the_middle_value_as_median() {
        let t = ms(&[30, 10, 20]).summary().times.unwrap();
        assert_eq!(t.median_ns, 20e6);
        assert_eq!((t.min_ns, t.max_ns), (10_000_000, 30_000_000));
    }

    #[test]
    fn one_result_has_no_spread_and_none_has_no_times() {
        let t = ms(&[7]).summary().times.unwrap();
        assert_eq!((t.sd_ns, t.cv, t.median_ns), (0.0, 0.0, 7e6));
        let mut s = TransferStats::new();
        s.record_failure();
        s.record_failure();
        assert_eq!(
            s.summary(),
            TransferSummary {
                count: 0,
                failed: 2,
                times: None
            }
        );
        assert_eq!(s.mean(), None);
    }

    #[test]
    fn failures_do_not_enter_the_times() {
        let mut s = ms(&[10, 20]);
        s.record_failure();
        let sum = s.summary();
        assert_eq!((sum.count, sum.failed), (2, 1));
        assert_eq!(sum.times.unwrap().mean_ns, 15e6);
    }

    #[test]
    fn long_runs_keep_a_bounded_window_for_the_median_and_exact_moments() {
        let mut s = TransferStats::with_median_window(3);
        for v in 1..=5 {
            s.record(Duration::from_millis(v));
        }
        assert_eq!(s.recent_ns.len(), 3);
        let t = s.summary().times.unwrap();
        // Median of 3, 4, 5; the rest over all five.
        assert_eq!(t.median_ns, 4e6);
        assert_eq!((t.min_ns, t.max_ns), (1_000_000, 5_000_000));
        assert!((t.mean_ns - 3e6).abs() < 1e-3);
        assert!((t.sd_ns - 2f64.sqrt() * 1e6).abs() < 1e-3, "{}", t.sd_ns);
    }

    #[test]
    fn large_times_with_small_spread_keep_their_precision() {
        // 324 s transfers (Table 4.8) a nanosecond apart: a naive sum of squares in f64
        // would lose the spread entirely.
        let mut s = TransferStats::new();
        for extra in [1, 2, 3] {
            s.record(Duration::from_nanos(324_000_000_000 + extra));
        }
        let t = s.summary().times.unwrap();
        assert!((t.sd_ns - (2f64 / 3.0).sqrt()).abs() < 1e-3, "{}", t.sd_ns);
        assert_eq!(t.median_ns, 324_000_000_002.0);
    }

    #[test]
    fn live_stats_give_the_rate_between_first_and_last_and_latency_percentiles() {
        let mut s = LiveStats::default();
        let t0 = std::time::Instant::now();
        for i in 0..21u64 {
            let latency = Duration::from_millis(if i == 20 { 50 } else { 10 + i % 3 });
            s.record(t0 + Duration::from_millis(100 * i), Some(latency));
        }
        s.skipped = 3;
        let summary = s.summary();
        assert_eq!(summary.frames, 21);
        assert!((summary.fps.unwrap() - 10.0).abs() < 1e-9, "{summary:?}");
        assert_eq!(summary.latency_ms, Some([11.0, 12.0, 50.0]));
        assert_eq!(summary.skipped, 3);
        assert_eq!(LiveStats::default().summary().fps, None);
    }
}
