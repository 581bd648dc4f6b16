//! `coapcam monitor`: the thesis's test procedure (§3.4) as a command. A grab or a
//! measurement is repeated every `--interval` seconds (or a resource is observed), one
//! line is printed per result, and the transfer times are summarised as in the thesis's
//! Tables 4.1-4.11: count, minimum, median, maximum, mean, standard deviation and
//! coefficient of variation.

use std::time::{Duration, Instant, SystemTime};

use anyhow::bail;
use clap::Args;
use coap::ContentFormat;

use coapcam::api::record::Record;
use coapcam::client::live::{self, LiveFrame};
use coapcam::client::measure::{self, Calibration, Source};
use coapcam::client::timed::{self, Repeat, Timed, TimedError};
use coapcam::client::{CamClient, results};
use coapcam::report::{Billing, Found, Measurement, Parcel, Reported};
use coapcam::repr::Stream;
use coapcam::stats::{LiveStats, TransferStats};

use super::{
    CameraArgs, DimensionArgs, Exit, Interrupted, Signals, TransmissionArgs, error_text,
    exit_status, out, outln, usage, values,
};

/// What `monitor` repeats.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub(crate) enum Target {
    /// Grab a color image of one camera.
    Color,
    /// Grab a depth image of one camera.
    Depth,
    /// Grab a point cloud of one camera.
    Pointcloud,
    /// Grab every camera's cloud, merged (POST /cams/pointclouds).
    Pointclouds,
    /// Measure the parcel (one camera with --camera, else every camera of the server).
    Measure,
}

impl Target {
    /// The grab resource of one camera, if the target is one.
    fn stream(self) -> Option<Stream> {
        match self {
            Self::Color => Some(Stream::Color),
            Self::Depth => Some(Stream::Depth),
            Self::Pointcloud => Some(Stream::Pointcloud),
            Self::Pointclouds | Self::Measure => None,
        }
    }
}

/// Flags of `monitor`.
#[derive(Debug, Args)]
pub(crate) struct MonitorArgs {
    /// What to repeat (or, with --observe, which resource of the camera to observe).
    target: Target,
    #[command(flatten)]
    cameras: CameraArgs,
    /// Seconds from the start of one request to the start of the next; a request that
    /// takes longer is followed at once by the next.
    #[arg(
        long,
        value_name = "SECONDS",
        default_value = "1",
        conflicts_with = "observe",
        value_parser = values::seconds_or_zero
    )]
    interval: Duration,
    /// Stop after this many results (failed ones included); without it, run until Ctrl-C.
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u64).range(1..))]
    count: Option<u64>,
    /// Observe the camera's color, depth or pointcloud resource (GET with Observe) instead
    /// of grabbing: the latest frame, then each frame anyone grabs, is a result; its time
    /// is the time since the previous result. A camera with no frame yet is waited for
    /// (said on standard error) until someone grabs one. With `measure`: follow the station's
    /// results log (/station/measurements/latest) instead of measuring: each measurement
    /// recorded from then on (by a client or the station itself) is a result, none
    /// skipped (records appended between two notifications are fetched).
    #[arg(long)]
    observe: bool,
    /// Observe the camera's live stream (/cams/<sn>/<stream>/live): each frame with its
    /// capture-to-client latency, then the frames per second and the latency's p50 and p95;
    /// a frame that arrives while an older one is taken in is skipped for the newer.
    #[arg(long, conflicts_with_all = ["observe", "interval"])]
    live: bool,
    /// With --live: frames a second to ask for (the camera's rate at most and by default).
    #[arg(long, value_name = "N", requires = "live",
          value_parser = clap::value_parser!(u32).range(1..=1000))]
    fps: Option<u32>,
    /// The representation asked for (Accept): a number or a short name (png, jpeg, cbor,
    /// ply, depth-cloud, ...). Left out, grabs ask for the compact form (color JPEG, depth
    /// RVL+zstd, clouds the compact cloud; the thesis packet from a server without it)
    /// and --observe for the thesis packet. Not for `measure`.
    #[arg(long, value_name = "CF")]
    accept: Option<ContentFormat>,
    /// One JSON object per line for each result, and the statistics as the last line.
    #[arg(long)]
    json: bool,
    #[command(flatten)]
    dimension: DimensionArgs,
    #[command(flatten)]
    transmission: TransmissionArgs,
}

/// A line of `--json` for a request that succeeded: with `--measure` the measurement's
/// fields, then the request's.
#[derive(serde::Serialize)]
struct Line {
    #[serde(flatten)]
    measurement: Option<Measurement>,
    /// With `measure --observe`: the record's id, time, station and trigger.
    #[serde(skip_serializing_if = "Option::is_none")]
    record: Option<RecordLine>,
    n: u64,
    at_unix_ms: u64,
    ok: bool,
    received_bytes: usize,
    time_ms: f64,
    mean_ms: f64,
    #[serde(skip_serializing_if = "Option::is_none")]
    latency_ms: Option<f64>,
}

/// A record's fields on a `--json` line of `measure --observe`.
#[derive(serde::Serialize)]
struct RecordLine {
    id: u64,
    time: String,
    station: String,
    trigger: &'static str,
}

impl Success {
    /// A grab or a measurement; a measurement is reported as `calibration` says (an
    /// uncalibrated camera's measurement has no dimensions, as with `measure`).
    fn timed(t: Timed, calibration: &Calibration) -> Self {
        Self {
            bytes: t.bytes,
            time: t.time,
            measurement: t.measurement.map(|m| Measurement {
                // The line's own.
                received_bytes: None,
                ..m.report_with(&Billing::default(), calibration)
            }),
            record: None,
            latency: None,
        }
    }
}

/// What one request brought.
struct Success {
    bytes: usize,
    /// The time the statistics count.
    time: Duration,
    measurement: Option<Measurement>,
    /// A record of the results log (`measure --observe`).
    record: Option<Record>,
    /// A live frame's capture-to-client latency.
    latency: Option<Duration>,
}

/// What `monitor` does, resolved once at the start.
enum Plan {
    Repeat(Repeat),
    Observe {
        serial: String,
        stream: Stream,
    },
    /// `measure --observe`: the results log's new records.
    Records,
}

impl Plan {
    async fn resolve(args: &MonitorArgs, client: &CamClient) -> anyhow::Result<Self> {
        if let Some(stream) = args.target.stream() {
            let serial = client.one_camera(args.cameras.camera.as_deref()).await?;
            return Ok(if args.observe || args.live {
                Self::Observe { serial, stream }
            } else {
                Self::Repeat(Repeat::Grab { serial, stream })
            });
        }
        if args.observe || args.live {
            if args.target != Target::Measure || args.live {
                bail!(
                    "--observe watches one camera's color, depth or pointcloud resource, or the measurements; --live one camera's stream"
                );
            }
            if args.cameras.camera.is_some() {
                bail!(
                    "measure --observe follows every measurement of the station; leave out --camera"
                );
            }
            return Ok(Self::Records);
        }
        let repeat = match (args.target, &args.cameras.camera) {
            (Target::Measure, Some(sn)) => Repeat::Measure(Source::Camera(sn.clone())),
            (Target::Measure, None) => Repeat::Measure(Source::All),
            (_, Some(_)) => bail!("pointclouds merges every camera; leave out --camera"),
            (_, None) => Repeat::All,
        };
        Ok(Self::Repeat(repeat))
    }

    /// Words for the header (`live`: of the live stream).
    fn describe(&self, live: bool) -> String {
        match self {
            Self::Repeat(Repeat::Grab { serial, stream }) => {
                format!("POST /cams/{serial}/{}", stream.name())
            }
            Self::Repeat(Repeat::All) => "POST /cams/pointclouds".to_owned(),
            Self::Repeat(Repeat::Measure(Source::Camera(sn))) => {
                format!("measure with camera {sn}")
            }
            Self::Repeat(Repeat::Measure(_)) => "measure with every camera".to_owned(),
            Self::Observe { serial, stream } if live => {
                format!("observe GET {}", live::path(serial, *stream))
            }
            Self::Observe { serial, stream } => {
                format!("observe GET /cams/{serial}/{}", stream.name())
            }
            Self::Records => format!("observe GET {}", coapcam::api::paths::LATEST),
        }
    }
}

/// Prints results and keeps the statistics.
struct Report {
    json: bool,
    stats: TransferStats,
    seen: u64,
    /// How the last failed result would end the command.
    last_failure: Option<Exit>,
    /// With --live: the frame rate, the latencies and the frames skipped.
    live: LiveStats,
}

impl Report {
    fn result(
        &mut self,
        outcome: anyhow::Result<Success>,
        elapsed: Duration,
    ) -> anyhow::Result<()> {
        self.seen += 1;
        let unix_ms = SystemTime::now()
            .duration_since(SystemTime::UNIX_EPOCH)
            .map_or(0, |d| d.as_millis() as u64);
        match outcome {
            Ok(s) => {
                self.stats.record(s.time);
                self.live.record(Instant::now(), s.latency);
                let mean = self.stats.mean().unwrap_or(s.time);
                if self.json {
                    let measurement = s
                        .measurement
                        .clone()
                        .or_else(|| s.record.as_ref().map(|r| r.measurement.clone()));
                    let record = s.record.as_ref().map(|r| RecordLine {
                        id: r.id,
                        time: r.time.to_string(),
                        station: r.station.clone(),
                        trigger: r.trigger.name(),
                    });
                    let line = Line {
                        measurement,
                        record,
                        n: self.seen,
                        at_unix_ms: unix_ms,
                        ok: true,
                        received_bytes: s.bytes,
                        time_ms: millis(s.time),
                        mean_ms: millis(mean),
                        latency_ms: s.latency.map(millis),
                    };
                    outln!("{}", serde_json::to_string(&line)?);
                } else {
                    let mut line = format!(
                        "#{:<4} {}  {:>12} B  {:>10.1} ms  mean {:.1} ms",
                        self.seen,
                        clock(unix_ms),
                        thousands(s.bytes),
                        millis(s.time),
                        millis(mean)
                    );
                    if let Some(latency) = s.latency {
                        line += &format!("  latency {:.1} ms", millis(latency));
                    }
                    if let Some(r) = &s.record {
                        line += &format!(
                            "  record #{} {} {} {}",
                            r.id,
                            r.time,
                            r.station,
                            r.trigger.name()
                        );
                    }
                    let measurement = s
                        .measurement
                        .as_ref()
                        .or_else(|| s.record.as_ref().map(|r| &r.measurement));
                    match measurement.map(|m| (&m.parcel, m.parcel())) {
                        Some((Found::Uncalibrated { uncalibrated }, _)) => {
                            line += &format!(
                                "  not calibrated ({}): no dimensions",
                                uncalibrated.join(", ")
                            );
                        }
                        Some((_, Parcel::Measured(d, _))) => {
                            let dims = measurement
                                .and_then(Measurement::reported)
                                .map_or_else(String::new, Reported::dimensions_text);
                            line +=
                                &format!("  {dims}, yaw {:.1} deg, {} points", d.yaw_deg, d.points);
                        }
                        Some((_, Parcel::Nothing { .. })) => line += "  nothing on the table",
                        Some((_, Parcel::Refused { reason, .. })) => {
                            line += &format!("  refused: {reason}");
                        }
                        None => {}
                    }
                    if let Some(codes) = s.record.as_ref().map(Record::code_texts)
                        && !codes.is_empty()
                    {
                        line += &format!(", codes {}", codes.join(", "));
                    }
                    outln!("{line}");
                }
            }
            Err(e) => {
                self.stats.record_failure();
                self.last_failure = exit_status(&e);
                if self.json {
                    let line = serde_json::json!({
                        "n": self.seen,
                        "at_unix_ms": unix_ms,
                        "ok": false,
                        "time_ms": millis(elapsed),
                        "error": error_text(e.as_ref()),
                    });
                    outln!("{line}");
                } else {
                    outln!(
                        "#{:<4} {}  failed after {:.1} ms: {}",
                        self.seen,
                        clock(unix_ms),
                        millis(elapsed),
                        error_text(e.as_ref())
                    );
                }
            }
        }
        Ok(())
    }

    /// Whether `--count` results have been printed.
    fn done(&self, count: Option<u64>) -> bool {
        count.is_some_and(|n| self.seen >= n)
    }
}

/// Milliseconds with a tenth of a microsecond.
fn millis(d: Duration) -> f64 {
    (d.as_secs_f64() * 1e7).round() / 1e4
}

/// `hh:mm:ss.mmm UTC` of a UNIX time in milliseconds.
fn clock(unix_ms: u64) -> String {
    let ms_of_day = unix_ms % 86_400_000;
    format!(
        "{:02}:{:02}:{:02}.{:03} UTC",
        ms_of_day / 3_600_000,
        ms_of_day / 60_000 % 60,
        ms_of_day / 1000 % 60,
        ms_of_day % 1000
    )
}

/// 2764810 -> "2,764,810".
fn thousands(n: usize) -> String {
    let digits = n.to_string();
    let mut out = String::with_capacity(digits.len() + digits.len() / 3);
    for (i, c) in digits.chars().enumerate() {
        if i > 0 && (digits.len() - i).is_multiple_of(3) {
            out.push(',');
        }
        out.push(c);
    }
    out
}

/// Repeats the plan every `args.interval` until `args.count` results.
async fn repeat(
    client: &CamClient,
    plan: &Repeat,
    args: &MonitorArgs,
    report: &mut Report,
) -> anyhow::Result<()> {
    // tokio's interval refuses a zero period: then the requests follow each other.
    let period = args.interval;
    let mut ticks = (!period.is_zero()).then(|| {
        let mut ticks = tokio::time::interval(period);
        ticks.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        ticks
    });
    let config = args.dimension.config();
    // Whether the measured cameras are calibrated, asked once at the first measurement
    // (their documents, outside the timed requests).
    let mut calibration = None;
    while !report.done(args.count) {
        if let Some(ticks) = &mut ticks {
            ticks.tick().await;
        }
        let started = Instant::now();
        let outcome = timed::once(client, plan, args.accept, &config).await;
        let elapsed = started.elapsed();
        if let (
            Ok(Timed {
                measurement: Some(m),
                ..
            }),
            None,
        ) = (&outcome, &calibration)
        {
            calibration = Some(measure::calibration_of(client, &m.grabbed.cameras).await);
        }
        let calibration = calibration.clone().unwrap_or_default();
        let outcome = outcome.map(|t| Success::timed(t, &calibration));
        report.result(outcome.map_err(anyhow::Error::from), elapsed)?;
    }
    Ok(())
}

/// Carries out `plan` until `args.count` results (or for ever), each into `report`.
async fn carry_out(
    plan: &Plan,
    client: &CamClient,
    args: &MonitorArgs,
    report: &mut Report,
) -> anyhow::Result<()> {
    let timeout = args.transmission.timeout();
    match plan {
        Plan::Observe { serial, stream } if args.live => {
            let on_frame = |frame: Result<LiveFrame, TimedError>| {
                let elapsed = frame.as_ref().map_or(Duration::ZERO, |f| f.gap);
                if let Ok(f) = &frame {
                    report.live.skipped = f.skipped;
                }
                let frame = frame.map(|f| Success {
                    bytes: f.bytes,
                    time: f.gap,
                    measurement: None,
                    record: None,
                    latency: f.latency,
                });
                report.result(frame.map_err(anyhow::Error::from), elapsed)?;
                Ok::<_, anyhow::Error>(report.done(args.count))
            };
            let (accept, fps) = (args.accept, args.fps);
            live::follow(client, serial, *stream, accept, fps, timeout, on_frame).await
        }
        Plan::Observe { serial, stream } => {
            let on_result = |outcome: Result<Timed, TimedError>, elapsed| {
                let grab = outcome.map(|t| Success::timed(t, &Calibration::default()));
                report.result(grab.map_err(anyhow::Error::from), elapsed)?;
                Ok::<_, anyhow::Error>(report.done(args.count))
            };
            let on_waiting = |path: &str| {
                eprintln!(
                    "coapcam: camera {serial} has no frame yet: waiting for the first one anyone grabs (POST {path} grabs one)"
                );
            };
            timed::observe(
                client,
                serial,
                *stream,
                args.accept,
                timeout,
                on_waiting,
                on_result,
            )
            .await
        }
        Plan::Repeat(repeat_plan) => repeat(client, repeat_plan, args, report).await,
        Plan::Records => {
            let on_start = |from| {
                eprintln!(
                    "coapcam: following {} from record #{from}",
                    coapcam::api::paths::LATEST
                )
            };
            let on_record = |record, bytes, elapsed| {
                let success = Success {
                    bytes,
                    time: elapsed,
                    measurement: None,
                    record: Some(record),
                    latency: None,
                };
                report.result(Ok(success), elapsed)?;
                Ok::<_, anyhow::Error>(report.done(args.count))
            };
            results::follow(client, timeout, on_start, on_record).await
        }
    }
}

/// Runs `monitor`: a success when at least one result succeeded, else as its last
/// failure.
pub(crate) async fn run(args: MonitorArgs) -> anyhow::Result<Exit> {
    if args.interval.is_zero() && args.count.is_none() && !args.observe {
        usage!("--interval 0 needs --count");
    }
    if args.accept.is_some() && args.target == Target::Measure {
        usage!("--accept is for grabs: a measurement asks for the compact cloud");
    }
    // SIGINT and SIGTERM end the command from here on: before the first result as in
    // every command (status 130 or 143), after it with the statistics.
    let mut signals = Signals::install()?;
    let (client, plan) = tokio::select! {
        ready = async {
            let client = args.cameras.connect(&args.transmission).await?;
            let plan = Plan::resolve(&args, &client).await?;
            anyhow::Ok((client, plan))
        } => ready?,
        signal = signals.recv() => return Err(signal.into()),
    };
    let what = plan.describe(args.live);
    if !args.json {
        match args.count {
            Some(n) => outln!("{what}: {n} result(s)"),
            None => outln!("{what}: until Ctrl-C"),
        }
    }
    let mut report = Report {
        json: args.json,
        stats: TransferStats::new(),
        seen: 0,
        last_failure: None,
        live: LiveStats::default(),
    };
    let work = carry_out(&plan, &client, &args, &mut report);
    let mut interrupted = None;
    let ended = tokio::select! {
        ended = work => ended,
        signal = signals.recv() => {
            interrupted = Some(signal);
            Ok(())
        }
    };
    let summary = report.stats.summary();
    let live = args.live.then(|| report.live.summary());
    if args.json {
        let mut json = summary.to_json();
        if let Some(live) = &live {
            json["live"] = live.to_json();
        }
        outln!("{json}");
    } else {
        let times = if args.observe || args.live {
            "times between results"
        } else {
            "transfer times"
        };
        out!("{}", summary.text(times));
        if let Some(live) = &live {
            out!("{}", live.text());
        }
    }
    ended?;
    Ok(if summary.count > 0 {
        Exit::Success
    } else if let Some(Interrupted(signal)) = interrupted
        && summary.failed == 0
    {
        // Stopped before any result: as every command stopped by a signal.
        eprintln!("coapcam: interrupted by signal {signal}");
        Exit::Interrupted(signal)
    } else {
        report.last_failure.unwrap_or(Exit::Failure)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn clock_and_thousands_format_as_printed() {
        assert_eq!(clock(86_400_000 + 3_723_045), "01:02:03.045 UTC");
        assert_eq!(thousands(2_764_810), "2,764,810");
        assert_eq!(thousands(999), "999");
        assert_eq!(thousands(1000), "1,000");
        assert_eq!(millis(Duration::from_micros(12_345)), 12.345);
    }
}
