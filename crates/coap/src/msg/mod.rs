//! The CoAP message format (RFC 7252 §3): a checked zero-copy view over a datagram
//! ([`MessageView`]) and the validated owned form ([`Message`]). [`stream`] frames the
//! same code, token, options and payload for TCP, TLS and WebSockets (RFC 8323), and
//! [`signal`] holds the signalling messages only streams carry.
//!
//! Parsing never panics: [`MessageView::new_checked`] walks the whole datagram once and
//! every accessor after it only reads what was checked.

mod code;
pub mod option;
pub mod signal;
pub mod stream;

use std::fmt;

use bytes::{Bytes, BytesMut};

pub use code::Code;
pub use option::{BlockOpt, CoapOption, OptionNumber, OptionValue, Options};

/// The message type (RFC 7252 §3).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Type {
    /// Confirmable.
    Con,
    /// Non-confirmable.
    Non,
    /// Acknowledgement.
    Ack,
    /// Reset.
    Rst,
}

impl Type {
    fn from_bits(bits: u8) -> Self {
        match bits & 3 {
            0 => Self::Con,
            1 => Self::Non,
            2 => Self::Ack,
            _ => Self::Rst,
        }
    }

    fn bits(self) -> u8 {
        match self {
            Self::Con => 0,
            Self::Non => 1,
            Self::Ack => 2,
            Self::Rst => 3,
        }
    }
}

/// A token of 0 to 8 bytes (RFC 7252 §5.3.1), stored inline.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Default)]
pub struct Token {
    len: u8,
    bytes: [u8; 8],
}

impl Token {
    /// The empty token.
    pub const EMPTY: Self = Self {
        len: 0,
        bytes: [0; 8],
    };

    /// A token from up to 8 bytes; longer input gives `None`.
    pub fn new(bytes: &[u8]) -> Option<Self> {
        let mut t = Self {
            len: u8::try_from(bytes.len()).ok()?,
            bytes: [0; 8],
        };
        t.bytes.get_mut(..bytes.len())?.copy_from_slice(bytes);
        Some(t)
    }

    /// The token bytes.
    pub fn as_bytes(&self) -> &[u8] {
        &self.bytes[..usize::from(self.len.min(8))]
    }

    /// Token length in bytes.
    pub fn len(&self) -> usize {
        self.as_bytes().len()
    }

    /// Whether the token is empty.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }
}

impl fmt::Debug for Token {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("0x")?;
        for b in self.as_bytes() {
            write!(f, "{b:02x}")?;
        }
        Ok(())
    }
}

/// Why a datagram is not a valid CoAP message.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("{kind} at byte {offset}")]
pub struct DecodeError {
    /// What is wrong.
    pub kind: DecodeErrorKind,
    /// Where in the datagram it was found.
    pub offset: usize,
    /// The header, when the first four bytes could be read: the reaction depends on it.
    pub header: Option<(Type, u16)>,
}

/// The kinds of [`DecodeError`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum DecodeErrorKind {
    /// Fewer than the 4 header bytes.
    #[error("datagram shorter than the 4-byte header")]
    TooShort,
    /// Version other than 1 (RFC 7252 §3: silently ignored).
    #[error("unknown version")]
    Version,
    /// Token length 9-15 (RFC 7252 §3: a message format error).
    #[error("token length above 8")]
    TokenLength,
    /// The message ends inside the token, an option header or an option value.
    #[error("message truncated")]
    Truncated,
    /// Option delta or length nibble 15 outside a payload marker (RFC 7252 §3.1).
    #[error("reserved option nibble 15")]
    ReservedNibble,
    /// Option number above 65535.
    #[error("option number out of range")]
    OptionNumber,
    /// A payload marker followed by no payload (RFC 7252 §3).
    #[error("payload marker with empty payload")]
    EmptyPayload,
    /// An Empty message (code 0.00) with a token, options or payload (RFC 7252 §4.1).
    #[error("empty message with content")]
    EmptyWithContent,
    /// Code classes 1, 6 and 7 are reserved (RFC 7252 §12.1); over a stream, class 7 is
    /// signalling (RFC 8323 §5).
    #[error("reserved code class")]
    ReservedClass,
}

/// What an endpoint does with a datagram that failed to decode: the single mapping from
/// decode errors to the wire (RFC 7252 §4.2, §4.3).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Reaction {
    /// Silently ignore.
    Drop,
    /// Reject with a Reset carrying this message ID.
    Reset(u16),
}

impl From<&DecodeError> for Reaction {
    fn from(e: &DecodeError) -> Self {
        match (e.kind, e.header) {
            // Unknown versions are silently ignored; so is anything we cannot even read
            // the message ID of, and ACK/RST (never answered by RST, §4.2/§4.3).
            (DecodeErrorKind::Version | DecodeErrorKind::TooShort, _) => Self::Drop,
            (_, Some((Type::Con | Type::Non, mid))) => Self::Reset(mid),
            _ => Self::Drop,
        }
    }
}

/// A checked view of a datagram that holds one CoAP message.
#[derive(Debug, Clone, Copy)]
pub struct MessageView<'a> {
    data: &'a [u8],
    token_len: usize,
    options_end: usize,
    payload_start: usize,
}

impl<'a> MessageView<'a> {
    /// Checks the whole datagram: header, token, every option header and value, the payload
    /// marker. On success every accessor is infallible.
    pub fn new_checked(data: &'a [u8]) -> Result<Self, DecodeError> {
        let err = |kind, offset, header| DecodeError {
            kind,
            offset,
            header,
        };
        let [b0, code, m0, m1, ..] = *data else {
            return Err(err(DecodeErrorKind::TooShort, 0, None));
        };
        if b0 >> 6 != 1 {
            return Err(err(DecodeErrorKind::Version, 0, None));
        }
        let header = Some((Type::from_bits(b0 >> 4), u16::from_be_bytes([m0, m1])));
        let token_len = usize::from(b0 & 0x0f);
        if token_len > 8 {
            return Err(err(DecodeErrorKind::TokenLength, 0, header));
        }
        if matches!(code >> 5, 1 | 6 | 7) {
            return Err(err(DecodeErrorKind::ReservedClass, 1, header));
        }
        let pos = 4 + token_len;
        if data.len() < pos {
            return Err(err(DecodeErrorKind::Truncated, data.len(), header));
        }
        let (options_end, payload_start) =
            check_options(data, pos).map_err(|(kind, offset)| err(kind, offset, header))?;
        let view = Self {
            data,
            token_len,
            options_end,
            payload_start,
        };
        if code == 0 && (token_len != 0 || data.len() > 4) {
            return Err(err(DecodeErrorKind::EmptyWithContent, 4, header));
        }
        Ok(view)
    }

    /// Message type.
    pub fn ty(&self) -> Type {
        Type::from_bits(self.data[0] >> 4)
    }

    /// Code.
    pub fn code(&self) -> Code {
        Code(self.data[1])
    }

    /// Message ID.
    pub fn message_id(&self) -> u16 {
        u16::from_be_bytes([self.data[2], self.data[3]])
    }

    /// Token.
    pub fn token(&self) -> Token {
        // NOTE(unwrap): token_len <= 8 was checked in new_checked.
        Token::new(&self.data[4..4 + self.token_len]).unwrap_or_default()
    }

    /// Options in wire order, as (number, value).
    pub fn options(&self) -> OptionIter<'a> {
        OptionIter {
            data: &self.data[4 + self.token_len..self.options_end],
            number: 0,
        }
    }

    /// Payload (empty when there is no payload marker).
    pub fn payload(&self) -> &'a [u8] {
        &self.data[self.payload_start..]
    }
}

/// Checks the options, payload marker and payload that fill `data` from `pos` on (RFC 7252
/// §3, §3.1), the part of a message both framings share: the end of the options and the
/// start of the payload (both `data.len()` without a payload), or what is wrong and where.
fn check_options(data: &[u8], mut pos: usize) -> Result<(usize, usize), (DecodeErrorKind, usize)> {
    let mut number: u32 = 0;
    while let Some(&byte) = data.get(pos) {
        if byte == 0xff {
            if pos + 1 == data.len() {
                return Err((DecodeErrorKind::EmptyPayload, pos));
            }
            return Ok((pos, pos + 1));
        }
        let start = pos;
        pos += 1;
        let delta = read_ext(data, &mut pos, byte >> 4).map_err(|kind| (kind, start))?;
        let len = read_ext(data, &mut pos, byte & 0x0f).map_err(|kind| (kind, start))?;
        number += delta;
        if number > u32::from(u16::MAX) {
            return Err((DecodeErrorKind::OptionNumber, start));
        }
        pos += len as usize;
        if pos > data.len() {
            return Err((DecodeErrorKind::Truncated, start));
        }
    }
    Ok((data.len(), data.len()))
}

/// Reads the 4-bit delta/length field and its extension (RFC 7252 §3.1).
fn read_ext(data: &[u8], pos: &mut usize, nibble: u8) -> Result<u32, DecodeErrorKind> {
    match nibble {
        0..=12 => Ok(u32::from(nibble)),
        13 => {
            let b = *data.get(*pos).ok_or(DecodeErrorKind::Truncated)?;
            *pos += 1;
            Ok(u32::from(b) + 13)
        }
        14 => {
            let b = data.get(*pos..*pos + 2).ok_or(DecodeErrorKind::Truncated)?;
            *pos += 2;
            Ok(u32::from(u16::from_be_bytes([b[0], b[1]])) + 269)
        }
        _ => Err(DecodeErrorKind::ReservedNibble),
    }
}

/// Iterates the options of a checked view.
#[derive(Debug, Clone)]
pub struct OptionIter<'a> {
    data: &'a [u8],
    number: u16,
}

impl<'a> Iterator for OptionIter<'a> {
    type Item = (OptionNumber, &'a [u8]);

    fn next(&mut self) -> Option<Self::Item> {
        let (&byte, _) = self.data.split_first()?;
        let mut pos = 1;
        // The view was checked, so these cannot fail; stop quietly if they ever did.
        let delta = read_ext(self.data, &mut pos, byte >> 4).ok()?;
        let len = read_ext(self.data, &mut pos, byte & 0x0f).ok()? as usize;
        let value = self.data.get(pos..pos + len)?;
        self.data = &self.data[pos + len..];
        self.number = self.number.checked_add(u16::try_from(delta).ok()?)?;
        Some((OptionNumber(self.number), value))
    }
}

/// A validated CoAP message that owns its data.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Message {
    /// Message type.
    pub ty: Type,
    /// Request method, response code, or 0.00 for Empty.
    pub code: Code,
    /// Message ID.
    pub message_id: u16,
    /// Token.
    pub token: Token,
    /// Options, sorted by number.
    pub options: Options,
    /// Payload.
    pub payload: Bytes,
}

impl Message {
    /// An Empty message (ACK, RST, or a CON ping).
    pub fn empty(ty: Type, message_id: u16) -> Self {
        Self {
            ty,
            code: Code::EMPTY,
            message_id,
            token: Token::EMPTY,
            options: Options::new(),
            payload: Bytes::new(),
        }
    }

    /// Decodes a datagram.
    pub fn decode(data: &[u8]) -> Result<Self, DecodeError> {
        let mut msg = Self::empty(Type::Con, 0);
        let payload = msg.decode_in_place(data)?;
        msg.payload = Bytes::copy_from_slice(payload);
        Ok(msg)
    }

    /// Decodes a datagram into this message, all but the payload: the message's payload is
    /// left empty and the payload's bytes are returned. A block-wise receiver copies each
    /// block once, into the body, and the message (a few hundred bytes with its inline
    /// options) is filled where it lies rather than built and moved.
    pub(crate) fn decode_in_place<'d>(&mut self, data: &'d [u8]) -> Result<&'d [u8], DecodeError> {
        let view = MessageView::new_checked(data)?;
        self.ty = view.ty();
        self.code = view.code();
        self.message_id = view.message_id();
        self.token = view.token();
        self.options.fill_in_wire_order(view.options());
        self.payload = Bytes::new();
        Ok(view.payload())
    }

    /// The message as an [`Outgoing`] with nothing set over its options.
    pub(crate) fn outgoing(&self) -> Outgoing<'_> {
        Outgoing {
            ty: self.ty,
            code: self.code,
            message_id: self.message_id,
            token: self.token,
            options: &self.options,
            uints: &[],
            payload: &self.payload,
        }
    }

    /// The exact number of bytes [`Message::encode`] gives.
    pub fn encoded_len(&self) -> usize {
        self.outgoing().encoded_len()
    }

    /// Encodes into a new buffer.
    pub fn encode(&self) -> Vec<u8> {
        self.outgoing().encode()
    }
}

/// A message to encode, borrowed from its parts: options plus uint options set over them.
/// A client builds each block's request this way from the request it keeps, without
/// copying the request's options into a new [`Message`].
#[derive(Debug, Clone, Copy)]
pub(crate) struct Outgoing<'a> {
    pub(crate) ty: Type,
    pub(crate) code: Code,
    pub(crate) message_id: u16,
    pub(crate) token: Token,
    /// Options, sorted by number.
    pub(crate) options: &'a Options,
    /// Uint options set over `options`, sorted by number: each replaces every instance
    /// of its number in `options` (as [`Options::set_uint`] would).
    pub(crate) uints: &'a [(OptionNumber, u32)],
    pub(crate) payload: &'a [u8],
}

impl Outgoing<'_> {
    /// Calls `f` with the bytes before the payload: header, token, options and the payload
    /// marker.
    fn with_head<R>(&self, f: impl FnOnce(&[u8]) -> R) -> R {
        debug_assert!(
            self.uints.is_sorted_by_key(|(n, _)| *n),
            "uints out of order"
        );
        // A uint option takes at most 1 + 2 + 4 bytes.
        let options = 7 * self.uints.len()
            + self
                .options
                .iter()
                .map(|o| 5 + o.value.len())
                .sum::<usize>();
        let header = (self.ty, self.code, self.message_id, self.token);
        let write_options = |w: &mut HeadWriter<'_>| {
            let mut uints = self.uints;
            for o in self.options.iter() {
                if self.uints.iter().any(|(n, _)| *n == o.number) {
                    continue;
                }
                while let [(number, v), rest @ ..] = uints
                    && *number < o.number
                {
                    w.uint(*number, *v);
                    uints = rest;
                }
                w.option(o.number, &o.value);
            }
            for &(number, v) in uints {
                w.uint(number, v);
            }
            if !self.payload.is_empty() {
                w.bytes(&[0xff]);
            }
        };
        with_head(options, header, write_options, f)
    }

    /// The exact number of bytes the encoding takes.
    pub(crate) fn encoded_len(&self) -> usize {
        self.with_head(<[u8]>::len) + self.payload.len()
    }

    /// Appends the encoded message to `out`.
    pub(crate) fn encode_into(&self, out: &mut BytesMut) {
        self.with_head(|head| out.extend_from_slice(head));
        out.extend_from_slice(self.payload);
    }

    /// Encodes into a new buffer.
    pub(crate) fn encode(&self) -> Vec<u8> {
        let mut out = Vec::new();
        self.with_head(|head| {
            out.reserve_exact(head.len() + self.payload.len());
            out.extend_from_slice(head);
        });
        out.extend_from_slice(self.payload);
        out
    }
}

/// The options of a message sent many times over with only its header, token, payload and
/// one uint option changed: each block of a block-wise transfer (the request's Block2 on
/// a client, the stored response's Block2 on a server). They are encoded once; each block
/// then copies them around its own option instead of encoding every option again.
#[derive(Debug, Clone)]
pub(crate) struct BlockHead {
    /// The options before `number`, then those after it (encoded as if `number` came
    /// between).
    bytes: Vec<u8>,
    split: usize,
    /// The number of the last option before `number` (0 for none).
    prev: u16,
    number: OptionNumber,
}

impl BlockHead {
    /// The bytes it holds.
    pub(crate) fn held(&self) -> usize {
        size_of::<Self>() + self.bytes.capacity()
    }

    /// The encoding of `options` around `number`; instances of `number` itself are left
    /// out (each block sets its own).
    pub(crate) fn new(options: &Options, number: OptionNumber) -> Self {
        let bound = options.iter().map(|o| 5 + o.value.len()).sum::<usize>();
        let mut bytes = vec![0; bound];
        let mut w = HeadWriter {
            out: &mut bytes,
            pos: 0,
            prev: 0,
        };
        for o in options.iter().filter(|o| o.number < number) {
            w.option(o.number, &o.value);
        }
        let (split, prev) = (w.pos, w.prev);
        w.prev = number.0;
        for o in options.iter().filter(|o| o.number > number) {
            w.option(o.number, &o.value);
        }
        let len = w.pos;
        bytes.truncate(len);
        Self {
            bytes,
            split,
            prev,
            number,
        }
    }

    /// Appends the message with these options and `value` for the block option.
    pub(crate) fn encode_into(
        &self,
        out: &mut BytesMut,
        header: Header,
        value: u32,
        payload: &[u8],
    ) {
        // A uint option takes at most 1 + 2 + 4 bytes.
        let options = self.bytes.len() + 7;
        let write_options = |w: &mut HeadWriter<'_>| {
            w.bytes(&self.bytes[..self.split]);
            w.prev = self.prev;
            w.uint(self.number, value);
            w.bytes(&self.bytes[self.split..]);
            if !payload.is_empty() {
                w.bytes(&[0xff]);
            }
        };
        with_head(options, header, write_options, |head| {
            out.extend_from_slice(head);
        });
        out.extend_from_slice(payload);
    }
}

/// A message's type, code, message ID and token.
pub(crate) type Header = (Type, Code, u16, Token);

/// Puts a message's head together (header, token, then what `write_options` adds: the
/// options and the payload marker, at most `options` bytes) and hands it to `f`. It is
/// written on the stack, byte by byte, unless the options are long, rather than through
/// a buffer call per field.
fn with_head<R>(
    options: usize,
    (ty, code, message_id, token): Header,
    write_options: impl FnOnce(&mut HeadWriter<'_>),
    f: impl FnOnce(&[u8]) -> R,
) -> R {
    const ON_STACK: usize = 256;
    let bound = 4 + 8 + options + 1;
    let mut stack = [0u8; ON_STACK];
    let mut heap = Vec::new();
    let out = if bound <= ON_STACK {
        &mut stack[..]
    } else {
        heap.resize(bound, 0);
        &mut heap[..]
    };
    let token = token.as_bytes();
    out[0] = 0x40 | (ty.bits() << 4) | token.len() as u8;
    out[1] = code.0;
    out[2..4].copy_from_slice(&message_id.to_be_bytes());
    out[4..4 + token.len()].copy_from_slice(token);
    let mut w = HeadWriter {
        out,
        pos: 4 + token.len(),
        prev: 0,
    };
    write_options(&mut w);
    let len = w.pos;
    f(&w.out[..len])
}

/// Writes options one after the other (RFC 7252 §3.1).
struct HeadWriter<'a> {
    out: &'a mut [u8],
    pos: usize,
    prev: u16,
}

impl HeadWriter<'_> {
    #[inline]
    fn option(&mut self, number: OptionNumber, value: &[u8]) {
        let delta = u32::from(number.0 - self.prev);
        self.prev = number.0;
        // Values longer than 65535 + 269 bytes cannot be expressed; the option registry
        // caps every known option far below, and callers building unknown options get
        // them truncated rather than a corrupt datagram.
        let value = &value[..value.len().min(MAX_OPTION_LEN)];
        let len = value.len() as u32;
        self.out[self.pos] = (nibble(delta) << 4) | nibble(len);
        self.pos += 1;
        self.ext(delta);
        self.ext(len);
        self.bytes(value);
    }

    /// A uint option (RFC 7252 §3.2: no leading zero bytes, zero is the empty value).
    #[inline]
    fn uint(&mut self, number: OptionNumber, v: u32) {
        self.option(number, &v.to_be_bytes()[(v.leading_zeros() / 8) as usize..]);
    }

    /// Bytes already encoded.
    #[inline]
    fn bytes(&mut self, bytes: &[u8]) {
        self.out[self.pos..self.pos + bytes.len()].copy_from_slice(bytes);
        self.pos += bytes.len();
    }

    /// The extension of a delta or length.
    #[inline]
    fn ext(&mut self, v: u32) {
        match v {
            0..=12 => {}
            13..=268 => {
                self.out[self.pos] = (v - 13) as u8;
                self.pos += 1;
            }
            _ => self.bytes(&((v - 269).min(0xffff) as u16).to_be_bytes()),
        }
    }
}

/// The exact number of bytes [`write_options`] appends for `options`.
fn options_len(options: &Options) -> usize {
    let ext = |v: usize| match nibble(v as u32) {
        13 => 1,
        14 => 2,
        _ => 0,
    };
    let mut prev = 0;
    options
        .iter()
        .map(|o| {
            let delta = usize::from(o.number.0 - prev);
            prev = o.number.0;
            let len = o.value.len().min(MAX_OPTION_LEN);
            1 + ext(delta) + ext(len) + len
        })
        .sum()
}

/// Appends `options` in wire order (RFC 7252 §3.1), as a datagram carries them after its
/// token; a stream frame carries them the same way (RFC 8323 §3.2).
fn write_options(options: &Options, out: &mut Vec<u8>) {
    let start = out.len();
    out.resize(
        start + options.iter().map(|o| 5 + o.value.len()).sum::<usize>(),
        0,
    );
    let mut w = HeadWriter {
        out: &mut out[start..],
        pos: 0,
        prev: 0,
    };
    for o in options.iter() {
        w.option(o.number, &o.value);
    }
    let len = w.pos;
    out.truncate(start + len);
}

/// The longest option value the wire format can express (RFC 7252 §3.1: 14 + 2 bytes).
const MAX_OPTION_LEN: usize = 65535 + 269;

fn nibble(v: u32) -> u8 {
    match v {
        0..=12 => v as u8,
        13..=268 => 13,
        _ => 14,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_block_head_encodes_as_the_whole_message_would() {
        let mut around = Options::new();
        around.set_path("/a/segment-longer-than-twelve/c");
        around.set_uint(OptionNumber::ACCEPT, 50);
        // Replaced by each block's own Block2.
        around.set_uint(OptionNumber::BLOCK2, 0x1234);
        around.set_uint(OptionNumber::SIZE2, 70_000);
        around.push(OptionNumber(2000), b"far");
        let mut before = Options::new();
        before.set(OptionNumber::ETAG, b"etag");
        let mut after = Options::new();
        after.set_uint(OptionNumber::SIZE2, 5);
        let token = Token::new(b"tok").unwrap_or_default();
        for options in [Options::new(), around, before, after] {
            let head = BlockHead::new(&options, OptionNumber::BLOCK2);
            for (value, payload) in [(0, &b""[..]), (0x76, b"x"), (0xfffff6, &[7; 300][..])] {
                let whole = Outgoing {
                    ty: Type::Ack,
                    code: Code::CONTENT,
                    message_id: 0xbeef,
                    token,
                    options: &options,
                    uints: &[(OptionNumber::BLOCK2, value)],
                    payload,
                };
                let mut out = BytesMut::new();
                let header = (Type::Ack, Code::CONTENT, 0xbeef, token);
                head.encode_into(&mut out, header, value, payload);
                assert_eq!(&out[..], &whole.encode()[..], "{options:?} {value}");
                assert_eq!(out.len(), whole.encoded_len());
                let back = Message::decode(&out).unwrap();
                assert_eq!(back.options.block2().map(BlockOpt::as_uint), Some(value));
            }
        }
    }
}
