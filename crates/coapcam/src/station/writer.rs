//! One log, one writer: a station holds an advisory lock (`flock`, through std's
//! `File::try_lock`) on a file beside its results log, `<log>.lock`, for as long as it
//! runs, with its process id and addresses in it. A second station started on the same
//! log finds the lock taken and refuses to start, naming the first; the kernel lets the
//! lock go when the holder exits, however it exits. The file stays behind (removing it
//! would let two stations lock two different files of one name); a file left by a station
//! that is gone is unlocked and taken over.

use std::fs::{File, OpenOptions, TryLockError};
use std::io::{Read as _, Seek as _, Write as _};
use std::path::{Path, PathBuf};

/// The lock file of the results log at `log`: its path and `.lock`.
pub fn lock_path(log: &Path) -> PathBuf {
    let mut name = log.as_os_str().to_owned();
    name.push(".lock");
    PathBuf::from(name)
}

/// Why the station may not write the log.
#[derive(Debug, thiserror::Error)]
pub enum WriterError {
    /// Another process holds the lock.
    #[error(
        "the results log {log} is written by another station ({holder}; its lock is {lock}): one log has one writer. Stop that one, or give this one a log of its own (--results FILE or --state-dir DIR)"
    )]
    Held {
        /// The log.
        log: PathBuf,
        /// The lock file.
        lock: PathBuf,
        /// What the holder wrote in it.
        holder: String,
    },
    /// The lock file cannot be made or locked.
    #[error("the lock {lock} of the results log: {source}")]
    Io {
        /// The lock file.
        lock: PathBuf,
        /// What failed.
        source: std::io::Error,
    },
}

/// The lock of a results log, held until dropped.
#[derive(Debug)]
pub struct WriterLock {
    file: File,
    path: PathBuf,
}

impl WriterLock {
    /// Takes the lock of the log at `log`, or says who holds it.
    pub fn take(log: &Path) -> Result<Self, WriterError> {
        let path = lock_path(log);
        let io = |source| WriterError::Io {
            lock: path.clone(),
            source,
        };
        let mut file = OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&path)
            .map_err(io)?;
        match file.try_lock() {
            Ok(()) => {}
            Err(TryLockError::WouldBlock) => {
                let mut text = String::new();
                let _ = file.read_to_string(&mut text);
                let holder = text.split_whitespace().collect::<Vec<_>>().join(" ");
                return Err(WriterError::Held {
                    log: log.to_owned(),
                    lock: path,
                    holder: if holder.is_empty() {
                        "a process that has not written its id yet".into()
                    } else {
                        holder
                    },
                });
            }
            Err(TryLockError::Error(e)) => return Err(io(e)),
        }
        let mut lock = Self { file, path };
        lock.write(&format!("pid {}", std::process::id()))?;
        Ok(lock)
    }

    /// Replaces what the lock file says of its holder with `pid <id>` and `holder`.
    pub fn write(&mut self, holder: &str) -> Result<(), WriterError> {
        let text = if holder.starts_with("pid ") {
            format!("{holder}\n")
        } else {
            format!("pid {}, {holder}\n", std::process::id())
        };
        let file = &mut self.file;
        let written = file
            .set_len(0)
            .and_then(|()| file.rewind())
            .and_then(|()| file.write_all(text.as_bytes()));
        written.map_err(|source| WriterError::Io {
            lock: self.path.clone(),
            source,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_second_lock_on_one_log_is_refused_and_names_the_first() {
        let dir = crate::ScratchDir::new("writer-lock");
        let log = dir.0.join("results.sqlite");
        let mut first = WriterLock::take(&log).expect("the first takes it");
        first.write("coap 127.0.0.1:5683").expect("write");
        // Another open file description of the same file, as a second process has.
        let second = WriterLock::take(&log).expect_err("the second is refused");
        let text = second.to_string();
        assert!(
            text.contains(&format!("pid {}, coap 127.0.0.1:5683", std::process::id())),
            "{text}"
        );
        assert!(text.contains("results.sqlite"), "{text}");
        drop(first);
        WriterLock::take(&log).expect("taken again once the first let it go");
    }
}
