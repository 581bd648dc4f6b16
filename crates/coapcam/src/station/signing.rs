//! The station key: an Ed25519 key (RFC 8032) that signs every record the results log
//! appends, kept in a file outside the log (`serve --signing-key FILE`, made by
//! `coapcam results keygen FILE`); its public half is published beside the station's
//! identity and checks a log (`results verify --public-key`). docs/station.md, "Signed
//! records", has the files' format and what is signed.

use std::io::Write as _;
use std::os::unix::fs::{OpenOptionsExt as _, PermissionsExt as _};
use std::path::Path;

use ed25519_dalek::{Signature, Signer as _, SigningKey, Verifier as _, VerifyingKey};

use crate::api::record::Record;

/// The station's secret key, which signs records.
pub struct StationKey {
    key: SigningKey,
}

impl std::fmt::Debug for StationKey {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("StationKey")
            .field("public", &self.public().to_string())
            .finish_non_exhaustive()
    }
}

impl StationKey {
    /// Makes a new key from the operating system's random source and writes its secret
    /// half to `path` (64 hex digits and a newline), readable and writable by its owner
    /// only (0600). Refuses to replace a file that exists: a station's key is made once.
    pub fn generate(path: &Path) -> Result<Self, String> {
        let mut seed = [0u8; 32];
        std::fs::File::open("/dev/urandom")
            .and_then(|mut random| std::io::Read::read_exact(&mut random, &mut seed))
            .map_err(|e| format!("reading 32 random bytes from /dev/urandom: {e}"))?;
        let key = Self {
            key: SigningKey::from_bytes(&seed),
        };
        let mut file = std::fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .mode(0o600)
            .open(path)
            .map_err(|e| match e.kind() {
                std::io::ErrorKind::AlreadyExists => format!(
                    "{} exists: a station key is made once (remove the file first to make another; records signed with the old key then verify only with its public key)",
                    path.display()
                ),
                _ => format!("creating {}: {e}", path.display()),
            })?;
        file.write_all(format!("{}\n", hex(&seed)).as_bytes())
            .and_then(|()| file.sync_all())
            .map_err(|e| format!("writing {}: {e}", path.display()))?;
        Ok(key)
    }

    /// Reads the secret key at `path`, as [`StationKey::generate`] wrote it. Refuses a
    /// missing file (naming `coapcam results keygen`, as a station never makes a key by
    /// itself: a path mistyped must not become a new key) and a file that others than
    /// its owner may read or write.
    pub fn load(path: &Path) -> Result<Self, String> {
        let meta = std::fs::metadata(path).map_err(|e| match e.kind() {
            std::io::ErrorKind::NotFound => format!(
                "no station key at {}: make one with `coapcam results keygen {}` (it prints the public key to publish)",
                path.display(),
                path.display()
            ),
            _ => format!("reading the station key {}: {e}", path.display()),
        })?;
        let mode = meta.permissions().mode() & 0o777;
        if mode & 0o077 != 0 {
            return Err(format!(
                "the station key {} may be read or written by others (mode {mode:03o}): chmod 600 it",
                path.display()
            ));
        }
        let text = std::fs::read_to_string(path)
            .map_err(|e| format!("reading the station key {}: {e}", path.display()))?;
        let seed = unhex::<32>(text.trim()).ok_or_else(|| {
            format!(
                "the station key {} is not 64 hex digits (a secret key as `coapcam results keygen` writes it)",
                path.display()
            )
        })?;
        Ok(Self {
            key: SigningKey::from_bytes(&seed),
        })
    }

    /// The public half, which checks the signatures.
    pub fn public(&self) -> PublicKey {
        PublicKey(self.key.verifying_key())
    }

    /// The signature (128 hex digits) of the record whose canonical bytes are `body`:
    /// over [`Record::hashed_bytes`], the bytes its hash is taken over.
    pub fn sign(&self, body: &[u8]) -> String {
        hex(&self.key.sign(&Record::hashed_bytes(body)).to_bytes())
    }
}

/// A station key's public half: 64 hex digits written.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PublicKey(VerifyingKey);

impl PublicKey {
    /// Reads 64 hex digits, or a file holding them (as `results keygen` prints them and
    /// the station publishes them).
    pub fn parse(text: &str) -> Result<Self, String> {
        match Self::parse_all(text)?.as_slice() {
            [key] => Ok(*key),
            keys => Err(format!(
                "{:?} holds {} public keys, not one",
                text.trim(),
                keys.len()
            )),
        }
    }

    /// Reads 64 hex digits, or a file of public keys: one a line, blank lines and lines
    /// starting with # skipped (a file holding one key, as keygen's output saved, is such
    /// a file).
    pub fn parse_all(text: &str) -> Result<Vec<Self>, String> {
        let text = text.trim();
        if text.len() == 64 && text.bytes().all(|b| b.is_ascii_hexdigit()) {
            return Self::from_hex(text, text).map(|k| vec![k]);
        }
        let file = std::fs::read_to_string(text).map_err(|e| {
            format!("{text:?} is neither a public key (64 hex digits) nor a file holding one ({e})")
        })?;
        let mut keys = Vec::new();
        for (n, line) in file.lines().enumerate() {
            let line = line.trim();
            if line.is_empty() || line.starts_with('#') {
                continue;
            }
            keys.push(Self::from_hex(line, &format!("{text} line {}", n + 1))?);
        }
        if keys.is_empty() {
            return Err(format!("{text:?} holds no public key (64 hex digits)"));
        }
        Ok(keys)
    }

    /// The key of 64 hex digits; `source` names where they came from when they are not.
    fn from_hex(digits: &str, source: &str) -> Result<Self, String> {
        let bytes = unhex::<32>(digits)
            .ok_or_else(|| format!("{source:?} does not hold a public key (64 hex digits)"))?;
        VerifyingKey::from_bytes(&bytes)
            .map(Self)
            .map_err(|e| format!("{source:?} is not an Ed25519 public key ({e})"))
    }

    /// Whether `signature` (hex) is this key's signature of the record whose canonical
    /// bytes are `body`; why not when it is not.
    pub fn check(&self, body: &[u8], signature: &str) -> Result<(), String> {
        let bytes = unhex::<64>(signature)
            .ok_or_else(|| "its signature is not 128 hex digits".to_owned())?;
        self.0
            .verify(&Record::hashed_bytes(body), &Signature::from_bytes(&bytes))
            .map_err(|_| "its signature does not hold for this public key".to_owned())
    }
}

impl std::fmt::Display for PublicKey {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&hex(self.0.as_bytes()))
    }
}

fn hex(bytes: &[u8]) -> String {
    use std::fmt::Write as _;
    let mut out = String::with_capacity(bytes.len() * 2);
    for b in bytes {
        let _ = write!(out, "{b:02x}");
    }
    out
}

/// `N` bytes from `2 N` hex digits.
fn unhex<const N: usize>(text: &str) -> Option<[u8; N]> {
    let digits = text.as_bytes();
    if digits.len() != 2 * N {
        return None;
    }
    let mut out = [0u8; N];
    for (byte, pair) in out.iter_mut().zip(digits.chunks_exact(2)) {
        let pair = std::str::from_utf8(pair).ok()?;
        *byte = u8::from_str_radix(pair, 16).ok()?;
    }
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ScratchDir;

    #[test]
    fn a_key_made_once_signs_and_its_public_half_checks() {
        let dir = ScratchDir::new("signing-key");
        let path = dir.path().join("station.key");
        let made = StationKey::generate(&path).expect("generate");
        let mode = std::fs::metadata(&path).expect("key").permissions().mode();
        assert_eq!(mode & 0o777, 0o600);
        assert!(StationKey::generate(&path).is_err(), "never replaced");
        let key = StationKey::load(&path).expect("load");
        assert_eq!(key.public(), made.public());
        let public = PublicKey::parse(&key.public().to_string()).expect("hex");
        let body = br#"{"id":1}"#;
        let signature = key.sign(body);
        assert_eq!(signature.len(), 128);
        assert_eq!(public.check(body, &signature), Ok(()));
        assert!(public.check(br#"{"id":2}"#, &signature).is_err());
        let other = dir.path().join("other.key");
        let other = StationKey::generate(&other).expect("another");
        assert!(other.public().check(body, &signature).is_err());
        std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o644)).expect("chmod");
        let loose = StationKey::load(&path).expect_err("readable by others");
        assert!(loose.contains("chmod 600"), "{loose}");
        let missing = StationKey::load(&dir.path().join("none")).expect_err("missing");
        assert!(missing.contains("coapcam results keygen"), "{missing}");
    }
}
