//! The bodies of `bench transfer`: seeded random bytes, one file per size, and how a
//! client's output differs from its body.

use std::path::{Path, PathBuf};

use anyhow::Context as _;
use rand_chacha::ChaCha8Rng;
use rand_core::{RngCore as _, SeedableRng as _};

use super::config::BLOCK_BYTES;

/// A body of random bytes and its file.
pub(super) struct Body {
    pub(super) size: u64,
    pub(super) path: PathBuf,
    pub(super) bytes: Vec<u8>,
}

impl Body {
    pub(super) fn file_name(&self) -> String {
        format!("body-{}.bin", self.size)
    }

    /// `size` random bytes from `seed` (ChaCha8), written into `dir`.
    pub(super) fn write(dir: &Path, size: u64, seed: u64) -> anyhow::Result<Self> {
        let len = usize::try_from(size).context("body size")?;
        let mut bytes = vec![0u8; len];
        ChaCha8Rng::seed_from_u64(mix(seed, size)).fill_bytes(&mut bytes);
        let mut body = Self {
            size,
            path: PathBuf::new(),
            bytes,
        };
        body.path = dir.join(body.file_name());
        std::fs::write(&body.path, &body.bytes)
            .with_context(|| format!("writing {}", body.path.display()))?;
        Ok(body)
    }
}

/// SplitMix64's finaliser of `a` and `b`: seeds that differ in any input differ.
pub(super) fn mix(a: u64, b: u64) -> u64 {
    let mut z = a
        .wrapping_add(b.wrapping_mul(0x9e37_79b9_7f4a_7c15))
        .wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// How `got` (a file) differs from `want`; `None` if it is the same, byte for byte.
pub(super) fn difference(got: &Path, want: &[u8]) -> Option<String> {
    let bytes = match std::fs::read(got) {
        Ok(b) => b,
        Err(e) => return Some(format!("no output ({}: {e})", got.display())),
    };
    if bytes == want {
        return None;
    }
    let first = bytes.iter().zip(want).position(|(a, b)| a != b);
    Some(
        match first {
            Some(i) => format!(
                "body differs: {} of {} bytes, first difference at byte {i}",
                bytes.len(),
                want.len()
            ),
            None => format!(
                "body differs: {} of {} bytes, the same up to there",
                bytes.len(),
                want.len()
            ),
        } + &which_block(&bytes, want),
    )
}

/// For a short output that starts with one of the body's other blocks (a client that
/// wrote the wrong block), which one: `"; it starts with block N"`; else nothing.
pub(super) fn which_block(got: &[u8], want: &[u8]) -> String {
    let block = BLOCK_BYTES as usize;
    let Some(head) = got.get(..block) else {
        return String::new();
    };
    want.chunks(block)
        .position(|c| c == head)
        .filter(|&n| n > 0)
        .map_or_else(String::new, |n| {
            format!("; it starts with block {n} of the body")
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bodies_are_reproducible_from_the_seed() {
        let dir = std::env::temp_dir().join(format!("coapcam-bt-unit-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let other = dir.join("other");
        std::fs::create_dir_all(&other).unwrap();
        let a = Body::write(&dir, 1000, 3).unwrap();
        let b = Body::write(&other, 1000, 3).unwrap();
        let c = Body::write(&other, 1000, 4).unwrap();
        assert_eq!(a.bytes, b.bytes);
        assert_ne!(a.bytes, c.bytes);
        assert_eq!(std::fs::read(&a.path).unwrap(), a.bytes);
        assert_eq!(difference(&a.path, &a.bytes), None);
        assert!(
            difference(&a.path, &c.bytes)
                .unwrap()
                .contains("first difference")
        );
        let body: Vec<u8> = (0..4096u32).map(|i| (i / 1024) as u8).collect();
        assert_eq!(
            which_block(&body[2048..3072], &body),
            "; it starts with block 2 of the body"
        );
        assert_eq!(which_block(&body[..1024], &body), "");
        assert_eq!(which_block(&body[..10], &body), "");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
