//! RVL, lossless compression of 16-bit depth images (A. D. Wilson, "Fast Lossless Depth
//! Image Compression", ISS 2017), alone (coapcam's content format 65101) and followed by
//! zstd (65102).
//!
//! The pixels are read row by row as alternating runs: a run of zeros (no depth), then a
//! run of valid pixels, each valid pixel as the zig-zag coded difference to the valid
//! pixel before it (the first to 0). Every number (run lengths and differences) is
//! written in variable-length nibbles: 3 bits of the value, least significant first, the
//! fourth bit set when more nibbles follow. Nibbles fill 32-bit words from the top bits
//! down, eight to a word; the last word is padded with zero nibbles.
//!
//! The payload: a 12-byte header, then the words, each little-endian:
//!
//! | bytes | field |
//! |---|---|
//! | 0-1 | width, pixels (u16) |
//! | 2-3 | height, rows (u16) |
//! | 4-7 | metres per depth unit (f32) |
//! | 8-11 | seconds since the UNIX epoch of the grab (u32) |
//! | 12- | the words (u32 each) |
//!
//! 65102 is that whole payload as one zstd frame.

use std::io;

/// Bytes before the words.
const HEADER: usize = 12;
/// The zstd level of 65102: fast, and most of zstd's gain on RVL's output.
const ZSTD_LEVEL: i32 = 1;

/// Why an RVL payload could not be decoded.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum RvlError {
    /// Shorter than its header, or its words do not fill whole 4-byte words.
    #[error("RVL payload: {0} bytes is not a 12-byte header and whole 4-byte words")]
    Length(usize),
    /// The image has no pixels, or more than a depth image may have.
    #[error("RVL payload: a {width}x{height} image")]
    Size {
        /// Pixels per row.
        width: u16,
        /// Rows.
        height: u16,
    },
    /// The words end before every pixel was decoded.
    #[error("RVL payload: the data ends after {decoded} of {pixels} pixels")]
    Truncated {
        /// Pixels decoded.
        decoded: usize,
        /// Pixels the header gives.
        pixels: usize,
    },
    /// A run would pass the last pixel.
    #[error("RVL payload: a run of {run} pixels at pixel {at} passes the last ({pixels})")]
    Overrun {
        /// Where the run starts.
        at: usize,
        /// Its length.
        run: u64,
        /// Pixels the header gives.
        pixels: usize,
    },
    /// A number with more nibbles than 32 bits hold, or a depth outside 0-65535.
    #[error("RVL payload: a value out of range at pixel {0}")]
    Value(usize),
    /// Words left after the last pixel that are not padding.
    #[error("RVL payload: {0} bytes after the last pixel")]
    Trailing(usize),
    /// The zstd frame of 65102 does not decode.
    #[error("RVL+zstd payload: {0}")]
    Zstd(String),
}

/// The largest image decoded: 4096 x 4096 pixels (a D400's largest is 1280 x 720).
const MAX_PIXELS: usize = 1 << 24;

/// Writes nibbles into 32-bit words, the first in the top bits.
struct Writer {
    out: Vec<u8>,
    word: u32,
    nibbles: u32,
}

impl Writer {
    fn nibble(&mut self, n: u32) {
        self.word = (self.word << 4) | n;
        self.nibbles += 1;
        if self.nibbles == 8 {
            self.out.extend_from_slice(&self.word.to_le_bytes());
            self.word = 0;
            self.nibbles = 0;
        }
    }

    fn number(&mut self, mut value: u32) {
        loop {
            let low = value & 7;
            value >>= 3;
            if value == 0 {
                return self.nibble(low);
            }
            self.nibble(low | 8);
        }
    }

    fn finish(mut self) -> Vec<u8> {
        if self.nibbles > 0 {
            let word = self.word << (4 * (8 - self.nibbles));
            self.out.extend_from_slice(&word.to_le_bytes());
        }
        self.out
    }
}

/// Zig-zag: 0, -1, 1, -2, 2, ... to 0, 1, 2, 3, 4, ...
fn zigzag(delta: i32) -> u32 {
    ((delta << 1) ^ (delta >> 31)) as u32
}

fn unzigzag(value: u32) -> i32 {
    (value >> 1) as i32 ^ -((value & 1) as i32)
}

/// A depth image: what an RVL payload holds.
#[derive(Debug, Clone, PartialEq)]
pub struct DepthImage {
    /// Pixels per row.
    pub width: u16,
    /// Rows.
    pub height: u16,
    /// Metres per depth unit.
    pub depth_scale: f32,
    /// Seconds since the UNIX epoch of the grab.
    pub timestamp_s: u32,
    /// Row-major, `width * height` values; 0 = no depth.
    pub values: Vec<u16>,
}

/// RVL in a zstd frame (65102) of an RVL payload from [`encode`].
pub fn compress(rvl: &[u8]) -> io::Result<Vec<u8>> {
    zstd::bulk::compress(rvl, ZSTD_LEVEL)
}

/// RVL (65101) of `pixels`, row-major, `width * height` of them, under the header's
/// fields.
pub fn encode(
    width: u16,
    height: u16,
    depth_scale: f32,
    timestamp_s: u32,
    pixels: &[u16],
) -> Vec<u8> {
    let mut out = Vec::with_capacity(HEADER + pixels.len());
    out.extend_from_slice(&width.to_le_bytes());
    out.extend_from_slice(&height.to_le_bytes());
    out.extend_from_slice(&depth_scale.to_le_bytes());
    out.extend_from_slice(&timestamp_s.to_le_bytes());
    let mut w = Writer {
        out,
        word: 0,
        nibbles: 0,
    };
    let mut previous = 0i32;
    let mut at = 0;
    while at < pixels.len() {
        let zeros = pixels[at..].iter().take_while(|&&v| v == 0).count();
        at += zeros;
        let valid = pixels[at..].iter().take_while(|&&v| v != 0).count();
        w.number(zeros as u32);
        w.number(valid as u32);
        for &v in &pixels[at..at + valid] {
            let v = i32::from(v);
            w.number(zigzag(v - previous));
            previous = v;
        }
        at += valid;
    }
    w.finish()
}

/// Reads nibbles from 32-bit words, the first from the top bits.
struct Reader<'a> {
    words: std::slice::ChunksExact<'a, u8>,
    word: u32,
    left: u32,
}

impl Reader<'_> {
    fn nibble(&mut self) -> Option<u32> {
        if self.left == 0 {
            let bytes = self.words.next()?;
            self.word = u32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]]);
            self.left = 8;
        }
        self.left -= 1;
        let n = self.word >> 28;
        self.word <<= 4;
        Some(n)
    }

    /// The next number, read at pixel `at` of `pixels`.
    fn number(&mut self, at: usize, pixels: usize) -> Result<u32, RvlError> {
        let mut value = 0u64;
        let mut shift = 0;
        loop {
            let n = self.nibble().ok_or(RvlError::Truncated {
                decoded: at,
                pixels,
            })?;
            value |= u64::from(n & 7) << shift;
            if n & 8 == 0 {
                break;
            }
            shift += 3;
            if shift > 32 {
                // Twelve nibbles and more to come: past 32 bits.
                return Err(RvlError::Value(at));
            }
        }
        u32::try_from(value).map_err(|_| RvlError::Value(at))
    }
}

/// Decodes an RVL payload (65101).
pub fn decode(payload: &[u8]) -> Result<DepthImage, RvlError> {
    if payload.len() < HEADER || !(payload.len() - HEADER).is_multiple_of(4) {
        return Err(RvlError::Length(payload.len()));
    }
    let field = |at: usize| {
        [
            payload[at],
            payload[at + 1],
            payload[at + 2],
            payload[at + 3],
        ]
    };
    let width = u16::from_le_bytes([payload[0], payload[1]]);
    let height = u16::from_le_bytes([payload[2], payload[3]]);
    let depth_scale = f32::from_le_bytes(field(4));
    let timestamp_s = u32::from_le_bytes(field(8));
    let pixels = usize::from(width) * usize::from(height);
    if pixels == 0 || pixels > MAX_PIXELS {
        return Err(RvlError::Size { width, height });
    }
    let mut r = Reader {
        words: payload[HEADER..].chunks_exact(4),
        word: 0,
        left: 0,
    };
    let mut values = vec![0u16; pixels];
    let mut at = 0usize;
    let mut previous = 0i32;
    let run = |at: usize, n: u32| {
        let end = at.checked_add(n as usize).filter(|&end| end <= pixels);
        end.ok_or_else(|| RvlError::Overrun {
            at,
            run: u64::from(n),
            pixels,
        })
    };
    while at < pixels {
        at = run(at, r.number(at, pixels)?)?;
        let end = run(at, r.number(at, pixels)?)?;
        for slot in &mut values[at..end] {
            let v = previous + unzigzag(r.number(at, pixels)?);
            *slot = u16::try_from(v).map_err(|_| RvlError::Value(at))?;
            previous = v;
            at += 1;
        }
    }
    // What follows may only be the last word's padding.
    let trailing = r.words.len() * 4;
    if trailing > 0 || (r.left > 0 && r.word != 0) {
        return Err(RvlError::Trailing(trailing));
    }
    Ok(DepthImage {
        width,
        height,
        depth_scale,
        timestamp_s,
        values,
    })
}

/// Decodes an RVL+zstd payload (65102).
pub fn decode_zstd(payload: &[u8]) -> Result<DepthImage, RvlError> {
    // RVL takes at most 3 bytes a pixel (a difference of 17 bits is 6 nibbles; runs take
    // at most 4 nibbles a pixel), so this bounds what is decompressed.
    let rvl = crate::wire::unzstd(payload, HEADER + MAX_PIXELS * 3 + 8).map_err(|e| match e {
        crate::WireError::Zstd(why) => RvlError::Zstd(why),
        other => RvlError::Zstd(other.to_string()),
    })?;
    decode(&rvl)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn rvl(width: u16, height: u16, values: &[u16]) -> Vec<u8> {
        encode(width, height, 0.001, 1_700_000_000, values)
    }

    #[test]
    fn a_known_image_gives_known_words() {
        // Two zeros, then 3 valid pixels: 1000 (+1000), 1001 (+1), 999 (-2); one zero.
        let values = [0, 0, 1000, 1001, 999, 0];
        let payload = rvl(3, 2, &values);
        // Numbers: 2, 3, zigzag(1000)=2000, zigzag(1)=2, zigzag(-2)=3, then 1 zero and
        // 0 valid. 2000 = 0o3720: nibbles 0+8, 2+8, 7+8, 3 (low first).
        let nibbles = [2, 3, 8, 10, 15, 3, 2, 3, 1, 0];
        let mut words = Vec::new();
        for chunk in nibbles.chunks(8) {
            let mut word = 0u32;
            for (i, &n) in chunk.iter().enumerate() {
                word |= n << (28 - 4 * i);
            }
            words.extend_from_slice(&word.to_le_bytes());
        }
        assert_eq!(&payload[HEADER..], &words[..]);
        let back = decode(&payload).expect("decodes");
        assert_eq!(back.values, values);
        assert_eq!((back.width, back.height, back.depth_scale), (3, 2, 0.001));
        assert_eq!(back.timestamp_s, 1_700_000_000);
    }

    #[test]
    fn malformed_payloads_give_errors() {
        let payload = rvl(4, 1, &[300, 0, 0, 65535]);
        assert!(matches!(decode(&payload[..5]), Err(RvlError::Length(5))));
        assert!(matches!(
            decode(&payload[..HEADER]),
            Err(RvlError::Truncated { decoded: 0, .. })
        ));
        let mut empty = payload.clone();
        empty[0..2].copy_from_slice(&0u16.to_le_bytes());
        assert!(matches!(decode(&empty), Err(RvlError::Size { .. })));
        let mut longer = payload.clone();
        longer.extend_from_slice(&[1, 0, 0, 0]);
        assert!(matches!(decode(&longer), Err(RvlError::Trailing(4))));
        // A run of 15 zeros in a 4-pixel image.
        let mut over = payload[..HEADER].to_vec();
        over.extend_from_slice(&(0xF1u32 << 24).to_le_bytes());
        assert!(matches!(decode(&over), Err(RvlError::Overrun { .. })));
        // Sixteen continuation nibbles: more than 32 bits.
        let mut wide = payload[..HEADER].to_vec();
        wide.extend_from_slice(&u32::MAX.to_le_bytes());
        wide.extend_from_slice(&u32::MAX.to_le_bytes());
        assert!(matches!(decode(&wide), Err(RvlError::Value(0))));
        // A difference below 0.
        let mut negative = payload[..HEADER].to_vec();
        negative.extend_from_slice(&(0x0110_0000u32).to_le_bytes());
        assert!(matches!(decode(&negative), Err(RvlError::Value(0))));
        assert!(matches!(decode_zstd(b"not zstd"), Err(RvlError::Zstd(_))));
    }

    /// Depth-like rows: runs of holes between runs of smooth or noisy values.
    fn depth_image() -> impl Strategy<Value = (u16, u16, Vec<u16>)> {
        (1u16..40, 1u16..20).prop_flat_map(|(w, h)| {
            let n = usize::from(w) * usize::from(h);
            let pixel = prop_oneof![
                3 => Just(0u16),
                3 => 900u16..1100,
                1 => any::<u16>(),
            ];
            (Just(w), Just(h), prop::collection::vec(pixel, n))
        })
    }

    proptest! {
        #[test]
        fn rvl_round_trips((w, h, values) in depth_image()) {
            let payload = rvl(w, h, &values);
            let back = decode(&payload).expect("decodes");
            prop_assert_eq!(&back.values, &values);
            let back = decode_zstd(&compress(&payload).expect("compresses")).expect("decodes");
            prop_assert_eq!(back.values, values);
        }

        #[test]
        fn any_bytes_decode_or_fail_cleanly(bytes in prop::collection::vec(any::<u8>(), 0..200)) {
            let _ = decode(&bytes);
            let _ = decode_zstd(&bytes);
        }
    }
}
