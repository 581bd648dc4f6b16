//! Measuring: point clouds grabbed from one camera, from every camera of a server, or
//! from every server of a multicast group, merged and handed to `geometry::dimension`;
//! the preparation of the cameras that makes the clouds small (docs/design.md §6); and the
//! comparison with a synthetic scene's truth.

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use bytes::Bytes;
use coap::Code;
use geometry::{DimensionConfig, DimensionError, Dimensions, Point3, PointCloud, Roi3, RoiError};
use rgbd::filter::{FlyingPixelsConfig, SpatialConfig};
use rgbd::{ColorSettings, Scene};

use super::{
    CallError, CamClient, DiscoveryError, DocumentError, FrameError, NoAnswer, check, clocks,
    cloud_of,
};
use crate::documents::AppConfig;
use crate::report::{self, Billing, Found, Measurement, Parcel, Table};
use crate::repr::no_depth::{self, NoDepth};
use crate::timesync::{FrameTime, Limits, MAX_BELIEVED_APART_US, Problem, ServerTimes};

/// A measurement, its grabs or the cameras' preparation failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum MeasureError {
    /// A request failed (transparent: the causes the command's exit status looks for
    /// are the [`CallError`]'s sources, not itself).
    #[error(transparent)]
    Call(#[from] CallError),
    /// The cameras of a server could not be listed (transparent, as `Call`).
    #[error(transparent)]
    Discovery(#[from] DiscoveryError),
    /// A camera's document could not be read or written (transparent, as `Call`).
    #[error(transparent)]
    Document(#[from] DocumentError),
    /// One server's grab failed ([`Source::Servers`]).
    #[error("grabbing the clouds of {server}")]
    Server {
        /// The server.
        server: SocketAddr,
        /// Why.
        source: CallError,
    },
    /// The group request was not sent, or failed.
    #[error("POST /cams/pointclouds to the group {group}")]
    Group {
        /// The group.
        group: SocketAddr,
        /// Why.
        source: coap_net::Error,
    },
    /// No server of the group answered. Said as the [`NoAnswer`] says itself, which is
    /// also the source (not `transparent`), so that the command's exit status finds it
    /// among the causes; [`crate::error_text`] says it once.
    #[error("{0}")]
    NoAnswer(#[source] NoAnswer),
    /// Servers of the group answered, but none with a cloud.
    #[error("no server of the group {group} sent a cloud: {}", failed.join("; "))]
    NoCloud {
        /// The group.
        group: SocketAddr,
        /// Why each server's answer was left out.
        failed: Vec<String>,
    },
    /// A server's cloud did not decode.
    #[error("reading the point cloud of {server}")]
    Cloud {
        /// The server.
        server: SocketAddr,
        /// Why.
        source: FrameError,
    },
    /// A grab task panicked or was cancelled.
    #[error("a grab task failed")]
    GrabTask(#[source] tokio::task::JoinError),
    /// The decoding task panicked or was cancelled.
    #[error("the decoding task failed")]
    DecodingTask(#[source] tokio::task::JoinError),
    /// The measuring task panicked or was cancelled.
    #[error("the measuring task failed")]
    MeasuringTask(#[source] tokio::task::JoinError),
    /// The merged cloud could not be measured.
    #[error("measuring the point cloud")]
    Measuring(#[source] DimensionError),
    /// The box the cameras are prepared to keep is not one.
    #[error("roi3d within {half_width_m} m")]
    Roi {
        /// The half width asked for.
        half_width_m: f64,
        /// Why.
        source: RoiError,
    },
}

/// Where the clouds come from.
#[derive(Debug, Clone)]
pub enum Source {
    /// One camera of a server.
    Camera(String),
    /// Every camera of a server, merged by the server.
    All,
    /// Every camera of each of these servers, asked at once, merged here.
    Servers(Vec<SocketAddr>),
    /// Every server of a multicast group.
    Group {
        /// The group's address and port.
        group: SocketAddr,
        /// Stop once this many servers answered.
        expect: Option<usize>,
        /// How long to collect answers.
        wait: Duration,
        /// The members a resource directory lists (`measure --group --rd`): collecting
        /// stops as soon as each of these addresses answered, and an answer from any
        /// other address is left out (anyone on the link can join a group; the directory
        /// says who the stations are). Empty: not known, every answer counts.
        members: Vec<SocketAddr>,
    },
}

/// A task aborted when dropped.
struct AbortOnDrop(tokio::task::JoinHandle<()>);

impl Drop for AbortOnDrop {
    fn drop(&mut self) {
        self.0.abort();
    }
}

/// The clouds of one measurement, merged, and where they came from.
#[derive(Debug)]
pub struct Grabbed {
    /// Every camera's cloud in the common frame.
    pub cloud: PointCloud,
    /// `(server, camera serial)` of every camera that contributed.
    pub cameras: Vec<(SocketAddr, String)>,
    /// Frame timestamps, microseconds since the UNIX epoch (one per cloud received).
    pub timestamps_us: Vec<u64>,
    /// Each camera's frame with its capture time on its server's clock, where the
    /// representation tells (the compact cloud).
    pub frames: Vec<FrameTime>,
    /// Clouds whose representation does not tell each camera's capture time: their
    /// frames are not checked.
    pub untimed: Vec<String>,
    /// Servers of a group that answered with an error, and why: their clouds are missing.
    pub failed: Vec<String>,
    /// Bytes of point-cloud representations received.
    pub bytes: usize,
    /// What the cameras saw, when the clouds came as the compact cloud.
    pub views: Vec<geometry::View>,
    /// The parts of the table from which the cameras' pixels returned no depth, as their
    /// servers found them (the No-Depth option; none from a server without it).
    pub no_depth: Vec<NoDepth>,
}

/// One measurement made here from the clouds, with the clouds, their provenance and the
/// timing ([`CloudMeasurement::report`] is what it reports).
#[derive(Debug)]
pub struct CloudMeasurement {
    /// The largest parcel's dimensions, or that nothing is on the table.
    pub parcel: Parcel,
    /// Every parcel on the table.
    pub table: Table,
    /// The coverage below which a parcel is not complete.
    pub min_coverage: f32,
    /// The clouds it was measured from.
    pub grabbed: Grabbed,
    /// From sending the first request until the result was known.
    pub cycle: Duration,
    /// Of the cycle: until the last cloud arrived (the servers' grabs and the transfers).
    pub grab: Duration,
    /// Why the frames do not belong together; when there is a reason, nothing was
    /// measured (`parcel` is nothing with 0 points).
    pub unsynced: Vec<Problem>,
    /// What could not be checked of the frames' times.
    pub unchecked: Vec<String>,
}

impl CloudMeasurement {
    /// The servers that sent clouds, each once, in the order they answered.
    pub fn servers(&self) -> Vec<SocketAddr> {
        let mut servers: Vec<SocketAddr> = Vec::new();
        for (server, _) in &self.grabbed.cameras {
            if !servers.contains(server) {
                servers.push(*server);
            }
        }
        servers
    }

    /// The parcel's dimensions; `None` when nothing is on the table.
    pub fn dimensions(&self) -> Option<&Dimensions> {
        match &self.parcel {
            Parcel::Measured(d, _) => Some(d),
            Parcel::Nothing { .. } | Parcel::Refused { .. } => None,
        }
    }

    /// What it reports (the document of `measure --json`, docs/design.md §6): the
    /// parcel as `billing` says and where the clouds came from. The clouds do not say
    /// which camera is uncalibrated (the thesis packet carries no transform), so only a
    /// floor far from z = 0 warns; [`CloudMeasurement::report_with`] knows more.
    pub fn report(&self, billing: &Billing) -> Measurement {
        self.report_with(billing, &Calibration::default())
    }

    /// [`CloudMeasurement::report`] with what the cameras' documents said
    /// ([`calibration_of`]): no dimensions when a camera is uncalibrated, and no floor
    /// check on a cloud whose floor every camera's `roi3d` cut away (it would look
    /// miscalibrated; the server's measurement checks the floor in the whole views).
    pub fn report_with(&self, billing: &Billing, calibration: &Calibration) -> Measurement {
        let g = &self.grabbed;
        let cameras = g.cameras.iter().map(|(_, sn)| sn.clone()).collect();
        let mut m = Measurement::of_table(
            &self.table,
            billing,
            self.min_coverage,
            g.cloud.len(),
            cameras,
            g.timestamps_us.clone(),
            self.grab,
        );
        m.servers = g.cameras.iter().map(|(s, _)| *s).collect();
        m.cycle_ms = Some(report::ms(self.cycle));
        m.received_bytes = Some(g.bytes as u64);
        m.frames = g.frames.clone();
        m.warnings = g.failed.clone();
        m.warnings.extend(duplicate_serials(&g.cameras));
        m.warnings.extend(self.unchecked.iter().cloned());
        m.warnings.extend(g.untimed.iter().cloned());
        if !self.unsynced.is_empty() {
            let reasons: Vec<String> = self.unsynced.iter().map(ToString::to_string).collect();
            m.parcel = Found::Unsynced {
                reason: reasons.join("; "),
            };
            m.cloud_points = 0;
            m.warnings.extend(reasons);
            return m;
        }
        let floor = if calibration.floor_cut {
            Vec::new()
        } else {
            vec![(
                None,
                report::floor_level(g.cloud.points.iter().map(|p| p.z)),
            )]
        };
        m.warnings.extend(report::calibration_warnings(
            &calibration.uncalibrated,
            &floor,
        ));
        m.withhold_uncalibrated(&calibration.uncalibrated);
        m
    }
}

/// A warning for each serial that more than one server answered for (two scene files
/// that share a serial, a copied state): the clouds are all merged, but the serial does
/// not say which camera is meant (`--camera`, the calibration, the record's cameras).
fn duplicate_serials(cameras: &[(SocketAddr, String)]) -> Vec<String> {
    let mut servers: BTreeMap<&str, Vec<String>> = BTreeMap::new();
    for (server, sn) in cameras {
        servers.entry(sn).or_default().push(server.to_string());
    }
    servers
        .into_iter()
        .filter(|(_, at)| at.len() > 1)
        .map(|(sn, at)| {
            format!(
                "camera serial {sn} came from {} servers ({}): each camera is merged, but the serial does not tell them apart; give each camera its own serial (a synthetic camera's `serial` in its scene file)",
                at.len(),
                at.join(", ")
            )
        })
        .collect()
}

/// What the cameras' documents say about a measurement's calibration.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Calibration {
    /// Cameras whose 3d-transformation is the identity.
    pub uncalibrated: Vec<String>,
    /// Every camera's `roi3d` starts above z = 0: the floor is not in the cloud.
    pub floor_cut: bool,
}

/// Asks each camera of `cameras` (`(server, serial)`, as [`Grabbed`] names them) for its
/// 3d-transformation and application-config: which are uncalibrated, and whether the
/// floor was cut away. A camera whose documents cannot be read counts as calibrated and
/// uncut (the cloud's floor is then checked).
pub async fn calibration_of(client: &CamClient, cameras: &[(SocketAddr, String)]) -> Calibration {
    let mut out = Calibration {
        uncalibrated: Vec::new(),
        floor_cut: !cameras.is_empty(),
    };
    for (server, sn) in cameras {
        let one = CamClient::unicast(client, *server);
        let transformation = one
            .get_json::<geometry::Transformation>(sn, "3d-transformation")
            .await;
        if transformation.is_ok_and(|t| t == geometry::Transformation::identity()) {
            out.uncalibrated.push(sn.clone());
        }
        let app = one.get_json::<AppConfig>(sn, "application-config").await;
        if !app.is_ok_and(|a| a.roi3d.min().z > 0.0) {
            out.floor_cut = false;
        }
    }
    out
}

/// Grabs the clouds of `source` (`client` is the server's client; for a group, any
/// client) and merges them. Clouds come compactly (65103) from servers that offer it, as
/// the thesis packet from the others.
pub async fn grab_clouds(client: &CamClient, source: &Source) -> Result<Grabbed, MeasureError> {
    let mut failed = Vec::new();
    let answers = match source {
        Source::Camera(sn) => vec![(client.server(), client.grab_cloud(Some(sn)).await?)],
        Source::All => vec![(client.server(), client.grab_cloud(None).await?)],
        Source::Servers(servers) => {
            // All at once: frames asked for one after the other would be a transfer apart.
            let mut grabs = tokio::task::JoinSet::new();
            for (i, &server) in servers.iter().enumerate() {
                let one = CamClient::unicast(client, server);
                grabs.spawn(async move { (i, server, one.grab_cloud(None).await) });
            }
            let mut answers = Vec::with_capacity(servers.len());
            while let Some(done) = grabs.join_next().await {
                let (i, server, r) = done.map_err(MeasureError::GrabTask)?;
                let r = r.map_err(|source| MeasureError::Server { server, source })?;
                answers.push((i, server, r));
            }
            answers.sort_by_key(|(i, ..)| *i);
            let answers: Vec<_> = answers.into_iter().map(|(_, s, r)| (s, r)).collect();
            answers
        }
        Source::Group {
            group,
            expect,
            wait,
            members,
        } => {
            let accept = Some(crate::repr::DEPTH_CLOUD);
            let mut request = client.request(
                Code::POST,
                crate::api::paths::POINTCLOUDS,
                Bytes::new(),
                None,
                accept,
            );
            request.timeout = Some(*wait);
            // A listed member that is gone without removing its registration: a small
            // unicast request meets its closed port (ICMP port unreachable), and it is
            // not waited for.
            let gone = Arc::new(Mutex::new(Vec::<SocketAddr>::new()));
            let probes: Vec<_> = members
                .iter()
                .map(|m| {
                    let (coap, gone, m) = (client.coap().clone(), gone.clone(), *m);
                    let mut probe = coap::Request::new(Code::GET, "/.well-known/core");
                    probe
                        .options
                        .push(coap::OptionNumber::URI_QUERY, "href=/coap-group");
                    probe.timeout = Some(*wait);
                    AbortOnDrop(tokio::spawn(async move {
                        if let Err(coap_net::Error::Request(coap::RequestError::Unreachable)) =
                            coap.send(m, probe).await
                        {
                            gone.lock().unwrap_or_else(PoisonError::into_inner).push(m);
                        }
                    }))
                })
                .collect();
            let sent_us = clocks::unix_now_us();
            let answers = client
                .coap()
                .multicast_until(*group, request, |answers| {
                    let gone = gone.lock().unwrap_or_else(PoisonError::into_inner);
                    let all_members = !members.is_empty()
                        && members
                            .iter()
                            .all(|m| gone.contains(m) || answers.iter().any(|(from, _)| from == m));
                    all_members || expect.is_some_and(|n| answers.len() >= n)
                })
                .await
                .map_err(|source| MeasureError::Group {
                    group: *group,
                    source,
                })?;
            drop(probes);
            let (answers, strangers): (Vec<_>, Vec<_>) = answers
                .into_iter()
                .partition(|(from, _)| members.is_empty() || members.contains(from));
            for (from, _) in &strangers {
                failed.push(format!(
                    "{from} answered the group {group} but the directory does not list it: left out"
                ));
            }
            for m in gone.lock().unwrap_or_else(PoisonError::into_inner).iter() {
                failed.push(format!("{m}: port unreachable (the server is not running)"));
            }
            // Samples of the servers' clocks, loose ones: the answers were collected
            // until the last (the filter prefers the quick exchanges that follow).
            let received_us = clocks::unix_now_us();
            for (server, r) in &answers {
                client
                    .clocks()
                    .exchanged(*server, sent_us, &r.options, received_us);
            }
            if answers.is_empty() {
                let also = if failed.is_empty() {
                    String::new()
                } else {
                    format!(" ({})", failed.join("; "))
                };
                return Err(MeasureError::NoAnswer(NoAnswer(format!(
                    "no server of the group {group} answered within {wait:?}{also}"
                ))));
            }
            let mut checked = Vec::with_capacity(answers.len());
            for (server, r) in answers {
                let r = if r.code == Code::NOT_ACCEPTABLE {
                    // A server without the compact cloud: its thesis packet.
                    CamClient::unicast(client, server).grab_all(None).await
                } else {
                    check(&format!("POST /cams/pointclouds on {server}"), r)
                };
                // One server's failure leaves its cameras out, not the others'.
                match r {
                    Ok(r) => checked.push((server, r)),
                    Err(e) => failed.push(format!("{e:#}")),
                }
            }
            if checked.is_empty() {
                return Err(MeasureError::NoCloud {
                    group: *group,
                    failed,
                });
            }
            checked
        }
    };
    let bytes = answers.iter().map(|(_, r)| r.payload.len()).sum();
    let decoded = tokio::task::spawn_blocking(move || {
        answers
            .into_iter()
            .map(|(server, r)| {
                let asked = ServerTimes::of(&r.options).and_then(Result::ok);
                // A server clock far from ours: its times are not believed (the age of
                // its frames is then not judged, and a warning says so).
                let apart_us = asked.map(|t| t.received_us - clocks::unix_now_us());
                let believed = apart_us.is_none_or(|a| a.abs() <= MAX_BELIEVED_APART_US);
                let asked = asked.filter(|_| believed);
                // An elective option (RFC 7252 §5.4.1): a malformed one is left out.
                let blind = no_depth::of_options(&r.options).unwrap_or_else(|e| {
                    tracing::warn!(%server, error = %e, "a malformed No-Depth option is ignored");
                    Vec::new()
                });
                let c = cloud_of(&r).map_err(|source| MeasureError::Cloud { server, source });
                let distrusted = apart_us.filter(|_| !believed);
                c.map(|c| (server, asked.map(|t| t.received_us), c, blind, distrusted))
            })
            .collect::<Result<Vec<_>, _>>()
    })
    .await
    .map_err(MeasureError::DecodingTask)??;
    let mut grabbed = Grabbed {
        cloud: PointCloud::default(),
        cameras: Vec::new(),
        timestamps_us: Vec::new(),
        frames: Vec::new(),
        untimed: Vec::new(),
        failed,
        bytes,
        views: Vec::new(),
        no_depth: Vec::new(),
    };
    for (server, requested_unix_us, mut c, blind, distrusted) in decoded {
        grabbed.no_depth.extend(blind);
        if let Some(apart_us) = distrusted {
            grabbed.untimed.push(format!(
                "the clock of {server} is {:.0} s from this client's (more than {} min): its times are not believed and its frames' age was not checked",
                apart_us as f64 / 1e6,
                MAX_BELIEVED_APART_US / 60_000_000
            ));
        }
        for f in &c.frames {
            grabbed.frames.push(FrameTime {
                camera: f.serial.clone(),
                server: Some(server),
                frame_number: f.frame_number,
                captured_unix_us: i64::try_from(f.timestamp_us).unwrap_or(i64::MAX),
                requested_unix_us,
                clock: None,
                fps: None,
            });
        }
        if c.frames.is_empty() {
            grabbed.untimed.push(format!(
                "the cloud of {server} does not tell each camera's capture time (not the compact cloud): its frames were not checked"
            ));
        }
        if c.serials.is_empty() {
            // The thesis packet names no camera.
            c.serials = match source {
                Source::Camera(sn) => vec![sn.clone()],
                _ => CamClient::unicast(client, server).cameras().await?,
            };
        }
        grabbed.cloud.extend_from(&c.cloud);
        grabbed.timestamps_us.push(c.timestamp_us);
        grabbed.views.extend(c.views.iter().copied());
        grabbed
            .cameras
            .extend(c.serials.into_iter().map(|sn| (server, sn)));
    }
    Ok(grabbed)
}

/// Grabs and measures once, refusing frames that do not belong together as the default
/// [`Limits`] say (one frame period; see [`measure_checked`]).
pub async fn measure_once(
    client: &CamClient,
    source: &Source,
    config: &DimensionConfig,
) -> Result<CloudMeasurement, MeasureError> {
    let limits = Limits {
        max_skew_us: None,
        skew: true,
    };
    measure_checked(client, source, config, &limits).await
}

/// Grabs, checks that the frames belong together (capture times, corrected by each
/// server's clock offset, no further apart than `limits` allow; no stale camera), and
/// measures if they do; if they do not, nothing is measured and
/// [`CloudMeasurement::unsynced`] says why.
pub async fn measure_checked(
    client: &CamClient,
    source: &Source,
    config: &DimensionConfig,
    limits: &Limits,
) -> Result<CloudMeasurement, MeasureError> {
    let started = Instant::now();
    let mut grabbed = grab_clouds(client, source).await?;
    let grab = started.elapsed();
    // A group's servers answer a multicast request each after a random Leisure (RFC 7252
    // §8.2), and a server that first verifies the client's address (RFC 9175) grabs only
    // when the client's retry comes, so their frames lie up to a Leisure apart: their
    // times are compared only when --max-skew-ms asks; staleness is always checked.
    let mut limits = *limits;
    if matches!(source, Source::Group { .. }) && limits.max_skew_us.is_none() {
        limits.skew = false;
    }
    let checked = super::frames::check_frames(client, &mut grabbed.frames, &limits).await;
    if !checked.problems.is_empty() {
        return Ok(CloudMeasurement {
            parcel: Parcel::Nothing { points: 0 },
            table: Table::default(),
            min_coverage: config.min_coverage,
            grabbed,
            cycle: started.elapsed(),
            grab,
            unsynced: checked.problems,
            unchecked: checked.unchecked,
        });
    }
    let (table, grabbed) = tokio::task::spawn_blocking({
        let config = *config;
        move || {
            let views = if grabbed.views.len() == grabbed.cameras.len() {
                &grabbed.views[..]
            } else {
                // Some cloud came without its views: no camera's view can be judged.
                &[]
            };
            let table = Table::measure(&grabbed.cloud, &config, views)
                .map(|t| t.with_no_depth(&grabbed.no_depth, views));
            (table, grabbed)
        }
    })
    .await
    .map_err(MeasureError::MeasuringTask)?;
    let table = table.map_err(MeasureError::Measuring)?;
    Ok(CloudMeasurement {
        parcel: table.largest(),
        table,
        min_coverage: config.min_coverage,
        grabbed,
        cycle: started.elapsed(),
        grab,
        unsynced: Vec::new(),
        unchecked: checked.unchecked,
    })
}

/// Lowest point sent by the cameras, metres above the floor: the floor itself is not
/// transmitted (thesis §3.3.5), which makes the clouds several times smaller.
pub const FLOOR_CUT_M: f64 = 0.005;

/// Color settings at the D415's largest color mode, 1920x1080 at 30 fps, the format kept.
pub fn full_resolution(color_settings: &ColorSettings) -> ColorSettings {
    ColorSettings {
        width: 1920,
        height: 1080,
        fps: 30,
        ..*color_settings
    }
}

/// Sets the color stream of each camera of `serials` that is not there yet to 1920x1080
/// at 30 fps (its format stays), where the codes' modules span the most pixels; the
/// cameras changed, each with the resolution it had.
pub async fn color_for_codes(
    client: &CamClient,
    serials: &[String],
) -> Result<Vec<(String, (u32, u32))>, MeasureError> {
    let mut changed = Vec::new();
    for sn in serials {
        let color: ColorSettings = client.get_json(sn, "color-settings").await?;
        let full = full_resolution(&color);
        if (color.width, color.height) != (full.width, full.height) {
            client.put_json(sn, "color-settings", &full).await?;
            changed.push((sn.clone(), (color.width, color.height)));
        }
    }
    Ok(changed)
}

/// Prepares every camera for measuring as the thesis does (§3.3.5): roi3d becomes the
/// box above the floor within `half_width_m` of the origin, and the spatial filter runs
/// (librealsense's defaults: it smooths the depth noise that widens a footprint's hull),
/// after the flying-pixel stage (which drops the pixels that straddle a parcel's edge and
/// float on their rays beyond it, widening it and bridging it to its neighbours); the
/// rest of each application-config stays. With `for_codes` the color stream becomes
/// 1920x1080 at 30 fps (its format stays), so smaller codes can be read.
pub async fn prepare_cameras(
    client: &CamClient,
    serials: &[String],
    half_width_m: f64,
    for_codes: bool,
) -> Result<(), MeasureError> {
    if for_codes {
        color_for_codes(client, serials).await?;
    }
    for sn in serials {
        let mut doc: AppConfig = client.get_json(sn, "application-config").await?;
        let (half, floor) = (half_width_m as f32, FLOOR_CUT_M as f32);
        doc.roi3d = Roi3::new(
            Point3::new(-half, -half, floor),
            Point3::new(half, half, 3.0),
        )
        .map_err(|source| MeasureError::Roi {
            half_width_m,
            source,
        })?;
        doc.postprocessing.spatial = Some(SpatialConfig::default());
        doc.postprocessing.flying_pixels = Some(FlyingPixelsConfig::default());
        client.put_json(sn, "application-config", &doc).await?;
    }
    Ok(())
}

/// The scene's largest box as measurements: length >= width, height, yaw of the long
/// side in (-90, 90].
pub fn truth(scene: &Scene) -> Option<[f64; 4]> {
    let b = scene
        .boxes
        .iter()
        .max_by(|a, b| (a.size[0] * a.size[1]).total_cmp(&(b.size[0] * b.size[1])))?;
    let (length, width, mut yaw) = if b.size[0] >= b.size[1] {
        (b.size[0], b.size[1], b.yaw_deg)
    } else {
        (b.size[1], b.size[0], b.yaw_deg + 90.0)
    };
    yaw = (yaw + 90.0).rem_euclid(180.0) - 90.0;
    if yaw <= -90.0 {
        yaw += 180.0;
    }
    Some([length * 1e3, width * 1e3, b.size[2] * 1e3, yaw])
}

/// Difference of two yaw angles of a rectangle's long side, in (-90, 90].
pub fn yaw_difference(a: f64, b: f64) -> f64 {
    let d = (a - b).rem_euclid(180.0);
    if d > 90.0 { d - 180.0 } else { d }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_truth_names_the_long_side_and_its_yaw() {
        let mut scene = Scene::default_single();
        scene.boxes[0].size = [0.3, 0.5, 0.2];
        scene.boxes[0].yaw_deg = 30.0;
        assert_eq!(truth(&scene), Some([500.0, 300.0, 200.0, -60.0]));
        scene.boxes[0].size = [0.5, 0.3, 0.2];
        scene.boxes[0].yaw_deg = 100.0;
        assert_eq!(truth(&scene).map(|t| t[3].round()), Some(-80.0));
    }

    /// Whether a link of `e`'s chain of sources is a `T`.
    fn among_the_causes<T: std::error::Error + 'static>(
        e: &(dyn std::error::Error + 'static),
    ) -> bool {
        let mut cause = Some(e);
        while let Some(c) = cause {
            if c.is::<T>() {
                return true;
            }
            cause = c.source();
        }
        false
    }

    /// The causes the command's exit status looks for (a server's error response: 3;
    /// nobody answered: 4) stay links of a measurement's error, also within a timed
    /// request's, and each is said once.
    #[test]
    fn refusals_and_no_answers_stay_among_the_causes() {
        use crate::client::ErrorResponse;
        use crate::client::timed::TimedError;
        let refused = || {
            check(
                "POST /cams/pointclouds",
                coap::Response::diagnostic(Code::NOT_FOUND, "no camera"),
            )
            .expect_err("a 4.04")
        };
        let said = "POST /cams/pointclouds: 4.04 Not Found: no camera";
        let e = MeasureError::from(refused());
        assert!(among_the_causes::<ErrorResponse>(&e));
        assert_eq!(crate::error_text(&e), said);
        let server = SocketAddr::from(([127, 0, 0, 1], 5683));
        let e = MeasureError::Server {
            server,
            source: refused(),
        };
        assert!(among_the_causes::<ErrorResponse>(&e));
        assert_eq!(
            crate::error_text(&e),
            format!("grabbing the clouds of {server}: {said}")
        );
        let e = TimedError::from(MeasureError::from(refused()));
        assert!(among_the_causes::<ErrorResponse>(&e));
        assert_eq!(crate::error_text(&e), said);

        let none = "no server of the group 224.0.1.187:5683 answered within 1s";
        let e = TimedError::from(MeasureError::NoAnswer(NoAnswer(none.to_owned())));
        assert!(among_the_causes::<NoAnswer>(&e));
        assert!(!among_the_causes::<ErrorResponse>(&e));
        assert_eq!(crate::error_text(&e), none);
    }

    #[test]
    fn yaw_differences_wrap_at_half_a_turn() {
        assert_eq!(yaw_difference(89.0, -89.0), -2.0);
        assert_eq!(yaw_difference(10.0, 5.0), 5.0);
        assert_eq!(yaw_difference(-85.0, 85.0), 10.0);
    }
}
