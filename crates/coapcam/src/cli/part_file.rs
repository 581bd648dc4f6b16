//! `-o FILE` of the commands that write a body (`get`, `grab`): the file appears whole or
//! not at all. Not a command: what commands share, like [`super::values`].

use std::io::Write as _;
use std::path::{Path, PathBuf};

use anyhow::Context as _;

/// Where `-o FILE` writes: a temporary file beside FILE (new, or a regular file, possibly
/// through a symbolic link), renamed to it only when the body arrived whole and removed
/// otherwise; or FILE itself when it is not a regular file (a device such as /dev/null, a
/// pipe), which must not be replaced and where a partial body cannot be taken back.
pub(crate) struct PartFile {
    /// The file written.
    path: PathBuf,
    /// The file it becomes; `None` when `path` is the output itself.
    target: Option<PathBuf>,
    file: Option<std::io::BufWriter<std::fs::File>>,
}

impl PartFile {
    pub(crate) fn create(output: &Path) -> anyhow::Result<Self> {
        let existing = match std::fs::metadata(output) {
            Ok(m) => Some(m),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => None,
            Err(e) => return Err(e).with_context(|| format!("reading {}", output.display())),
        };
        if existing.as_ref().is_some_and(|m| !m.is_file()) {
            let file = std::fs::OpenOptions::new()
                .write(true)
                .truncate(true)
                .open(output)
                .with_context(|| format!("opening {}", output.display()))?;
            return Ok(Self {
                path: output.to_path_buf(),
                target: None,
                file: Some(std::io::BufWriter::with_capacity(1 << 16, file)),
            });
        }
        // A link to a regular file keeps pointing at it: the body replaces what it names.
        let target = match existing {
            Some(_) => std::fs::canonicalize(output)
                .with_context(|| format!("resolving {}", output.display()))?,
            None => output.to_path_buf(),
        };
        let name = target
            .file_name()
            .with_context(|| format!("{} names no file", output.display()))?;
        let dir = target
            .parent()
            .filter(|d| !d.as_os_str().is_empty())
            .unwrap_or_else(|| Path::new("."));
        let mut part_name = std::ffi::OsString::from(".");
        part_name.push(name);
        part_name.push(format!(".{}.part", std::process::id()));
        let path = dir.join(part_name);
        let file = std::fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(&path)
            .with_context(|| {
                format!(
                    "cannot write {} (creating {})",
                    output.display(),
                    path.display()
                )
            })?;
        let part = Self {
            path,
            target: Some(target),
            file: Some(std::io::BufWriter::with_capacity(1 << 16, file)),
        };
        if let Some(m) = existing {
            // The replacement keeps the permissions of the file it replaces.
            std::fs::set_permissions(&part.path, m.permissions())
                .with_context(|| format!("setting the permissions of {}", part.path.display()))?;
        }
        Ok(part)
    }

    pub(crate) fn write(&mut self, data: &[u8]) -> anyhow::Result<()> {
        if let Some(f) = &mut self.file {
            f.write_all(data)
                .with_context(|| format!("writing {}", self.path.display()))?;
        }
        Ok(())
    }

    /// Flushes the file and renames it to the output.
    pub(crate) fn keep(mut self) -> anyhow::Result<()> {
        if let Some(f) = self.file.take() {
            f.into_inner()
                .map_err(std::io::IntoInnerError::into_error)
                .with_context(|| format!("writing {}", self.path.display()))?;
        }
        if let Some(target) = &self.target {
            std::fs::rename(&self.path, target).with_context(|| {
                format!("renaming {} to {}", self.path.display(), target.display())
            })?;
        }
        // Renamed: nothing left to remove.
        self.target = None;
        Ok(())
    }
}

impl Drop for PartFile {
    fn drop(&mut self) {
        self.file = None;
        if self.target.is_some() {
            // Best effort: the file is a hidden leftover if this fails.
            let _ = std::fs::remove_file(&self.path);
        }
    }
}
