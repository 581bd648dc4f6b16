//! `serve --static DIR`: the regular files of a directory at `/files/<name>`, read from
//! disk block by block as clients ask for them, so a server of large files holds none of
//! them in memory.

use std::collections::{HashMap, HashSet};
use std::fs;
use std::hash::Hasher as _;
use std::io::{self, Read as _, Seek as _, SeekFrom, Write as _};
use std::ops::Range;
use std::os::unix::fs::MetadataExt as _;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError, RwLock};
use std::time::SystemTime;

use bytes::Bytes;
use coap::{BlockSource, Code, ContentFormat, IncomingRequest, OptionNumber, Response};
use coap_net::router::check_preconditions;
use coap_net::{Ctx, Resource, Router, handler};
use tokio::sync::mpsc;

use super::error::StartError;

/// Bytes read from a file at a time: one read serves 64 blocks of 1024 bytes.
const WINDOW: usize = 64 << 10;

/// What the server knows of a file: enough to tell when it changes, not its content.
/// The inode, length, and modification and change times: a write in place moves the
/// times (the change time even for tools that restore the modification time, `cp -p`,
/// `touch -r`), a replacement changes the inode.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Stamp {
    device: u64,
    inode: u64,
    len: u64,
    modified: Option<SystemTime>,
    changed: (i64, i64),
}

impl Stamp {
    fn of(meta: &fs::Metadata) -> Self {
        Self {
            device: meta.dev(),
            inode: meta.ino(),
            len: meta.len(),
            modified: meta.modified().ok(),
            changed: (meta.ctime(), meta.ctime_nsec()),
        }
    }
}

#[derive(Clone, Copy)]
struct File {
    stamp: Stamp,
    /// A hash of the content, computed when the file was (re)read.
    etag: [u8; 8],
}

/// The files of a directory, rescanned when they change on disk, and (with --writable)
/// changed by clients.
#[derive(Clone)]
pub(crate) struct StaticFiles {
    dir: PathBuf,
    files: Arc<RwLock<HashMap<String, File>>>,
    writable: bool,
    /// With `writable`: the most bytes the served files may be charged together
    /// ([`charge`]).
    quota: Option<u64>,
    /// Held through a client's write, from the quota check to the new file's record.
    writes: Arc<Mutex<()>>,
    /// Paths changed by clients, for notifications.
    changed: mpsc::UnboundedSender<String>,
    /// Set when the server stops: a rescan under way ends at its next window.
    stopped: Arc<AtomicBool>,
}

impl StaticFiles {
    pub(crate) fn load(
        dir: &Path,
        router: &Router,
        writable: bool,
        quota: Option<u64>,
        changed: mpsc::UnboundedSender<String>,
    ) -> Result<Self, StartError> {
        if !dir.is_dir() {
            return Err(StartError::NotADirectory(dir.to_owned()));
        }
        let me = Self {
            dir: dir.to_path_buf(),
            files: Arc::default(),
            writable,
            quota,
            writes: Arc::default(),
            changed,
            stopped: Arc::default(),
        };
        me.rescan(router);
        if writable {
            // Names that do not exist yet: PUT creates them; POST /files picks a name.
            router.add("/files/{name}", me.resource(None));
            router.add(
                "/files",
                me.resource(None).attr("title", "POST creates a file"),
            );
        }
        Ok(me)
    }

    fn read(&self) -> std::sync::RwLockReadGuard<'_, HashMap<String, File>> {
        self.files.read().unwrap_or_else(PoisonError::into_inner)
    }

    fn write(&self) -> std::sync::RwLockWriteGuard<'_, HashMap<String, File>> {
        self.files.write().unwrap_or_else(PoisonError::into_inner)
    }

    /// Ends a rescan under way (on another thread) at its next window; later rescans
    /// hash nothing.
    pub(crate) fn stop(&self) {
        self.stopped.store(true, Ordering::Relaxed);
    }

    /// Hashes new and changed files, drops vanished ones, keeps the router in step, and
    /// returns the paths whose content changed on disk.
    pub(crate) fn rescan(&self, router: &Router) -> Vec<String> {
        let mut changed = Vec::new();
        let Ok(entries) = fs::read_dir(&self.dir) else {
            return changed;
        };
        let mut present = HashSet::new();
        let routed: HashSet<String> = router.patterns().into_iter().collect();
        for entry in entries.flatten() {
            let Ok(meta) = entry.metadata() else { continue };
            let Some(name) = entry.file_name().to_str().map(str::to_string) else {
                continue;
            };
            if !meta.is_file() || !valid_name(&name) {
                continue;
            }
            present.insert(name.clone());
            let path = format!("/files/{name}");
            let stamp = Stamp::of(&meta);
            let known = self.read().get(&name).map(|f| f.stamp);
            if known != Some(stamp) {
                let Ok(etag) = etag_of_file(&entry.path(), stamp, &self.stopped) else {
                    continue;
                };
                self.write().insert(name.clone(), File { stamp, etag });
                if known.is_some() {
                    changed.push(path.clone());
                }
            }
            if !routed.contains(&path) {
                router.add(
                    &path,
                    self.resource(Some(name))
                        .attr("title", path.trim_start_matches("/files/")),
                );
            }
        }
        self.write().retain(|name, _| {
            // A file written (PUT, POST) after the directory was read is not in `present`
            // but is there: only a file that is really gone loses its resource.
            let keep = present.contains(name)
                || fs::symlink_metadata(self.dir.join(name)).is_ok_and(|m| m.is_file());
            if !keep {
                router.remove(&format!("/files/{name}"));
            }
            keep
        });
        changed
    }

    /// The resource of one file (`Some(name)`), or of the writable patterns (`None`: the
    /// name comes from the path, or POST picks one).
    fn resource(&self, name: Option<String>) -> Resource {
        let (me, fixed) = (self.clone(), name.clone());
        let name_of = move |ctx: &Ctx| {
            fixed
                .clone()
                .or_else(|| ctx.param("name").map(str::to_string))
        };
        let mut r = Resource::new();
        if let Some(n) = &name {
            let cf = content_format_of(Path::new(n));
            let size = self.read().get(n).map_or(0, |f| f.stamp.len);
            r = r
                .attr("ct", cf.0.to_string())
                .attr("sz", size.to_string())
                .observable();
        }
        let get = (me.clone(), name_of.clone());
        r = r.get(handler(move |ctx| {
            let response = get.0.get(get.1(&ctx));
            async move { response }
        }));
        if !self.writable {
            return r;
        }
        let put = (me.clone(), name_of.clone());
        let delete = (me.clone(), name_of);
        r.put(handler(move |ctx| {
            let response = put.0.put(put.1(&ctx), &ctx.request);
            async move { response }
        }))
        .delete(handler(move |ctx| {
            let response = delete.0.delete(delete.1(&ctx));
            async move { response }
        }))
        .post(handler(move |ctx| {
            let response = me.post(&ctx.request);
            async move { response }
        }))
        .configuring(&[Code::PUT, Code::DELETE, Code::POST])
    }

    fn get(&self, name: Option<String>) -> Response {
        let Some((name, file)) = name.and_then(|n| {
            let file = *self.read().get(&n)?;
            Some((n, file))
        }) else {
            return Response::diagnostic(Code::NOT_FOUND, "no such file");
        };
        let source = FileSource {
            path: self.dir.join(&name),
            stamp: file.stamp,
            window: Mutex::new((0, Bytes::new())),
        };
        match fs::metadata(&source.path) {
            Ok(meta) if Stamp::of(&meta) == file.stamp => {}
            // Changed since it was hashed: the next rescan gives it a new ETag.
            Ok(_) => return changing(),
            Err(e) if e.kind() == io::ErrorKind::NotFound => {
                return Response::diagnostic(Code::NOT_FOUND, "no such file");
            }
            Err(e) => {
                return Response::diagnostic(
                    Code::INTERNAL_SERVER_ERROR,
                    &format!("reading {name}: {e}"),
                );
            }
        }
        let cf = content_format_of(Path::new(&name));
        let mut r = Response::new(Code::CONTENT).with_source(source);
        r.options
            .set_uint(OptionNumber::CONTENT_FORMAT, u32::from(cf.0));
        r.options.set(OptionNumber::ETAG, file.etag);
        r
    }

    /// Writes through a temporary file of its own and a rename, so readers never see half
    /// a file. The stamp comes from the written file itself after the rename, so a second
    /// write to the same name cannot pair this ETag with its content.
    fn store(&self, name: &str, body: &Bytes) -> io::Result<()> {
        static WRITES: AtomicU64 = AtomicU64::new(0);
        let _write = self.writes.lock().unwrap_or_else(PoisonError::into_inner);
        if let Some(quota) = self.quota {
            let (files, others) = (self.read().iter())
                .filter(|(n, _)| *n != name)
                .fold((0, 0), |(n, sum), (name, f)| {
                    (n + 1, sum + charge(name, f.stamp.len))
                });
            let this = charge(name, body.len() as u64);
            if others + this > quota {
                let why = format!(
                    "the directory's quota of {quota} bytes is full: its {files} other files are charged {others} bytes and this one {this} (each file its bytes in whole 4 KiB blocks, at least one, and its link in /.well-known/core)"
                );
                return Err(io::Error::new(io::ErrorKind::StorageFull, why));
            }
        }
        let (tmp, mut file) = loop {
            let n = WRITES.fetch_add(1, Ordering::Relaxed);
            let tmp = self
                .dir
                .join(format!(".{name}.{}.{n}.tmp", std::process::id()));
            // Another server sharing the directory may have picked the same name.
            match fs::File::create_new(&tmp) {
                Ok(file) => break (tmp, file),
                Err(e) if e.kind() == io::ErrorKind::AlreadyExists => {}
                Err(e) => return Err(e),
            }
        };
        if let Err(e) = file
            .write_all(body)
            .and_then(|()| fs::rename(&tmp, self.dir.join(name)))
        {
            let _ = fs::remove_file(&tmp);
            return Err(e);
        }
        let stamp = Stamp::of(&file.metadata()?);
        let mut hash = Etag::new(body.len() as u64);
        hash.write(body);
        self.write().insert(
            name.to_string(),
            File {
                stamp,
                etag: hash.finish(),
            },
        );
        let _ = self.changed.send(format!("/files/{name}"));
        Ok(())
    }

    fn put(&self, name: Option<String>, request: &IncomingRequest) -> Response {
        let name = match self.writable_name(name) {
            Ok(name) => name,
            Err(refused) => return refused,
        };
        let current = self.read().get(&name).map(|f| f.etag);
        if let Some(refused) = check_preconditions(request, current.as_ref().map(|e| &e[..])) {
            return refused;
        }
        match self.store(&name, &request.payload) {
            Ok(()) => Response::new(if current.is_some() {
                Code::CHANGED
            } else {
                Code::CREATED
            }),
            Err(e) => write_error(&name, &e),
        }
    }

    fn post(&self, request: &IncomingRequest) -> Response {
        let stamp = SystemTime::now()
            .duration_since(SystemTime::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos());
        let name = format!("upload-{stamp}.bin");
        match self.store(&name, &request.payload) {
            Ok(()) => {
                let mut r = Response::new(Code::CREATED);
                r.options.push(OptionNumber::LOCATION_PATH, b"files");
                r.options
                    .push(OptionNumber::LOCATION_PATH, name.into_bytes());
                r
            }
            Err(e) => write_error(&name, &e),
        }
    }

    fn delete(&self, name: Option<String>) -> Response {
        let name = match self.writable_name(name) {
            Ok(name) => name,
            Err(refused) => return refused,
        };
        match fs::remove_file(self.dir.join(&name)) {
            Ok(()) => {
                self.write().remove(&name);
                Response::new(Code::DELETED)
            }
            Err(e) if e.kind() == io::ErrorKind::NotFound => {
                Response::diagnostic(Code::NOT_FOUND, "no such file")
            }
            Err(e) => {
                tracing::warn!(name, "deleting: {e}");
                Response::diagnostic(
                    Code::INTERNAL_SERVER_ERROR,
                    &format!("could not delete {name}"),
                )
            }
        }
    }

    /// The name a PUT or DELETE may change: valid, short enough for its temporary file
    /// (4.00 otherwise), and naming nothing or a regular file: a directory, a symbolic
    /// link, a FIFO or a device in the directory is left alone (4.05).
    #[expect(
        clippy::result_large_err,
        reason = "a refusal is the Response sent; it keeps its options inline"
    )]
    fn writable_name(&self, name: Option<String>) -> Result<String, Response> {
        let Some(name) = name.filter(|n| valid_name(n)) else {
            return Err(Response::diagnostic(
                Code::BAD_REQUEST,
                "a file name must not be empty, start with '.' or contain '/'",
            ));
        };
        if name.len() > MAX_NAME {
            let why = format!("a file name is at most {MAX_NAME} bytes");
            return Err(Response::diagnostic(Code::BAD_REQUEST, &why));
        }
        match fs::symlink_metadata(self.dir.join(&name)) {
            Ok(meta) if !meta.file_type().is_file() => Err(Response::diagnostic(
                Code::METHOD_NOT_ALLOWED,
                &format!("{name} is not a regular file; only regular files are changed"),
            )),
            _ => Ok(name),
        }
    }
}

/// A file system block: what a file's bytes are counted in.
const BLOCK: u64 = 4096;

/// What a file named `name` of `len` bytes is charged against `--quota`: what it takes on
/// disk and in discovery, not only its bytes (4,000 one-byte files would otherwise count
/// as 4,000 bytes while taking megabytes of disk and of `/.well-known/core`). Its bytes
/// in whole blocks of 4 KiB, at least one (an empty file still takes an inode and a
/// directory entry), and its link in discovery: `</files/NAME>;ct=..;sz=..;obs;title="NAME"`.
fn charge(name: &str, len: u64) -> u64 {
    const LINK: u64 = 48;
    len.div_ceil(BLOCK).max(1) * BLOCK + LINK + 2 * name.len() as u64
}

/// The answer to a write that failed: 4.13 when there is no room (the quota, or the disk),
/// else 5.00.
fn write_error(name: &str, e: &io::Error) -> Response {
    if e.kind() == io::ErrorKind::StorageFull {
        return Response::diagnostic(Code::REQUEST_ENTITY_TOO_LARGE, &format!("{name}: {e}"));
    }
    Response::diagnostic(Code::INTERNAL_SERVER_ERROR, &format!("writing {name}: {e}"))
}

/// Longest file name a client may write: its temporary file (`.<name>.<pid>.<n>.tmp`)
/// must fit the 255 bytes a name may have on Linux file systems.
const MAX_NAME: usize = 200;

/// One GET's view of a file, read a window at a time, and only while the file at its path
/// still has the stamp its ETag was computed for. The file is opened for each window, not
/// kept open: the Block2 store keeps a source for minutes after its last block, and open
/// files would pile up to the process's limit.
struct FileSource {
    path: PathBuf,
    stamp: Stamp,
    /// The last window read: its offset in the file and its bytes.
    window: Mutex<(usize, Bytes)>,
}

impl FileSource {
    /// `len` bytes from `offset`, into memory that is not zeroed first (`read_to_end`
    /// fills spare capacity); `None` when the file is no longer the one stamped or fewer
    /// bytes are there. Stamped before and after the read: a write that landed during it
    /// shows in the times.
    fn read_at(&self, offset: usize, len: usize) -> Option<Vec<u8>> {
        let mut file = fs::File::open(&self.path).ok()?;
        let unchanged = |file: &fs::File| {
            file.metadata()
                .is_ok_and(|meta| Stamp::of(&meta) == self.stamp)
        };
        if !unchanged(&file) {
            return None;
        }
        file.seek(SeekFrom::Start(offset as u64)).ok()?;
        let mut buf = Vec::with_capacity(len);
        (&file).take(len as u64).read_to_end(&mut buf).ok()?;
        (buf.len() == len && unchanged(&file)).then_some(buf)
    }
}

impl BlockSource for FileSource {
    fn len(&self) -> usize {
        self.stamp.len as usize
    }

    fn read(&self, range: Range<usize>) -> Option<Bytes> {
        let mut window = self.window.lock().unwrap_or_else(PoisonError::into_inner);
        let (start, bytes) = &*window;
        if range.start < *start || range.end > start + bytes.len() {
            let end = range.end.max(range.start + WINDOW).min(self.len());
            let buf = self.read_at(range.start, end - range.start)?;
            *window = (range.start, Bytes::from(buf));
        }
        let (start, bytes) = &*window;
        Some(bytes.slice(range.start - start..range.end - start))
    }

    fn held(&self) -> usize {
        WINDOW.min(self.len())
    }
}

/// 5.03 with Max-Age 1: the file is being changed; the client may try again in a second.
fn changing() -> Response {
    let mut r = Response::diagnostic(Code::SERVICE_UNAVAILABLE, "the file is changing; try again");
    r.options.set_uint(OptionNumber::MAX_AGE, 1);
    r
}

fn valid_name(name: &str) -> bool {
    !name.is_empty() && !name.starts_with('.') && !name.contains(['/', '\\', '\0'])
}

/// A file's ETag: a hash of its length and content.
struct Etag(std::collections::hash_map::DefaultHasher);

impl Etag {
    fn new(len: u64) -> Self {
        let mut h = std::collections::hash_map::DefaultHasher::new();
        h.write_u64(len);
        Self(h)
    }

    fn write(&mut self, bytes: &[u8]) {
        self.0.write(bytes);
    }

    fn finish(&self) -> [u8; 8] {
        self.0.finish().to_be_bytes()
    }
}

/// Hashes a file a window at a time, failing when it does not match `stamp` (it changed
/// while being read; the next rescan tries again) or when `stopped` is set.
fn etag_of_file(path: &Path, stamp: Stamp, stopped: &AtomicBool) -> io::Result<[u8; 8]> {
    let mut file = fs::File::open(path)?;
    let mut hash = Etag::new(stamp.len);
    let mut buf = vec![0; WINDOW];
    let mut total = 0u64;
    loop {
        if stopped.load(Ordering::Relaxed) {
            return Err(io::ErrorKind::Interrupted.into());
        }
        let n = file.read(&mut buf)?;
        if n == 0 {
            break;
        }
        hash.write(&buf[..n]);
        total += n as u64;
    }
    if total != stamp.len || Stamp::of(&file.metadata()?) != stamp {
        return Err(io::Error::other("changed while hashed"));
    }
    Ok(hash.finish())
}

fn content_format_of(path: &Path) -> ContentFormat {
    match path
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
        .as_deref()
    {
        Some("txt") => ContentFormat::TEXT_PLAIN,
        Some("json") => ContentFormat::JSON,
        Some("png") => ContentFormat::IMAGE_PNG,
        Some("jpg" | "jpeg") => ContentFormat::IMAGE_JPEG,
        Some("cbor") => ContentFormat::CBOR,
        Some("ply") => crate::repr::PLY,
        Some("wlnk") => ContentFormat::LINK_FORMAT,
        _ => ContentFormat::OCTET_STREAM,
    }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use super::*;

    /// A server that has not stopped.
    static RUNNING: AtomicBool = AtomicBool::new(false);

    fn source(path: &Path) -> FileSource {
        FileSource {
            path: path.to_path_buf(),
            stamp: Stamp::of(&fs::metadata(path).unwrap()),
            window: Mutex::new((0, Bytes::new())),
        }
    }

    #[test]
    fn a_file_is_read_a_window_at_a_time_and_not_after_it_changed_in_place() {
        let dir = crate::ScratchDir::new("files-in-place");
        let path = dir.path().join("body.bin");
        let body: Vec<u8> = (0..3 * WINDOW + 100).map(|i| (i * 7) as u8).collect();
        fs::write(&path, &body).unwrap();
        let s = source(&path);
        assert_eq!(s.len(), body.len());
        for start in (0..body.len()).step_by(1024) {
            let end = (start + 1024).min(body.len());
            assert_eq!(s.read(start..end).unwrap(), body[start..end], "at {start}");
        }
        assert_eq!(s.held(), WINDOW);
        // Written in place, the modification time put back as `cp -p` or `touch -r` do:
        // the change time still tells, and what is not read yet is refused.
        let modified = fs::metadata(&path).unwrap().modified().unwrap();
        let f = fs::OpenOptions::new().write(true).open(&path).unwrap();
        // Until the change time moves: a file system may count it in whole seconds.
        for wait in [20, 1100] {
            std::thread::sleep(Duration::from_millis(wait));
            std::os::unix::fs::FileExt::write_all_at(&f, b"changed", 0).unwrap();
            f.set_modified(modified).unwrap();
            if Stamp::of(&fs::metadata(&path).unwrap()) != s.stamp {
                break;
            }
        }
        assert_eq!(fs::metadata(&path).unwrap().modified().unwrap(), modified);
        assert_eq!(s.read(0..1024), None);
    }

    #[test]
    fn a_file_replaced_by_a_rename_is_refused() {
        let dir = crate::ScratchDir::new("files-rename");
        let path = dir.path().join("body.bin");
        fs::write(&path, vec![1; 2 * WINDOW]).unwrap();
        let s = source(&path);
        assert_eq!(s.read(0..16).unwrap(), vec![1; 16]);
        fs::write(dir.path().join("new"), vec![2; 2 * WINDOW]).unwrap();
        fs::rename(dir.path().join("new"), &path).unwrap();
        assert_eq!(
            s.read(WINDOW..WINDOW + 16),
            None,
            "same length, another inode"
        );
    }

    #[test]
    fn a_stored_file_is_recorded_with_its_own_stamp_and_etag() {
        let dir = crate::ScratchDir::new("files-store");
        let (tx, _rx) = mpsc::unbounded_channel();
        let files = StaticFiles::load(dir.path(), &Router::new(), true, None, tx).unwrap();
        for body in [&b"first"[..], &b"second, longer"[..]] {
            files.store("a.txt", &Bytes::copy_from_slice(body)).unwrap();
            let path = dir.path().join("a.txt");
            let stamp = Stamp::of(&fs::metadata(&path).unwrap());
            let recorded = *files.read().get("a.txt").unwrap();
            assert_eq!(recorded.stamp, stamp);
            assert_eq!(recorded.etag, etag_of_file(&path, stamp, &RUNNING).unwrap());
        }
        let names: Vec<_> = fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(names, ["a.txt"], "no temporary file left");
    }

    #[test]
    fn writes_beyond_the_quota_are_refused_and_write_nothing() {
        let dir = crate::ScratchDir::new("files-quota");
        fs::write(dir.path().join("old.bin"), [1; 40]).unwrap();
        let (tx, _rx) = mpsc::unbounded_channel();
        // Room for three files of one block each (and their links).
        let quota = 3 * (BLOCK + 100);
        let files = StaticFiles::load(dir.path(), &Router::new(), true, Some(quota), tx).unwrap();
        let body = |n: usize| Bytes::from(vec![7; n]);
        files
            .store("a.bin", &body(60))
            .expect("two blocks fit three");
        let full = files
            .store("b.bin", &body(4097))
            .expect_err("two more blocks do not");
        assert_eq!(full.kind(), io::ErrorKind::StorageFull);
        assert!(!dir.path().join("b.bin").exists(), "nothing written");
        // Replacing a file counts its new size, not both.
        files.store("a.bin", &body(4096)).expect("still one block");
        files.store("b.bin", &body(10)).expect("the third block");
        let r = write_error("c.bin", &files.store("c.bin", &body(0)).expect_err("full"));
        assert_eq!(r.code, Code::REQUEST_ENTITY_TOO_LARGE);
        let text = String::from_utf8_lossy(&r.payload).into_owned();
        assert!(text.contains(&format!("quota of {quota} bytes")), "{text}");
    }

    #[test]
    fn tiny_files_are_charged_what_they_take_so_a_quota_bounds_their_number() {
        let dir = crate::ScratchDir::new("files-quota-tiny");
        let (tx, _rx) = mpsc::unbounded_channel();
        let files = StaticFiles::load(dir.path(), &Router::new(), true, Some(100_000), tx)
            .expect("the directory");
        // One-byte files: 100,000 bytes of quota would have held 100,000 of them, each
        // taking a block of disk and a link in discovery.
        let written = (0..100)
            .take_while(|n| {
                files
                    .store(&format!("f{n:04}.txt"), &Bytes::from_static(b"x"))
                    .is_ok()
            })
            .count();
        assert!(
            written <= (100_000 / BLOCK) as usize,
            "{written} one-byte files within a quota of 100,000 bytes"
        );
        assert!(written > 0);
    }

    #[test]
    fn the_etag_follows_the_content_and_a_file_that_changes_while_hashed_has_none() {
        let dir = crate::ScratchDir::new("files-etag");
        let (a, b) = (dir.path().join("a"), dir.path().join("b"));
        fs::write(&a, vec![5; WINDOW + 1]).unwrap();
        fs::write(&b, vec![5; WINDOW + 1]).unwrap();
        let stamp = |p: &Path| Stamp::of(&fs::metadata(p).unwrap());
        assert_eq!(
            etag_of_file(&a, stamp(&a), &RUNNING).unwrap(),
            etag_of_file(&b, stamp(&b), &RUNNING).unwrap()
        );
        let mut written = Etag::new(WINDOW as u64 + 1);
        written.write(&vec![5; WINDOW + 1]);
        assert_eq!(
            written.finish(),
            etag_of_file(&a, stamp(&a), &RUNNING).unwrap()
        );
        let old = stamp(&b);
        fs::write(&b, vec![6; WINDOW + 1]).unwrap();
        fs::File::options()
            .write(true)
            .open(&b)
            .unwrap()
            .set_modified(SystemTime::now() + Duration::from_secs(5))
            .unwrap();
        assert!(etag_of_file(&b, old, &RUNNING).is_err());
        assert_ne!(
            etag_of_file(&a, stamp(&a), &RUNNING).unwrap(),
            etag_of_file(&b, stamp(&b), &RUNNING).unwrap()
        );
        // A stopping server hashes nothing more.
        let stopped = AtomicBool::new(true);
        let e = etag_of_file(&a, stamp(&a), &stopped).unwrap_err();
        assert_eq!(e.kind(), io::ErrorKind::Interrupted);
    }
}
