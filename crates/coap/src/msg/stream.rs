//! The framing of CoAP over reliable transports (RFC 8323): TCP and TLS (§3.2) and
//! WebSockets (§4), beside the datagram framing of [`MessageView`](super::MessageView).
//!
//! **The transport-neutral message.** A [`Frame`] is what every framing carries: code,
//! token, options and payload. [`Message`] stays the datagram message: its type and message
//! ID belong to the datagram's reliability layer (CON/ACK, deduplication), which a stream
//! replaces with its own (RFC 8323 §3.2 drops both fields). The two meet through
//! `From<Message> for Frame`, which drops type and ID, and [`Frame::into_message`], which
//! supplies them; the endpoint keeps working on [`Message`] until a stream connection
//! drives it. Both framings encode and check options with the same functions of
//! [`msg`](super), so an option has one wire form whichever transport carries it.
//!
//! **TCP and TLS** ([`Frame::encode`], [`decode`]): a first byte of Len (4 bits) and TKL
//! (4 bits), an extended length of 0, 1, 2 or 4 bytes as Len 0-12, 13, 14 or 15 choose,
//! then the code and the token. The length counts the options, the payload marker and the
//! payload; the extended length holds it minus 13, 269 or 65805. [`decode`] works on a
//! buffer that may end inside a frame and answers how many more bytes it needs.
//!
//! **WebSockets** ([`Frame::encode_ws`], [`decode_ws`]): the same header with Len 0 and
//! no extended length; each WebSocket binary message holds one CoAP message, whose length
//! the WebSocket framing gives.
//!
//! **Message size.** The limit a receiver announces with Max-Message-Size
//! ([`Csm`](super::signal::Csm)) is counted here over the whole frame, from its first byte
//! to its last. [`decode`] refuses a frame over the caller's limit as soon as its length
//! can be read, before its bytes arrive.
//!
//! Token lengths above 8 (TKL 9-15) are refused: RFC 8974's extended tokens are not
//! supported. A frame of code 0.00 decodes whatever it carries: over a stream an Empty
//! message is ignored by its receiver (RFC 8323 §3.4), not answered.

use bytes::Bytes;

use super::{
    Code, DecodeErrorKind, Message, OptionIter, Options, Token, Type, check_options, options_len,
    write_options,
};

/// Len values 13, 14 and 15 announce an extended length of 1, 2 or 4 bytes holding the
/// length minus these offsets (RFC 8323 §3.2).
const OFFSET_8: u64 = 13;
/// See [`OFFSET_8`].
const OFFSET_16: u64 = 269;
/// See [`OFFSET_8`].
const OFFSET_32: u64 = 65805;

/// The longest length (options, payload marker and payload) a frame can express: the
/// 4-byte extended length plus its offset.
const MAX_BODY: u64 = u32::MAX as u64 + OFFSET_32;

/// A CoAP message without the datagram's type and message ID: what a stream frame or a
/// WebSocket message carries (RFC 8323 §3.2, §4.2). Signalling messages (codes 7.xx) are
/// frames too; [`Signal`](super::signal::Signal) reads and writes their options.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Frame {
    /// Request method, response code, signalling code, or 0.00 for Empty.
    pub code: Code,
    /// Token.
    pub token: Token,
    /// Options, sorted by number. In a signalling message their numbers are the
    /// signalling code's own (RFC 8323 §5.2).
    pub options: Options,
    /// Payload.
    pub payload: Bytes,
}

impl From<Message> for Frame {
    /// The message's code, token, options and payload; its type and ID are dropped.
    fn from(m: Message) -> Self {
        Self {
            code: m.code,
            token: m.token,
            options: m.options,
            payload: m.payload,
        }
    }
}

impl Frame {
    /// A frame of `code` with no token, options or payload.
    pub fn new(code: Code) -> Self {
        Self {
            code,
            token: Token::EMPTY,
            options: Options::new(),
            payload: Bytes::new(),
        }
    }

    /// The datagram message of this frame, with the type and message ID a datagram needs.
    pub fn into_message(self, ty: Type, message_id: u16) -> Message {
        Message {
            ty,
            code: self.code,
            message_id,
            token: self.token,
            options: self.options,
            payload: self.payload,
        }
    }

    /// The payload that fits a frame: all of it unless options and payload together pass
    /// what the 4-byte extended length can express (4 GiB), past which it is cut, as the
    /// datagram writer cuts option values it cannot express.
    fn payload_that_fits(&self, options: usize) -> &[u8] {
        let room = MAX_BODY.saturating_sub(options as u64 + 1);
        let fits = usize::try_from(room).unwrap_or(usize::MAX);
        &self.payload[..self.payload.len().min(fits)]
    }

    /// The length the Len field counts: options, payload marker and payload.
    fn body_len(&self) -> usize {
        let options = options_len(&self.options);
        match self.payload_that_fits(options).len() {
            0 => options,
            n => options + 1 + n,
        }
    }

    /// The exact number of bytes [`Frame::encode`] gives.
    pub fn encoded_len(&self) -> usize {
        let body = self.body_len();
        1 + length_field(body).2 + 1 + self.token.len() + body
    }

    /// The exact number of bytes [`Frame::encode_ws`] gives.
    pub fn ws_encoded_len(&self) -> usize {
        2 + self.token.len() + self.body_len()
    }

    /// Appends the frame for TCP or TLS (RFC 8323 §3.2).
    pub fn encode_into(&self, out: &mut Vec<u8>) {
        let body = self.body_len();
        let (len, ext, ext_len) = length_field(body);
        out.reserve(1 + ext_len + 1 + self.token.len() + body);
        out.push((len << 4) | self.token.len() as u8);
        out.extend_from_slice(&ext[..ext_len]);
        self.encode_after_length(out);
    }

    /// Encodes the frame for TCP or TLS into a new buffer.
    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::new();
        self.encode_into(&mut out);
        out
    }

    /// Encodes the frame as one WebSocket message (RFC 8323 §4.2): Len 0, no extended
    /// length.
    pub fn encode_ws(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(self.ws_encoded_len());
        out.push(self.token.len() as u8);
        self.encode_after_length(&mut out);
        out
    }

    /// Code, token, options, payload marker and payload: the part both framings share.
    fn encode_after_length(&self, out: &mut Vec<u8>) {
        out.push(self.code.0);
        out.extend_from_slice(self.token.as_bytes());
        write_options(&self.options, out);
        let payload = self.payload_that_fits(options_len(&self.options));
        if !payload.is_empty() {
            out.push(0xff);
            out.extend_from_slice(payload);
        }
    }
}

/// The Len nibble for a body of `body` bytes, the extended length's bytes and how many of
/// them are used.
fn length_field(body: usize) -> (u8, [u8; 4], usize) {
    let body = body as u64;
    match body {
        0..=12 => (body as u8, [0; 4], 0),
        13..=268 => (13, [(body - OFFSET_8) as u8, 0, 0, 0], 1),
        269..=65804 => {
            let [a, b] = ((body - OFFSET_16) as u16).to_be_bytes();
            (14, [a, b, 0, 0], 2)
        }
        _ => (
            15,
            ((body.min(MAX_BODY) - OFFSET_32) as u32).to_be_bytes(),
            4,
        ),
    }
}

/// What [`decode`] found at the start of a buffer.
#[derive(Debug, Clone, PartialEq, Eq)]
#[expect(
    clippy::large_enum_variant,
    reason = "a frame is moved out once; boxing it would add an allocation per message, \
              which the inline Options exist to avoid"
)]
pub enum Decoded {
    /// No whole frame yet: at least `needed` more bytes are wanted, exactly that many once
    /// the buffer holds the frame's length field.
    Incomplete {
        /// Bytes still missing.
        needed: usize,
    },
    /// One frame, which took the first `consumed` bytes of the buffer.
    Frame {
        /// The frame.
        frame: Frame,
        /// Bytes it took.
        consumed: usize,
    },
}

/// Why bytes are not a valid frame. Any of them ends a stream connection: once a frame is
/// wrong, where the next one starts cannot be trusted.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum FrameError {
    /// The frame is longer than the receiver's limit (its Max-Message-Size).
    #[error("{size}-byte message over the limit of {max} bytes")]
    TooLarge {
        /// The frame's whole length, as its header gives it.
        size: u64,
        /// The limit.
        max: usize,
    },
    /// A WebSocket message whose Len nibble is not 0 (RFC 8323 §4.2).
    #[error("WebSocket message with Len {0}, not 0")]
    WebSocketLength(u8),
    /// A format error shared with datagrams, and where in the frame it was found.
    #[error("{kind} at byte {offset}")]
    Malformed {
        /// What is wrong.
        kind: DecodeErrorKind,
        /// Where, counted from the frame's first byte.
        offset: usize,
    },
}

impl FrameError {
    fn malformed(kind: DecodeErrorKind, offset: usize) -> Self {
        Self::Malformed { kind, offset }
    }
}

/// Decodes the frame at the start of `buf` (TCP or TLS, RFC 8323 §3.2), refusing one
/// longer than `max_message_size` bytes. The bytes after the frame are left for the next
/// call; a buffer that ends inside the frame gives [`Decoded::Incomplete`].
pub fn decode(buf: &[u8], max_message_size: usize) -> Result<Decoded, FrameError> {
    let Some(&first) = buf.first() else {
        return Ok(Decoded::Incomplete { needed: 1 });
    };
    let token_len = usize::from(first & 0x0f);
    if token_len > 8 {
        return Err(FrameError::malformed(DecodeErrorKind::TokenLength, 0));
    }
    let ext_len = match first >> 4 {
        13 => 1,
        14 => 2,
        15 => 4,
        _ => 0,
    };
    let code_at = 1 + ext_len;
    let Some(ext) = buf.get(1..code_at) else {
        let needed = code_at + 1 + token_len - buf.len();
        return Ok(Decoded::Incomplete { needed });
    };
    let body = match *ext {
        [a] => u64::from(a) + OFFSET_8,
        [a, b] => u64::from(u16::from_be_bytes([a, b])) + OFFSET_16,
        [a, b, c, d] => u64::from(u32::from_be_bytes([a, b, c, d])) + OFFSET_32,
        _ => u64::from(first >> 4),
    };
    let size = (code_at + 1 + token_len) as u64 + body;
    if size > max_message_size as u64 {
        return Err(FrameError::TooLarge {
            size,
            max: max_message_size,
        });
    }
    // Not over max_message_size, so it fits a usize.
    let size = size as usize;
    let Some(data) = buf.get(..size) else {
        return Ok(Decoded::Incomplete {
            needed: size - buf.len(),
        });
    };
    let frame = parse(data, code_at, token_len)?;
    Ok(Decoded::Frame {
        frame,
        consumed: size,
    })
}

/// Decodes one WebSocket message (RFC 8323 §4.2), refusing one longer than
/// `max_message_size` bytes.
pub fn decode_ws(message: &[u8], max_message_size: usize) -> Result<Frame, FrameError> {
    if message.len() > max_message_size {
        return Err(FrameError::TooLarge {
            size: message.len() as u64,
            max: max_message_size,
        });
    }
    let Some(&first) = message.first() else {
        return Err(FrameError::malformed(DecodeErrorKind::Truncated, 0));
    };
    if first >> 4 != 0 {
        return Err(FrameError::WebSocketLength(first >> 4));
    }
    let token_len = usize::from(first & 0x0f);
    if token_len > 8 {
        return Err(FrameError::malformed(DecodeErrorKind::TokenLength, 0));
    }
    parse(message, 1, token_len)
}

/// The frame that is exactly `data`, its code at `code_at`.
fn parse(data: &[u8], code_at: usize, token_len: usize) -> Result<Frame, FrameError> {
    let token_at = code_at + 1;
    let options_at = token_at + token_len;
    let (Some(&code), Some(token)) = (data.get(code_at), data.get(token_at..options_at)) else {
        return Err(FrameError::malformed(
            DecodeErrorKind::Truncated,
            data.len(),
        ));
    };
    let code = Code(code);
    if matches!(code.class(), 1 | 6) {
        return Err(FrameError::malformed(
            DecodeErrorKind::ReservedClass,
            code_at,
        ));
    }
    let (options_end, payload_start) =
        check_options(data, options_at).map_err(|(kind, at)| FrameError::malformed(kind, at))?;
    let mut options = Options::new();
    options.fill_in_wire_order(OptionIter {
        data: &data[options_at..options_end],
        number: 0,
    });
    Ok(Frame {
        code,
        token: Token::new(token).unwrap_or_default(),
        options,
        payload: Bytes::copy_from_slice(&data[payload_start..]),
    })
}
