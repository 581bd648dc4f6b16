//! What the cloud decoders share: a bounded zstd decompression and a reader of
//! little-endian fields that reports where a payload ended too early.

use std::io::{self, Read as _};

/// A decoder's complaint about the bytes it was given.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum WireError {
    /// The zstd frame does not decode, or decompresses to more than the format allows.
    #[error("zstd: {0}")]
    Zstd(String),
    /// The data ends inside a field.
    #[error("the data ends at byte {at} inside `{field}`")]
    Truncated {
        /// Byte offset (in the decompressed data) of the field.
        at: usize,
        /// The field's name.
        field: &'static str,
    },
    /// A field holds a value the format does not allow.
    #[error("`{field}` at byte {at}: {why}")]
    Invalid {
        /// Byte offset (in the decompressed data) of the field.
        at: usize,
        /// The field's name.
        field: &'static str,
        /// What is wrong with it.
        why: String,
    },
    /// Bytes left after the last field.
    #[error("{0} bytes after the end of the data")]
    Trailing(usize),
}

/// Decompresses one zstd frame, refusing more than `limit` bytes of output.
pub(crate) fn unzstd(payload: &[u8], limit: usize) -> Result<Vec<u8>, WireError> {
    let zstd = |e: io::Error| WireError::Zstd(e.to_string());
    let mut out = Vec::new();
    zstd::stream::read::Decoder::with_buffer(payload)
        .map_err(zstd)?
        .take(limit as u64 + 1)
        .read_to_end(&mut out)
        .map_err(zstd)?;
    if out.len() > limit {
        return Err(WireError::Zstd(format!(
            "more than {limit} bytes decompressed"
        )));
    }
    Ok(out)
}

/// Reads fields front to back.
pub(crate) struct Reader<'a> {
    data: &'a [u8],
    at: usize,
}

impl<'a> Reader<'a> {
    pub(crate) fn new(data: &'a [u8]) -> Self {
        Self { data, at: 0 }
    }

    /// Where the next field starts.
    pub(crate) fn at(&self) -> usize {
        self.at
    }

    pub(crate) fn bytes(&mut self, n: usize, field: &'static str) -> Result<&'a [u8], WireError> {
        let end = self.at.checked_add(n).filter(|&end| end <= self.data.len());
        let end = end.ok_or(WireError::Truncated { at: self.at, field })?;
        let bytes = &self.data[self.at..end];
        self.at = end;
        Ok(bytes)
    }

    fn array<const N: usize>(&mut self, field: &'static str) -> Result<[u8; N], WireError> {
        let mut out = [0; N];
        out.copy_from_slice(self.bytes(N, field)?);
        Ok(out)
    }

    pub(crate) fn u8(&mut self, field: &'static str) -> Result<u8, WireError> {
        Ok(self.array::<1>(field)?[0])
    }

    pub(crate) fn u32(&mut self, field: &'static str) -> Result<u32, WireError> {
        self.array(field).map(u32::from_le_bytes)
    }

    pub(crate) fn u64(&mut self, field: &'static str) -> Result<u64, WireError> {
        self.array(field).map(u64::from_le_bytes)
    }

    /// `N` finite f32 values.
    pub(crate) fn finite<const N: usize>(
        &mut self,
        field: &'static str,
    ) -> Result<[f32; N], WireError> {
        let at = self.at;
        let mut out = [0.0; N];
        for v in &mut out {
            *v = f32::from_le_bytes(self.array(field)?);
        }
        if out.iter().all(|v| v.is_finite()) {
            Ok(out)
        } else {
            Err(self.invalid(at, field, format!("{out:?} is not finite")))
        }
    }

    /// A LEB128 number of at most 32 bits.
    pub(crate) fn varint(&mut self, field: &'static str) -> Result<u32, WireError> {
        let at = self.at;
        let mut value = 0u64;
        for shift in (0..35).step_by(7) {
            let byte = self.u8(field)?;
            value |= u64::from(byte & 0x7f) << shift;
            if byte & 0x80 == 0 {
                return u32::try_from(value)
                    .map_err(|_| self.invalid(at, field, "more than 32 bits".into()));
            }
        }
        Err(self.invalid(at, field, "more than 32 bits".into()))
    }

    /// A string of at most 255 bytes after its length byte, UTF-8.
    pub(crate) fn string(&mut self, field: &'static str) -> Result<String, WireError> {
        let at = self.at;
        let n = self.u8(field)?;
        let bytes = self.bytes(usize::from(n), field)?;
        String::from_utf8(bytes.to_vec()).map_err(|_| self.invalid(at, field, "not UTF-8".into()))
    }

    pub(crate) fn invalid(&self, at: usize, field: &'static str, why: String) -> WireError {
        WireError::Invalid { at, field, why }
    }

    /// Done: nothing may follow.
    pub(crate) fn finish(self) -> Result<(), WireError> {
        match self.data.len() - self.at {
            0 => Ok(()),
            n => Err(WireError::Trailing(n)),
        }
    }
}

/// Appends a length byte and `s` (at most 255 bytes; longer strings are cut at a
/// character boundary).
pub(crate) fn put_string(out: &mut Vec<u8>, s: &str) {
    let mut end = s.len().min(255);
    while !s.is_char_boundary(end) {
        end -= 1;
    }
    out.push(end as u8);
    out.extend_from_slice(&s.as_bytes()[..end]);
}

/// Appends `value` as LEB128.
pub(crate) fn put_varint(out: &mut Vec<u8>, mut value: u32) {
    loop {
        let low = (value & 0x7f) as u8;
        value >>= 7;
        if value == 0 {
            out.push(low);
            return;
        }
        out.push(low | 0x80);
    }
}

/// Appends little-endian f32 values.
pub(crate) fn put_f32s(out: &mut Vec<u8>, values: &[f32]) {
    for v in values {
        out.extend_from_slice(&v.to_le_bytes());
    }
}
