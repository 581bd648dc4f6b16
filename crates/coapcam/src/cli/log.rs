//! The log on standard error, in the format of the lines the commands print themselves
//! (`coapcam: serving on ...`, `coapcam: warning: ...`): `coapcam: `, the level as the
//! commands say it (`error: `, `warning: `, nothing for information, `debug: `,
//! `trace: `), then the message with its fields. No time stamp, as none of the commands'
//! own lines has one (the journal adds its own). Before, the log's lines began with a
//! time stamp, the level and the module (issue 51, item 13).

use std::fmt;

use tracing::{Event, Level, Subscriber};
use tracing_subscriber::EnvFilter;
use tracing_subscriber::fmt::format::Writer;
use tracing_subscriber::fmt::{FmtContext, FormatEvent, FormatFields};
use tracing_subscriber::registry::LookupSpan;

/// What is logged when `RUST_LOG` is not set: warnings, and the few changes of state an
/// operator wants to see without asking: registered with a resource directory or its
/// registration removed, connected to the MQTT broker (again) or disconnected from it.
/// The OPC UA library's complaints that the server has no certificate (at the start, and
/// two errors for each connection) are left out: `--opcua` serves security mode None
/// only, where no certificate is used.
pub(crate) const DEFAULT_FILTER: &str = "warn,coap_rd::registrant=info,coapcam::station::mqtt=info,\
     opcua_crypto::certificate_store=off,opcua_core::comms::secure_channel=off,\
     opcua_server::server=error";

/// Starts the log: `RUST_LOG`'s filter, else [`DEFAULT_FILTER`].
pub(crate) fn init() {
    tracing_subscriber::fmt()
        .with_writer(std::io::stderr)
        // Fields in italics on a terminal only: a file or the journal gets plain text.
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .event_format(Line)
        .with_env_filter(
            EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new(DEFAULT_FILTER)),
        )
        .init();
}

/// `coapcam: warning: message field=value ...`.
struct Line;

impl<S, N> FormatEvent<S, N> for Line
where
    S: Subscriber + for<'a> LookupSpan<'a>,
    N: for<'a> FormatFields<'a> + 'static,
{
    fn format_event(
        &self,
        ctx: &FmtContext<'_, S, N>,
        mut writer: Writer<'_>,
        event: &Event<'_>,
    ) -> fmt::Result {
        let level = match *event.metadata().level() {
            Level::ERROR => "error: ",
            Level::WARN => "warning: ",
            Level::INFO => "",
            Level::DEBUG => "debug: ",
            Level::TRACE => "trace: ",
        };
        write!(writer, "coapcam: {level}")?;
        ctx.field_format().format_fields(writer.by_ref(), event)?;
        writeln!(writer)
    }
}
