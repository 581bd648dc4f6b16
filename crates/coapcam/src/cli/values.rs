//! The value parsers the commands' flags share: each turns a flag's text into a typed,
//! checked value while clap parses, so a bad value ends the command with status 2 (usage)
//! before it sends anything, and says which flag and why in words (never Rust's own
//! message for a failed conversion). docs/usage.md's "Values and where they are checked"
//! lists them.

use std::time::Duration;

use coapcam::report::EdgeQuery;

/// The longest time a flag takes: a year, in seconds (well within [`Duration`] and
/// tokio's timers).
const MAX_SECONDS: f64 = 365.0 * 86_400.0;

/// A number of seconds above 0 (`--timeout`, `--wait`, `--duration`).
pub(crate) fn positive_seconds(text: &str) -> Result<Duration, String> {
    seconds(text, false)
}

/// A number of seconds, 0 included (`monitor --interval`).
pub(crate) fn seconds_or_zero(text: &str) -> Result<Duration, String> {
    seconds(text, true)
}

fn seconds(text: &str, zero: bool) -> Result<Duration, String> {
    let least = if zero { "from 0" } else { "above 0" };
    let refused = || format!("{text:?} is not a number of seconds {least} to {MAX_SECONDS:.0}");
    let v: f64 = text.trim().parse().map_err(|_| refused())?;
    let fits = v.is_finite() && v <= MAX_SECONDS && (v > 0.0 || (zero && v == 0.0));
    if !fits {
        return Err(refused());
    }
    Duration::try_from_secs_f64(v).map_err(|_| refused())
}

/// A URI of a scheme coap_net::Uri takes (coap://, coaps://, coap+tcp://, coaps+tcp://,
/// coap+ws://, coaps+ws://) that parses (scheme, host, port 1-65535, percent-encoding);
/// kept as written for the commands that take text.
pub(crate) fn coap_uri(text: &str) -> Result<String, String> {
    coap_net::Uri::parse(text).map_err(|e| e.to_string())?;
    Ok(text.to_owned())
}

/// A multicast group as `measure --group` takes it: `224.0.1.187`, `ff02::fd`,
/// `[ff02::fd%eth0]` or a `coap://group[:port]` URI; kept as a URI. An IP literal must
/// be a multicast address.
pub(crate) fn group(text: &str) -> Result<String, String> {
    let uri = if text.starts_with("coap://") {
        text.to_owned()
    } else if text.contains(':') && !text.starts_with('[') {
        format!("coap://[{text}]")
    } else {
        format!("coap://{text}")
    };
    let parsed = coap_net::Uri::parse(&uri).map_err(|e| e.to_string())?;
    if let Ok(ip) = parsed.host.parse::<std::net::IpAddr>()
        && !ip.is_multicast()
    {
        return Err(format!("{ip} is not a multicast address"));
    }
    Ok(uri)
}

/// A camera's serial number (`--camera`): a D400's 12 digits, or another backend's name
/// for it ([`rgbd::Serial`]).
pub(crate) fn serial(text: &str) -> Result<String, String> {
    rgbd::Serial::parse(text)
        .map(|_| text.to_owned())
        .map_err(|e| e.to_string())
}

/// A number from `lo` to `hi` (both included), finite.
fn within(text: &str, lo: f64, hi: f64, unit: &str) -> Result<f64, String> {
    match text.trim().parse::<f64>() {
        Ok(v) if v.is_finite() && (lo..=hi).contains(&v) => Ok(v),
        _ => Err(format!("{text:?} is not a number from {lo} to {hi}{unit}")),
    }
}

/// The range of one of the measurement's query items, as the server checks it.
fn edge_range(key: &str) -> (f64, f64) {
    EdgeQuery::RANGES
        .iter()
        .find(|(k, ..)| *k == key)
        .map_or((f64::MIN, f64::MAX), |(_, lo, hi)| (*lo, *hi))
}

/// `--min-height-mm`, in the range the server takes.
pub(crate) fn min_height_mm(text: &str) -> Result<f32, String> {
    let (lo, hi) = edge_range("min_height_mm");
    within(text, lo, hi, " mm").map(|v| v as f32)
}

/// `--cluster-mm`, in the range the server takes.
pub(crate) fn cluster_mm(text: &str) -> Result<f32, String> {
    let (lo, hi) = edge_range("cluster_mm");
    within(text, lo, hi, " mm").map(|v| v as f32)
}

/// `--round-up-mm`, in the range the server takes.
pub(crate) fn round_up_mm(text: &str) -> Result<f64, String> {
    let (lo, hi) = edge_range("round_up_mm");
    within(text, lo, hi, " mm")
}

/// `--division-mm`, in the range the server takes.
pub(crate) fn division_mm(text: &str) -> Result<f64, String> {
    let (lo, hi) = edge_range("division_mm");
    within(text, lo, hi, " mm")
}

/// `--volumetric-divisor`, in the range the server takes.
pub(crate) fn volumetric_divisor(text: &str) -> Result<f64, String> {
    let (lo, hi) = edge_range("volumetric_divisor");
    within(text, lo, hi, " cm³ per kg")
}

/// `measure --max-skew-ms`: 0.001 ms (1 µs) to 10 s.
pub(crate) fn max_skew_ms(text: &str) -> Result<f64, String> {
    within(text, 0.001, 10_000.0, " ms")
}

/// A marker's side in metres: 5 mm to 2 m (`calibrate --marker-size`, `markers --size`).
pub(crate) fn marker_metres(text: &str) -> Result<f64, String> {
    within(text, 0.005, 2.0, " m")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn seconds_refuse_in_words_what_duration_would_refuse_in_its_own() {
        assert_eq!(positive_seconds("1.5"), Ok(Duration::from_millis(1500)));
        assert_eq!(seconds_or_zero("0"), Ok(Duration::ZERO));
        for bad in ["0", "-1", "nan", "inf", "1e300", "x", ""] {
            let why = positive_seconds(bad).expect_err(bad);
            assert!(why.contains("not a number of seconds above 0"), "{why}");
            assert!(!why.contains("Duration"), "{why}");
        }
        assert!(seconds_or_zero("-0.5").is_err());
    }

    #[test]
    fn uris_and_groups_are_parsed_as_the_client_will() {
        assert!(coap_uri("coap://127.0.0.1:5683/cams").is_ok());
        for bad in [
            "http://127.0.0.1",
            "127.0.0.1",
            "coap://127.0.0.1:99999",
            "coap://h/%ZZ",
        ] {
            assert!(coap_uri(bad).is_err(), "{bad}");
        }
        assert_eq!(group("224.0.1.187").as_deref(), Ok("coap://224.0.1.187"));
        assert_eq!(group("ff02::fd").as_deref(), Ok("coap://[ff02::fd]"));
        assert!(group("127.0.0.1").is_err());
    }

    #[test]
    fn the_measurements_values_are_the_servers_ranges() {
        assert_eq!(cluster_mm("20"), Ok(20.0));
        for bad in ["0", "0.001", "nan", "-10", "1e9"] {
            assert!(cluster_mm(bad).is_err(), "{bad}");
        }
        assert!(min_height_mm("-10").is_err());
        assert!(round_up_mm("1e9").is_err());
        assert!(marker_metres("-0.16").is_err());
        assert!(serial("840412060746").is_ok());
        assert!(serial("rec-01").is_ok());
        assert!(serial("rec/01").is_err() && serial("-rec").is_err() && serial("").is_err());
    }
}
