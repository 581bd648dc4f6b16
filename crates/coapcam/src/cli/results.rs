//! `coapcam results`: a station's results log. `results --server URI` lists the records
//! (`/station/measurements`) and the events beside them (`/station/events`); `results verify FILE` checks a log file's chain and names
//! the first altered record (docs/station.md).

use std::path::PathBuf;

use anyhow::{Context as _, bail};
use clap::{Args, Subcommand};

use coapcam::api::record::{EventRecord, Head, Record};
use coapcam::api::results::{ListQuery, MAX_LIST};
use coapcam::client::{CamClient, results};
use coapcam::report::{Reported, format_mm};
use coapcam::station::signing::{PublicKey, StationKey};
use coapcam::station::{log, postgres};

use super::{Exit, TransmissionArgs, out, outln};

/// Flags of `results`.
#[derive(Debug, Args)]
#[command(args_conflicts_with_subcommands = true, subcommand_negates_reqs = true)]
pub(crate) struct ResultsArgs {
    #[command(subcommand)]
    command: Option<ResultsCommand>,
    /// The station, coap://host[:port] (coaps://, coap+tcp://): list its records, newest first, with the events
    /// (changes of a camera's 3d-transformation or application-config) among them.
    #[arg(long, value_name = "URI", required = true, value_parser = super::values::coap_uri)]
    server: Option<String>,
    /// Only records after this id.
    #[arg(long, value_name = "ID")]
    since: Option<u64>,
    /// Only records before this id (the next page back: the smallest id listed).
    #[arg(long, value_name = "ID")]
    before: Option<u64>,
    /// At most this many records (asked for in pages of up to 1000).
    #[arg(long, value_name = "N", default_value_t = 50, value_parser = clap::value_parser!(u64).range(1..))]
    limit: u64,
    /// Only records with a code of exactly this text (no events then).
    #[arg(long, value_name = "TEXT")]
    code: Option<String>,
    /// One JSON record per line (the record as the station serves it; an event's has
    /// `event`); none, and "no records" on standard error, when nothing matches.
    #[arg(long, conflicts_with = "csv")]
    json: bool,
    /// Comma-separated values with a header line (RFC 4180): id, time, station,
    /// trigger, parcel, length_mm, width_mm, height_mm (the numbers to bill on, with the
    /// decimals of their division), volume_l, volumetric_weight_kg,
    /// volumetric_divisor_cm3_per_kg, codes (`;`-separated), warnings (count), hash.
    /// Measurements only.
    #[arg(long)]
    csv: bool,
    #[command(flatten)]
    transmission: TransmissionArgs,
}

/// `results`' subcommands.
#[derive(Debug, Subcommand)]
enum ResultsCommand {
    /// Check a results log file's chain: every record's SHA-256 over its content, every
    /// link to the record before, every picture kept. Names the first record that was
    /// altered or is missing and exits 7; exits 0 when the whole chain verifies. Ids the
    /// station skipped because a lost log had issued them (gaps it recorded) are named.
    Verify(Box<VerifyArgs>),
    /// Make a station key for `serve --signing-key FILE`: writes its secret half to FILE
    /// (64 hex digits, mode 0600; an existing file is never replaced) and prints the
    /// public half, which `results verify --public-key` takes.
    Keygen(KeygenArgs),
}

/// Flags of `results keygen`.
#[derive(Debug, Args)]
struct KeygenArgs {
    /// Where to write the secret key (outside the results log's folder if you can: a
    /// copy of the log should not carry the key that signs it).
    file: PathBuf,
}

/// Flags of `results verify`.
#[derive(Debug, Args)]
struct VerifyArgs {
    /// The results log (serve's --results; by default results.sqlite in the state
    /// directory).
    file: PathBuf,
    /// A head the station published earlier, ID:HASH (its `/api/log/head`, CoAP
    /// `/station/head` or MQTT `PREFIX/<station>/head`): the log must hold record ID with
    /// that hash, so a log cut off before it or rewritten at or before it fails.
    /// Repeatable.
    #[arg(long, value_name = "ID:HASH", value_parser = head)]
    head: Vec<Head>,
    /// A file of heads, one a line: ID:HASH, or the JSON the station publishes
    /// ({"id":ID,"hash":HASH}, as `mosquitto_sub -t PREFIX/STATION/head` prints it);
    /// blank lines and lines starting with # are skipped.
    #[arg(long, value_name = "FILE")]
    heads: Option<PathBuf>,
    /// The station key's public half (64 hex digits, or a file of keys, one a line; as
    /// `results keygen` printed it and /api/station publishes it): every record must
    /// carry the signature of one of the keys given, so a record without one or with
    /// another fails. Repeatable: a station re-keyed verifies with its old key and its
    /// new, and verify says which key signed which records.
    #[arg(long, value_name = "KEY", value_parser = public_keys)]
    public_key: Vec<PublicKeys>,
    /// Also compare the log with the PostgreSQL table `serve --postgres URL` fills: once
    /// the chain verifies, the table must hold each of the station's records (same ids,
    /// same hashes, bodies that hash to them, arrived in id order) and no other; the first
    /// difference is named (exit status 7). A table that lags names the first record
    /// not yet copied.
    #[arg(long, value_name = "URL")]
    postgres: Option<postgres::Target>,
    /// With --postgres: the station whose rows are compared (the table may hold many);
    /// by default the one named in the log's newest record.
    #[arg(long, value_name = "NAME", requires = "postgres")]
    station: Option<String>,
    /// Print one JSON object.
    #[arg(long)]
    json: bool,
}

fn head(text: &str) -> Result<Head, String> {
    Head::parse(text)
}

/// The keys of one `--public-key`: one, or a file's.
#[derive(Debug, Clone)]
struct PublicKeys(Vec<PublicKey>);

fn public_keys(text: &str) -> Result<PublicKeys, String> {
    PublicKey::parse_all(text).map(PublicKeys)
}

/// The heads of `--heads FILE`.
fn heads_of(file: &std::path::Path) -> anyhow::Result<Vec<Head>> {
    let text = std::fs::read_to_string(file)
        .with_context(|| format!("reading the heads {}", file.display()))?;
    let mut out = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let head = Head::parse(line)
            .map_err(|why| anyhow::anyhow!("{} line {}: {why}", file.display(), n + 1))?;
        out.push(head);
    }
    Ok(out)
}

/// Runs `results keygen`: a new station key in its file, its public key printed.
fn keygen(k: &KeygenArgs) -> anyhow::Result<Exit> {
    let key = StationKey::generate(&k.file).map_err(anyhow::Error::msg)?;
    outln!("{}", key.public());
    eprintln!(
        "coapcam: the station key is in {}; its public key (above) checks the records: results verify LOG --public-key {}",
        k.file.display(),
        key.public()
    );
    Ok(Exit::Success)
}

/// Runs `results`.
pub(crate) async fn run(args: ResultsArgs) -> anyhow::Result<Exit> {
    match &args.command {
        Some(ResultsCommand::Verify(v)) => return verify(v).await,
        Some(ResultsCommand::Keygen(k)) => return keygen(k),
        None => {}
    }
    let Some(server) = &args.server else {
        bail!("give --server URI to list a station's records, or `results verify FILE`");
    };
    let client = CamClient::connect(
        server,
        args.transmission.endpoint_config(),
        args.transmission.psk().as_ref(),
        args.transmission.timeout(),
    )
    .await?;
    let query = ListQuery {
        since: args.since,
        before: args.before,
        limit: MAX_LIST,
        code: args.code.clone(),
        ..ListQuery::default()
    };
    let limit = usize::try_from(args.limit).unwrap_or(usize::MAX);
    let records = results::list(&client, &query, limit).await?;
    // The events beside them: those among the ids the list spans (back to the oldest
    // record listed when the list is cut at --limit). A code selects measurements only,
    // and the CSV's columns are a measurement's.
    let events = if args.code.is_some() || args.csv {
        Vec::new()
    } else {
        let oldest = records.last().map(|r| r.id.saturating_sub(1));
        let since = match oldest {
            Some(oldest) if records.len() == limit => Some(oldest.max(args.since.unwrap_or(0))),
            _ => args.since,
        };
        let range = ListQuery {
            since,
            before: args.before,
            ..ListQuery::default()
        };
        results::events(&client, &range, limit).await?
    };
    if args.csv {
        outln!("{}", CSV_HEADER.join(","));
    }
    let nothing = records.is_empty() && events.is_empty();
    let mut events = events.iter().peekable();
    for record in &records {
        while let Some(event) = events.next_if(|e| e.id > record.id) {
            print_event(event, args.json)?;
        }
        if args.json {
            outln!("{}", serde_json::to_string(record)?);
        } else if args.csv {
            outln!("{}", csv_row(record));
        } else {
            outln!("{}", text(record));
        }
    }
    for event in events {
        print_event(event, args.json)?;
    }
    if nothing {
        if args.json || args.csv {
            // Said aside: what standard output holds stays JSON Lines (none) or the CSV
            // header alone, which a reader takes as it is.
            eprintln!("coapcam: no records");
        } else {
            outln!("no records");
        }
    }
    Ok(Exit::Success)
}

async fn verify(args: &VerifyArgs) -> anyhow::Result<Exit> {
    let file = &args.file;
    let mut heads = args.head.clone();
    if let Some(list) = &args.heads {
        heads.extend(heads_of(list)?);
    }
    let mut keys: Vec<PublicKey> = Vec::new();
    for key in args.public_key.iter().flat_map(|k| &k.0) {
        if !keys.contains(key) {
            keys.push(*key);
        }
    }
    let report = log::verify_against(file, &heads, &keys)
        .with_context(|| format!("verifying {}", file.display()))?;
    let table = match &args.postgres {
        Some(target) if report.first_altered.is_none() => {
            Some(compare_table(file, target, args.station.as_deref()).await?)
        }
        _ => None,
    };
    let differs = table.as_ref().is_some_and(|t| t.first_difference.is_some());
    if args.json {
        outln!("{}", verify_document(args, &report, &keys, table.as_ref()));
    } else {
        print_verified(args, &report, &heads, &keys, table.as_ref())?;
    }
    Ok(if report.first_altered.is_none() && !differs {
        Exit::Success
    } else {
        Exit::Altered
    })
}

/// `results verify --json`'s document: what `report` found, and the table's comparison.
fn verify_document(
    args: &VerifyArgs,
    report: &log::VerifyReport,
    keys: &[PublicKey],
    table: Option<&postgres::TableReport>,
) -> serde_json::Value {
    let file = &args.file;
    let mut doc = serde_json::json!({
        "file": file.display().to_string(),
        "verified": report.first_altered.is_none(),
        "records": report.records,
        "events": report.events,
        "pictures_checked": report.pictures_checked,
        "pictures_pruned": report.pictures_pruned,
        "heads_checked": report.heads_checked,
        "signatures_checked": report.signatures_checked,
    });
    if !keys.is_empty() {
        doc["signed"] = report
            .signed
            .iter()
            .map(|r| serde_json::json!({ "key": r.key.to_string(), "from": r.from, "to": r.to }))
            .collect();
    }
    if let Some((id, hash)) = &report.head {
        doc["head"] = serde_json::json!({ "id": id, "hash": hash });
    }
    if let Some(a) = &report.first_altered {
        doc["first_altered"] = serde_json::json!({ "id": a.id, "why": a.why });
    }
    if let (Some(target), Some(t)) = (&args.postgres, table) {
        doc["postgres"] = serde_json::json!({
            "url": target.to_string(),
            "station": t.station,
            "verified": t.first_difference.is_none(),
            "rows": t.rows,
        });
        if let Some((id, why)) = &t.first_difference {
            doc["postgres"]["first_difference"] = serde_json::json!({ "id": id, "why": why });
        }
    }
    doc["clock_jumps"] = report
        .clock_jumps
        .iter()
        .map(|(id, j)| {
            serde_json::json!({
                "id": id, "jump": j.jump, "previous": j.previous, "now": j.now,
                "monotonic_elapsed_ms": j.monotonic_elapsed_ms,
            })
        })
        .collect();
    doc["gaps"] = report
        .gaps
        .iter()
        .map(|g| {
            serde_json::json!({
                "from": g.from, "to": g.to, "last_hash": g.last_hash, "time": g.time,
                "note": g.note,
            })
        })
        .collect();
    doc
}

/// What `results verify` prints without --json: the gaps and clock jumps, which key
/// signed which records, whether the chain verifies, and the table's comparison.
fn print_verified(
    args: &VerifyArgs,
    report: &log::VerifyReport,
    heads: &[Head],
    keys: &[PublicKey],
    table: Option<&postgres::TableReport>,
) -> anyhow::Result<()> {
    let file = &args.file;
    for gap in &report.gaps {
        outln!("{}: {gap}", file.display());
    }
    for (id, jump) in &report.clock_jumps {
        outln!("{}: record {id}: {jump}", file.display());
    }
    // Which key signed which records, with several keys given (one key signs all).
    if keys.len() > 1 {
        for run in &report.signed {
            outln!("{}: {run}", file.display());
        }
    }
    match &report.first_altered {
        None => out!(
            "{}: the chain verifies: {} record(s) ({} event(s)){}, {} picture(s) checked, {} pruned{}{}\n",
            file.display(),
            report.records,
            report.events,
            report
                .head
                .as_ref()
                .map(|(id, hash)| format!(", newest #{id} with hash {hash}"))
                .unwrap_or_default(),
            report.pictures_checked,
            report.pictures_pruned,
            if heads.is_empty() {
                String::new()
            } else {
                format!(", {} head(s) published earlier held", report.heads_checked)
            },
            if !keys.is_empty() {
                format!(", {} signature(s) checked", report.signatures_checked)
            } else {
                String::new()
            },
        ),
        // The reason names the record (altered, missing, or where the file breaks).
        Some(a) => out!(
            "{}: {}\n({} record(s) before it verify)\n",
            file.display(),
            a.why,
            report.records
        ),
    }
    if let (Some(target), Some(t)) = (&args.postgres, table) {
        match &t.first_difference {
            None => outln!(
                "{target}: table {} holds the same {} record(s) of station {} as the log, in order",
                postgres::TABLE,
                t.rows,
                t.station
            ),
            Some((_, why)) => outln!(
                "{target}: station {}: {why}\n({} record(s) before it match)",
                t.station,
                t.rows
            ),
        }
    }
    Ok(())
}

/// The table at `target` compared with the log `file`'s measurements of `station` (by
/// default the station of the newest one).
async fn compare_table(
    file: &std::path::Path,
    target: &postgres::Target,
    station: Option<&str>,
) -> anyhow::Result<postgres::TableReport> {
    let logged = log::measurement_hashes(file)
        .with_context(|| format!("reading the records of {}", file.display()))?;
    let station = match station {
        Some(name) => name.to_owned(),
        None => match logged.last() {
            Some((_, name, _)) => name.clone(),
            None => bail!(
                "{} holds no record, so it names no station: give --station NAME",
                file.display()
            ),
        },
    };
    let records: Vec<(u64, String)> = logged
        .into_iter()
        .filter(|(_, name, _)| *name == station)
        .map(|(id, _, hash)| (id, hash))
        .collect();
    Ok(postgres::compare(target, &station, &records).await?)
}

/// An event's line: its JSON, or text.
fn print_event(event: &EventRecord, json: bool) -> anyhow::Result<()> {
    if json {
        outln!("{}", serde_json::to_string(event)?);
    } else {
        outln!("{}", event_text(event));
    }
    Ok(())
}

/// One line of text for an event.
fn event_text(r: &EventRecord) -> String {
    let e = &r.event;
    format!(
        "#{:<5} {}  {}  event {}  {} {} by {}  sha256 {} -> {}  parameters {}",
        r.id,
        r.time,
        r.station,
        r.counter,
        e.change.method(),
        e.document,
        e.by,
        short(&e.old_sha256),
        short(&e.new_sha256),
        short(&e.parameters_sha256),
    )
}

/// The first 12 hex digits of a SHA-256.
fn short(hash: &str) -> &str {
    hash.get(..12).unwrap_or(hash)
}

/// One line of text for a record.
fn text(r: &Record) -> String {
    let m = &r.measurement;
    let parcel = match m.reported() {
        Some(p) => format!(
            "{}  {:.2} l  {:.2} kg (divisor {})",
            p.dimensions_text(),
            p.volume_l,
            p.volumetric_weight_kg,
            p.volumetric_divisor_cm3_per_kg
        ),
        None => "nothing on the table".to_owned(),
    };
    let codes = r.code_texts();
    let mut line = format!(
        "#{:<5} {}  {}  {:<7}  {parcel}",
        r.id,
        r.time,
        r.station,
        r.trigger.name()
    );
    if !codes.is_empty() {
        line += &format!("  codes: {}", codes.join(", "));
    }
    let warnings = m.warnings.len();
    if warnings > 0 {
        line += &format!("  ({warnings} warning(s))");
    }
    if let Some(parameters) = &r.parameters_sha256 {
        line += &format!(
            "  parameters {} after event {}",
            short(parameters),
            r.events.unwrap_or(0)
        );
    }
    line
}

const CSV_HEADER: [&str; 14] = [
    "id",
    "time",
    "station",
    "trigger",
    "parcel",
    "length_mm",
    "width_mm",
    "height_mm",
    "volume_l",
    "volumetric_weight_kg",
    "volumetric_divisor_cm3_per_kg",
    "codes",
    "warnings",
    "hash",
];

/// A record's CSV row, in [`CSV_HEADER`]'s order.
fn csv_row(r: &Record) -> String {
    let m = &r.measurement;
    let p = m.reported();
    let number = |f: fn(&Reported) -> f64| p.map(|p| f(p).to_string()).unwrap_or_default();
    let dimension = |f: fn(&Reported) -> f64| {
        p.map(|p| format_mm(f(p), p.division_mm))
            .unwrap_or_default()
    };
    let fields = [
        r.id.to_string(),
        r.time.to_string(),
        r.station.clone(),
        r.trigger.name().to_owned(),
        if p.is_some() { "measured" } else { "nothing" }.to_owned(),
        dimension(|p| p.length_mm),
        dimension(|p| p.width_mm),
        dimension(|p| p.height_mm),
        number(|p| p.volume_l),
        number(|p| p.volumetric_weight_kg),
        number(|p| p.volumetric_divisor_cm3_per_kg),
        r.code_texts().join(";"),
        m.warnings.len().to_string(),
        r.hash.clone(),
    ];
    fields.map(|f| csv_field(&f)).join(",")
}

/// A CSV field, quoted when it holds a comma, a quote or a line break (RFC 4180).
fn csv_field(text: &str) -> String {
    if text.contains([',', '"', '\n', '\r']) {
        format!("\"{}\"", text.replace('"', "\"\""))
    } else {
        text.to_owned()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn csv_fields_are_quoted_only_when_needed() {
        assert_eq!(csv_field("PKG-1"), "PKG-1");
        assert_eq!(csv_field("a,b"), "\"a,b\"");
        assert_eq!(csv_field("say \"hi\""), "\"say \"\"hi\"\"\"");
    }
}
