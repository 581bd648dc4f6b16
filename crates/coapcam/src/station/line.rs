//! A plain text line per measurement on TCP (`serve --line-output tcp://ADDR:PORT`), for
//! systems that read a socket or a serial line: every reader connected gets a line for
//! each measurement recorded while it is connected,
//!
//! ```text
//! id,time,length_mm,width_mm,height_mm,kg,code\r\n
//! ```
//!
//! ([`format_line`] says each field exactly). A reader that does not keep up, or that is
//! gone, never holds up the station: each has a queue of [`QUEUE_LINES`] lines, and one
//! whose queue is full, or that takes no bytes for [`WRITE_TIMEOUT`], is disconnected
//! with a log line. No address holds more than [`MAX_PER_ADDRESS`] of the
//! [`MAX_READERS`] places, and when all are taken a new reader takes the oldest place of
//! the address that holds the most: idle connections from elsewhere cannot lock the
//! plant's reader out.

use std::io;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};

use tokio::io::AsyncWriteExt as _;
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::mpsc;
use tokio::task::JoinHandle;

use super::follow::{self, Feed, Next, Output, OutputId, Sink, Start};
use super::log::ResultsLog;
use crate::api::record::Record;
use crate::report::format_mm;

/// The line output's address could not be listened on.
#[derive(Debug, thiserror::Error)]
#[error("listening for line output readers on {addr}")]
pub struct ListenError {
    /// The address.
    pub addr: SocketAddr,
    /// Why.
    pub source: io::Error,
}

/// The flag of the line output (`serve --line-output`).
#[derive(Debug, Clone, Default, clap::Args)]
#[group(skip)]
pub struct Args {
    /// Serve one text line per measurement (id,time,length_mm,width_mm,height_mm,kg,code
    /// and CR LF; docs/station.md) to every reader connected to this TCP address. A
    /// reader that falls 256 lines behind is disconnected.
    #[arg(long, value_name = "tcp://ADDR:PORT", value_parser = parse_tcp_uri)]
    line_output: Option<SocketAddr>,
}

impl Args {
    /// Whether `--line-output` is given.
    pub(super) fn configured(&self) -> bool {
        self.line_output.is_some()
    }

    /// The line output `--line-output` asks for, listening (it keeps no
    /// cursor: its id only tells it apart).
    pub(super) async fn start(
        &self,
        feed: &Feed<'_>,
        _id: &OutputId,
    ) -> Result<Option<Box<dyn Output>>, ListenError> {
        let Some(addr) = self.line_output else {
            return Ok(None);
        };
        let output = LineOutput::start(addr, feed.log.clone())
            .await
            .map_err(|source| ListenError { addr, source })?;
        Ok(Some(Box::new(output)))
    }
}

/// The address of `tcp://ADDR:PORT` (`serve --line-output`; an IPv6 address in brackets).
pub fn parse_tcp_uri(uri: &str) -> Result<SocketAddr, String> {
    uri.strip_prefix("tcp://")
        .and_then(|a| a.trim_end_matches('/').parse().ok())
        .ok_or_else(|| {
            format!("{uri:?} is not tcp://ADDR:PORT (e.g. tcp://0.0.0.0:4001 or tcp://[::]:4001)")
        })
}

/// Lines a reader may be behind before it is disconnected.
pub const QUEUE_LINES: usize = 256;
/// Readers served at once.
pub const MAX_READERS: usize = 64;
/// Readers of one IP address at once; one more is refused (closed at once, with a log
/// line).
pub const MAX_PER_ADDRESS: usize = 4;
/// How long a line may take to be written to a reader before it is disconnected.
pub const WRITE_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(10);

/// The fields of a line, in order (the first line of the documentation's example).
pub const HEADER: &str = "id,time,length_mm,width_mm,height_mm,kg,code";

/// One measurement as a line's fields.
#[derive(Debug, Clone, PartialEq)]
pub struct LineFields {
    /// The record's id in the results log.
    pub id: u64,
    /// UTC time of the measurement, RFC 3339 (e.g. `2026-11-27T09:41:07.250Z`).
    pub time: String,
    /// Length, width and height as billed, mm; `None` when nothing was measured.
    pub dimensions_mm: Option<[f64; 3]>,
    /// The division they were rounded to (`None` in records made before it was given).
    pub division_mm: Option<f64>,
    /// The volumetric weight, kg; `None` when nothing was measured.
    pub volumetric_weight_kg: Option<f64>,
    /// The first code read, if any.
    pub code: Option<String>,
}

impl LineFields {
    /// The fields of a recorded measurement.
    pub fn of(record: &Record) -> Self {
        let reported = record.measurement.reported();
        Self {
            id: record.id,
            time: record.time.to_string(),
            dimensions_mm: reported.map(|r| [r.length_mm, r.width_mm, r.height_mm]),
            division_mm: reported.and_then(|r| r.division_mm),
            volumetric_weight_kg: reported.map(|r| r.volumetric_weight_kg),
            code: record.code_texts().into_iter().next(),
        }
    }
}

/// The line of a measurement, with its `\r\n`:
/// - `id`: decimal; `time`: as recorded (RFC 3339, UTC, `Z`);
/// - `length_mm`, `width_mm`, `height_mm`: the numbers to bill on, with the decimals of
///   their division ([`format_mm`]: `400` at 5 mm; one decimal in records made before the
///   division); `kg`: the volumetric weight, three decimals (`4.800`); all four empty
///   when nothing was measured;
/// - `code`: the text of the first code read, empty when none was. It is written between
///   double quotes when it holds a comma, a double quote, or starts or ends with a space,
///   each double quote inside doubled (RFC 4180); a control character in it (below U+0020,
///   and U+007F) is written as a space, so that a line is always one line.
pub fn format_line(f: &LineFields) -> String {
    let dims = f.dimensions_mm.map_or_else(
        || ",,".to_owned(),
        |dims| dims.map(|v| format_mm(v, f.division_mm)).join(","),
    );
    let kg = f
        .volumetric_weight_kg
        .map_or_else(String::new, |kg| format!("{kg:.3}"));
    let code = f.code.as_deref().map_or_else(String::new, quote);
    format!("{},{},{dims},{kg},{code}\r\n", f.id, f.time)
}

/// The code field: controls as spaces, quoted when needed (RFC 4180).
fn quote(text: &str) -> String {
    let clean: String = text
        .chars()
        .map(|c| {
            if c.is_control() && (c as u32) < 0x80 {
                ' '
            } else {
                c
            }
        })
        .collect();
    if clean.contains([',', '"']) || clean.starts_with(' ') || clean.ends_with(' ') {
        format!("\"{}\"", clean.replace('"', "\"\""))
    } else {
        clean
    }
}

/// The line output of a results log: a [`LineServer`] and the task that hands it a line
/// for each record appended from now on. Dropping it stops both.
pub struct LineOutput {
    server: Arc<LineServer>,
    follow: JoinHandle<()>,
}

impl LineOutput {
    /// Listens on `addr` and follows `log`.
    pub async fn start(addr: SocketAddr, log: ResultsLog) -> io::Result<Self> {
        let server = Arc::new(LineServer::bind(addr).await?);
        let follow = tokio::spawn(follow::run(log, Lines(server.clone())));
        Ok(Self { server, follow })
    }

    /// The address it listens on.
    pub fn local_addr(&self) -> SocketAddr {
        self.server.local_addr()
    }

    /// How many readers are connected.
    pub fn readers(&self) -> usize {
        self.server.readers()
    }
}

impl Output for LineOutput {
    fn describe(&self) -> String {
        format!("line output on {}", self.local_addr())
    }
}

impl Drop for LineOutput {
    fn drop(&mut self) {
        self.follow.abort();
    }
}

/// The line output as a [`Sink`]: a line to every reader for each record appended.
struct Lines(Arc<LineServer>);

impl Sink for Lines {
    type Event = std::convert::Infallible;

    fn name(&self) -> String {
        format!("line output on {}", self.0.local_addr())
    }

    fn start(&self) -> Start {
        Start::Newest
    }

    async fn deliver(&mut self, record: &Record) -> Next {
        self.0.send(&format_line(&LineFields::of(record)));
        Next::Go
    }

    async fn handle(&mut self, event: Self::Event) -> Next {
        match event {}
    }
}

type Readers = Arc<Mutex<Vec<Reader>>>;

struct Reader {
    peer: SocketAddr,
    lines: mpsc::Sender<Arc<str>>,
}

/// The listening socket and its readers; dropping it closes every connection.
pub struct LineServer {
    addr: SocketAddr,
    readers: Readers,
    accept: JoinHandle<()>,
}

impl LineServer {
    /// Listens on `addr` (port 0 picks a free one).
    pub async fn bind(addr: SocketAddr) -> io::Result<Self> {
        let listener = TcpListener::bind(addr).await?;
        let addr = listener.local_addr()?;
        let readers: Readers = Arc::default();
        let accept = tokio::spawn(accept(listener, readers.clone()));
        Ok(Self {
            addr,
            readers,
            accept,
        })
    }

    /// The address it listens on.
    pub fn local_addr(&self) -> SocketAddr {
        self.addr
    }

    /// How many readers are connected.
    pub fn readers(&self) -> usize {
        let mut list = lock(&self.readers);
        list.retain(|r| !r.lines.is_closed());
        list.len()
    }

    /// Queues `line` to every reader; never waits. A reader whose queue is full is
    /// disconnected (logged), one that is gone is forgotten.
    pub fn send(&self, line: &str) {
        let line: Arc<str> = Arc::from(line);
        lock(&self.readers).retain(|r| match r.lines.try_send(line.clone()) {
            Ok(()) => true,
            Err(mpsc::error::TrySendError::Full(_)) => {
                tracing::warn!(reader = %r.peer, "line output: reader {QUEUE_LINES} lines behind, disconnected");
                false
            }
            Err(mpsc::error::TrySendError::Closed(_)) => {
                tracing::info!(reader = %r.peer, "line output: reader gone");
                false
            }
        });
    }
}

impl Drop for LineServer {
    fn drop(&mut self) {
        self.accept.abort();
        lock(&self.readers).clear();
    }
}

fn lock(readers: &Readers) -> std::sync::MutexGuard<'_, Vec<Reader>> {
    // A panic elsewhere while holding it leaves a list that is still whole.
    readers
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
}

async fn accept(listener: TcpListener, readers: Readers) {
    loop {
        let (stream, peer) = match listener.accept().await {
            Ok(s) => s,
            Err(e) => {
                // Out of descriptors and the like: pause rather than spin.
                tracing::warn!(error = %e, "line output: accepting a reader failed");
                tokio::time::sleep(std::time::Duration::from_millis(100)).await;
                continue;
            }
        };
        let mut list = lock(&readers);
        list.retain(|r| !r.lines.is_closed());
        let of = |list: &[Reader], ip| list.iter().filter(|r| r.peer.ip() == ip).count();
        if of(&list, peer.ip()) >= MAX_PER_ADDRESS {
            tracing::warn!(reader = %peer, "line output: {MAX_PER_ADDRESS} readers from this address already, refused");
            continue;
        }
        if list.len() >= MAX_READERS {
            // The oldest reader of the address with the most (the list is in the order
            // they came); dropping its queue ends its connection.
            let mut most: Option<(usize, std::net::IpAddr)> = None;
            for r in list.iter() {
                let n = of(&list, r.peer.ip());
                if most.is_none_or(|(m, _)| n > m) {
                    most = Some((n, r.peer.ip()));
                }
            }
            if let Some(i) = most.and_then(|(_, ip)| list.iter().position(|r| r.peer.ip() == ip)) {
                let gone = list.remove(i);
                tracing::warn!(reader = %gone.peer, "line output: {MAX_READERS} readers, the oldest of the address with the most disconnected for {peer}");
            }
        }
        let (tx, rx) = mpsc::channel(QUEUE_LINES);
        list.push(Reader { peer, lines: tx });
        drop(list);
        tracing::info!(reader = %peer, "line output: reader connected");
        tokio::spawn(write(stream, peer, rx));
    }
}

/// Writes a reader's lines until its queue is dropped (disconnected) or it is gone.
async fn write(mut stream: TcpStream, peer: SocketAddr, mut lines: mpsc::Receiver<Arc<str>>) {
    let _ = stream.set_nodelay(true);
    let (mut read, mut write) = stream.split();
    let mut sink = [0u8; 256];
    loop {
        tokio::select! {
            line = lines.recv() => {
                let Some(line) = line else { return };
                match tokio::time::timeout(WRITE_TIMEOUT, write.write_all(line.as_bytes())).await {
                    Ok(Ok(())) => {}
                    Ok(Err(e)) => {
                        tracing::info!(reader = %peer, error = %e, "line output: reader gone");
                        return;
                    }
                    Err(_) => {
                        tracing::warn!(reader = %peer, "line output: a line took over {WRITE_TIMEOUT:?} to write, reader disconnected");
                        return;
                    }
                }
            }
            // What a reader sends is ignored; its end (0 bytes or an error) ends it.
            n = tokio::io::AsyncReadExt::read(&mut read, &mut sink) => {
                if !matches!(n, Ok(n) if n > 0) {
                    tracing::info!(reader = %peer, "line output: reader closed the connection");
                    return;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tcp_uris() {
        assert_eq!(
            parse_tcp_uri("tcp://127.0.0.1:4001"),
            Ok(SocketAddr::from(([127, 0, 0, 1], 4001)))
        );
        assert_eq!(
            parse_tcp_uri("tcp://[::]:0"),
            Ok(SocketAddr::from(([0u16; 8], 0)))
        );
        for bad in [
            "127.0.0.1:4001",
            "tcp://host:4001",
            "tcp://1.2.3.4",
            "udp://1.2.3.4:5",
        ] {
            assert!(parse_tcp_uri(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn lines() {
        let mut f = LineFields {
            id: 12,
            time: "2026-11-27T09:41:07.250Z".into(),
            dimensions_mm: Some([400.04, 300.0, 199.96]),
            division_mm: None,
            volumetric_weight_kg: Some(4.8),
            code: Some("PKG-0001".into()),
        };
        assert_eq!(
            format_line(&f),
            "12,2026-11-27T09:41:07.250Z,400.0,300.0,200.0,4.800,PKG-0001\r\n"
        );
        f.code = Some("A,\"B\"\r\nC".into());
        assert_eq!(
            format_line(&f),
            "12,2026-11-27T09:41:07.250Z,400.0,300.0,200.0,4.800,\"A,\"\"B\"\"  C\"\r\n"
        );
        f.code = Some(" x".into());
        assert!(format_line(&f).ends_with(",\" x\"\r\n"));
        f.dimensions_mm = None;
        f.volumetric_weight_kg = None;
        f.code = None;
        assert_eq!(format_line(&f), "12,2026-11-27T09:41:07.250Z,,,,,\r\n");
    }

    /// Issue 51, item 4: the line gave 320.2 where the record's parcel was billed at 320
    /// (its 5 mm division); it gives the numbers to bill on, as the record and its
    /// `parcels` do, written as the division has them.
    #[test]
    fn a_line_gives_the_numbers_to_bill_on() {
        let record = crate::api::record::tests::billed_record();
        let m = &record.measurement;
        let line = format_line(&LineFields::of(&record));
        let fields: Vec<&str> = line.trim_end().split(',').collect();
        assert_eq!(fields[2..5], ["325", "240", "100"], "{line:?}");
        let parcel = &m.parcels[0];
        let billed = [parcel.length_mm, parcel.width_mm, parcel.height_mm]
            .map(|v| format_mm(v.expect("measured"), Some(5.0)));
        assert_eq!(fields[2..5], billed, "{line:?}");
        assert_eq!(fields[5], "1.560", "{line:?}");
    }

    async fn wait_for_readers(server: &LineServer, n: usize) {
        for _ in 0..1000 {
            if server.readers() == n {
                return;
            }
            tokio::time::sleep(std::time::Duration::from_millis(5)).await;
        }
        panic!("{} readers, {n} expected", server.readers());
    }

    #[tokio::test]
    async fn every_reader_gets_every_line_and_a_stalled_one_is_dropped() {
        use tokio::io::AsyncBufReadExt as _;
        let server = LineServer::bind(SocketAddr::from(([127, 0, 0, 1], 0)))
            .await
            .unwrap();
        let mut a =
            tokio::io::BufReader::new(TcpStream::connect(server.local_addr()).await.unwrap());
        let mut b =
            tokio::io::BufReader::new(TcpStream::connect(server.local_addr()).await.unwrap());
        wait_for_readers(&server, 2).await;
        for n in 0..3 {
            server.send(&format!("{n},x\r\n"));
        }
        for reader in [&mut a, &mut b] {
            for n in 0..3 {
                let mut line = String::new();
                reader.read_line(&mut line).await.unwrap();
                assert_eq!(line, format!("{n},x\r\n"));
            }
        }
        // b goes away; a stops reading: b is forgotten, a is dropped once its socket
        // buffers and its queue are full, and sending never waits for either.
        drop(b);
        let line = format!("{}\r\n", "y".repeat(1000));
        let mut sent = 0;
        while server.readers() > 0 {
            assert!(sent < 1_000_000, "the stalled reader was never dropped");
            server.send(&line);
            sent += 1;
            if sent % 64 == 0 {
                tokio::time::sleep(std::time::Duration::from_millis(1)).await;
            }
        }
        drop(a);
    }

    /// A reader connected from `ip` (a loopback address: every 127.x.y.z is this host's).
    async fn reader_from(server: &LineServer, ip: [u8; 4]) -> tokio::io::BufReader<TcpStream> {
        let socket = tokio::net::TcpSocket::new_v4().unwrap();
        socket.bind(SocketAddr::from((ip, 0))).unwrap();
        tokio::io::BufReader::new(socket.connect(server.local_addr()).await.unwrap())
    }

    /// Whether the server closed `reader` (end of stream within a short wait).
    async fn closed(reader: &mut tokio::io::BufReader<TcpStream>) -> bool {
        use tokio::io::AsyncBufReadExt as _;
        let mut line = String::new();
        let read = tokio::time::timeout(
            std::time::Duration::from_millis(500),
            reader.read_line(&mut line),
        );
        matches!(read.await, Ok(Ok(0)))
    }

    #[tokio::test]
    async fn idle_readers_from_elsewhere_never_lock_the_plants_reader_out() {
        use tokio::io::AsyncBufReadExt as _;
        let server = LineServer::bind(SocketAddr::from(([127, 0, 0, 1], 0)))
            .await
            .unwrap();
        // One address holds at most MAX_PER_ADDRESS places: the next is closed at once.
        let mut own = Vec::new();
        for _ in 0..MAX_PER_ADDRESS {
            own.push(reader_from(&server, [127, 0, 0, 2]).await);
        }
        wait_for_readers(&server, MAX_PER_ADDRESS).await;
        let mut extra = reader_from(&server, [127, 0, 0, 2]).await;
        assert!(
            closed(&mut extra).await,
            "a fifth reader of one address was kept"
        );
        // Idle readers from many addresses fill every place...
        let mut idle = Vec::new();
        for n in 0..(MAX_READERS / MAX_PER_ADDRESS - 1) {
            let ip = [127, 0, 1, u8::try_from(n).unwrap()];
            for _ in 0..MAX_PER_ADDRESS {
                idle.push(reader_from(&server, ip).await);
            }
        }
        wait_for_readers(&server, MAX_READERS).await;
        // ...and the plant's reader still gets in, and gets the next line.
        let mut plant = reader_from(&server, [127, 0, 2, 1]).await;
        assert!(
            closed(&mut own[0]).await,
            "the oldest place of 127.0.0.2 was kept"
        );
        wait_for_readers(&server, MAX_READERS).await;
        server.send("7,x\r\n");
        let mut line = String::new();
        plant.read_line(&mut line).await.unwrap();
        assert_eq!(line, "7,x\r\n");
    }

    #[tokio::test(start_paused = true)]
    async fn a_reader_that_takes_no_bytes_is_disconnected_after_the_write_timeout() {
        let server = LineServer::bind(SocketAddr::from(([127, 0, 0, 1], 0)))
            .await
            .unwrap();
        let socket = tokio::net::TcpSocket::new_v4().unwrap();
        socket.set_recv_buffer_size(4096).unwrap();
        let stalled = socket.connect(server.local_addr()).await.unwrap();
        wait_for_readers(&server, 1).await;
        // Lines past what the sockets' buffers hold (the queue keeps the rest), then time
        // runs on with nothing read: the reader is dropped though its queue is not full.
        let line = format!("{}\r\n", "y".repeat(64 * 1024));
        for _ in 0..QUEUE_LINES / 2 {
            server.send(&line);
            tokio::task::yield_now().await;
        }
        tokio::time::sleep(WRITE_TIMEOUT * 2).await;
        wait_for_readers(&server, 0).await;
        drop(stalled);
    }
}
