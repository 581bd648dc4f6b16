//! Per-serial persistence of the JSON resources: `<state-dir>/<serial>/<name>.json`,
//! written atomically (temporary file, fsync, rename, fsync of the directory). A server
//! killed during a write leaves its temporary file; the next one to start removes those
//! of processes that no longer run.

use std::fs::File;
use std::io::{self, Write as _};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

use rgbd::Serial;

/// The state directory.
#[derive(Debug, Clone)]
pub(crate) struct StateDir {
    root: PathBuf,
}

impl StateDir {
    pub(crate) fn new(root: &Path) -> Self {
        Self {
            root: root.to_path_buf(),
        }
    }

    /// Removes the temporary files (`.<name>.json.<pid>.<n>.tmp`) that writes of a process
    /// no longer running left behind (a server killed with SIGKILL in the middle of a PUT),
    /// and returns how many. A live process's file is left alone, and so is every file
    /// where `/proc` cannot tell which processes run.
    pub(crate) fn remove_leftovers(&self) -> usize {
        let Ok(serials) = std::fs::read_dir(&self.root) else {
            return 0;
        };
        let mut removed = 0;
        for serial in serials.flatten() {
            let Ok(entries) = std::fs::read_dir(serial.path()) else {
                continue;
            };
            for entry in entries.flatten() {
                let leftover = entry
                    .file_name()
                    .to_str()
                    .and_then(writer_of)
                    .is_some_and(|pid| !runs(pid))
                    && entry.file_type().is_ok_and(|t| t.is_file());
                if leftover {
                    match std::fs::remove_file(entry.path()) {
                        Ok(()) => removed += 1,
                        Err(e) => tracing::warn!(
                            path = %entry.path().display(),
                            error = %e,
                            "a temporary file left by an interrupted write stays"
                        ),
                    }
                }
            }
        }
        removed
    }

    fn path(&self, serial: &Serial, name: &str) -> PathBuf {
        self.root.join(serial.as_str()).join(format!("{name}.json"))
    }

    /// The stored document, `None` when there is none. Anything but a regular file (a
    /// FIFO would block the reader, a device would never end) is refused, the error naming
    /// the path.
    pub(crate) fn load(&self, serial: &Serial, name: &str) -> io::Result<Option<Vec<u8>>> {
        let path = self.path(serial, name);
        let named = |e: io::Error| io::Error::new(e.kind(), format!("{}: {e}", path.display()));
        match std::fs::metadata(&path) {
            Ok(m) if !m.is_file() => {
                let why = format!("{}: not a regular file", path.display());
                Err(io::Error::new(io::ErrorKind::InvalidInput, why))
            }
            Ok(_) => std::fs::read(&path).map(Some).map_err(named),
            Err(e) if e.kind() == io::ErrorKind::NotFound => Ok(None),
            Err(e) => Err(named(e)),
        }
    }

    /// Moves a stored document that could not be read aside, to
    /// `<name>.json.corrupt-<unix seconds>` (`-2`, `-3`, ... after it when taken), and
    /// returns where: it is kept for a person to look at, and never overwritten.
    pub(crate) fn set_aside(&self, serial: &Serial, name: &str) -> io::Result<PathBuf> {
        let path = self.path(serial, name);
        let secs = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_secs());
        for n in 1..1000 {
            let suffix = if n == 1 {
                String::new()
            } else {
                format!("-{n}")
            };
            let aside = path.with_extension(format!("json.corrupt-{secs}{suffix}"));
            // A hard link fails when the name is taken, where a rename would replace it.
            match std::fs::hard_link(&path, &aside) {
                Ok(()) => {
                    std::fs::remove_file(&path)?;
                    return Ok(aside);
                }
                Err(e) if e.kind() == io::ErrorKind::AlreadyExists => {}
                Err(e) => return Err(e),
            }
        }
        let why = format!("{}: no free name to set it aside", path.display());
        Err(io::Error::new(io::ErrorKind::AlreadyExists, why))
    }

    /// Replaces the stored document; a reader sees the old or the new one, never a part.
    /// Each write has a temporary file of its own (two writers never share one), removed
    /// when the write fails.
    pub(crate) fn store(&self, serial: &Serial, name: &str, body: &[u8]) -> io::Result<()> {
        static NEXT: AtomicU64 = AtomicU64::new(0);
        let dir = self.root.join(serial.as_str());
        std::fs::create_dir_all(&dir)?;
        let n = NEXT.fetch_add(1, Ordering::Relaxed);
        let tmp = dir.join(format!(".{name}.json.{}.{n}.tmp", std::process::id()));
        let written = (|| {
            let mut f = File::create_new(&tmp)?;
            f.write_all(body)?;
            f.sync_all()?;
            drop(f);
            std::fs::rename(&tmp, self.path(serial, name))
        })();
        if let Err(e) = written {
            let _ = std::fs::remove_file(&tmp);
            return Err(e);
        }
        File::open(&dir)?.sync_all()
    }
}

impl StateDir {
    /// Forgets the stored document (the defaults apply from now on, also after a
    /// restart); nothing to do when none is stored.
    pub(crate) fn remove(&self, serial: &Serial, name: &str) -> io::Result<()> {
        match std::fs::remove_file(self.path(serial, name)) {
            Ok(()) => File::open(self.root.join(serial.as_str()))?.sync_all(),
            Err(e) if e.kind() == io::ErrorKind::NotFound => Ok(()),
            Err(e) => Err(e),
        }
    }
}

/// The process that wrote the temporary file `name` (`.<name>.json.<pid>.<n>.tmp`, what
/// [`StateDir::store`] makes); `None` for any other name.
fn writer_of(name: &str) -> Option<u32> {
    let inner = name.strip_prefix('.')?.strip_suffix(".tmp")?;
    let mut parts = inner.rsplitn(3, '.');
    let n = parts.next()?;
    let pid = parts.next()?;
    let document = parts.next()?;
    n.parse::<u64>().ok()?;
    (document.ends_with(".json") && document.len() > ".json".len()).then_some(())?;
    pid.parse().ok()
}

/// Whether process `pid` runs (or may: true where `/proc` does not say).
fn runs(pid: u32) -> bool {
    pid == std::process::id()
        || !Path::new("/proc/self").exists()
        || Path::new(&format!("/proc/{pid}")).exists()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_names_of_our_temporary_files_have_a_writer() {
        assert_eq!(writer_of(".application-config.json.4242.7.tmp"), Some(4242));
        for other in [
            "application-config.json",
            ".application-config.json.4242.7",
            ".json.4242.7.tmp",
            ".application-config.json.x.7.tmp",
            ".application-config.json.4242.x.tmp",
            ".notes.txt.4242.7.tmp",
            "application-config.json.4242.7.tmp",
        ] {
            assert_eq!(writer_of(other), None, "{other}");
        }
    }

    #[test]
    fn stores_and_loads_per_serial() {
        let root = std::env::temp_dir().join(format!("coapcam-state-unit-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        let dir = StateDir::new(&root);
        let sn = Serial::parse("840412060746").expect("serial");
        assert!(matches!(dir.load(&sn, "color-settings"), Ok(None)));
        assert!(dir.store(&sn, "color-settings", b"{}").is_ok());
        assert!(dir.store(&sn, "color-settings", b"{\"a\":1}").is_ok());
        assert_eq!(
            dir.load(&sn, "color-settings").ok().flatten(),
            Some(b"{\"a\":1}".to_vec())
        );
        let _ = std::fs::remove_dir_all(&root);
    }

    #[test]
    fn a_document_set_aside_keeps_its_bytes_and_never_replaces_another() {
        let root = std::env::temp_dir().join(format!("coapcam-state-aside-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        let dir = StateDir::new(&root);
        let sn = Serial::parse("840412060746").expect("serial");
        let mut aside = Vec::new();
        for body in [&b"{ broken"[..], b"\x00\x01"] {
            dir.store(&sn, "application-config", body).expect("store");
            let path = dir.set_aside(&sn, "application-config").expect("set aside");
            assert_eq!(std::fs::read(&path).expect("kept"), body);
            aside.push(path);
        }
        assert_ne!(aside[0], aside[1], "the second did not replace the first");
        assert!(matches!(dir.load(&sn, "application-config"), Ok(None)));
        let _ = std::fs::remove_dir_all(&root);
    }

    #[test]
    fn a_fifo_is_refused_at_once_and_named() {
        let root = std::env::temp_dir().join(format!("coapcam-state-fifo-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        let sn = Serial::parse("840412060746").expect("serial");
        std::fs::create_dir_all(root.join(sn.as_str())).expect("mkdir");
        let fifo = root.join(sn.as_str()).join("application-config.json");
        let made = std::process::Command::new("mkfifo")
            .arg(&fifo)
            .status()
            .expect("mkfifo runs");
        assert!(made.success());
        let err = StateDir::new(&root)
            .load(&sn, "application-config")
            .expect_err("a FIFO is not a document");
        assert!(err.to_string().contains("application-config.json"), "{err}");
        let _ = std::fs::remove_dir_all(&root);
    }
}
