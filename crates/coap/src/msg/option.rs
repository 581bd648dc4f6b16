//! Options: numbers and their properties (RFC 7252 §5.4, §12.2), the owned option list and
//! the typed values that the rest of the stack reads (Block, Content-Format, ...).

use std::fmt;

use smallvec::SmallVec;

use crate::content_format::ContentFormat;

/// An option number (RFC 7252 §5.4.6). Odd numbers are critical.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct OptionNumber(pub u16);

/// How an option's value is encoded (RFC 7252 §3.2).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ValueFormat {
    /// Zero-length value.
    Empty,
    /// An opaque byte sequence.
    Opaque,
    /// A non-negative integer in network byte order, without leading zero bytes.
    Uint,
    /// A UTF-8 string (Net-Unicode, RFC 5198).
    String,
}

/// What the stack knows about one registered option.
#[derive(Debug, Clone, Copy)]
pub struct OptionInfo {
    /// Registered name, as in the IANA registry.
    pub name: &'static str,
    /// Value format.
    pub format: ValueFormat,
    /// Smallest allowed value length in bytes.
    pub min_len: u16,
    /// Largest allowed value length in bytes.
    pub max_len: u16,
    /// Whether the option may occur more than once.
    pub repeatable: bool,
}

macro_rules! options {
    ($($(#[$doc:meta])* $konst:ident = $num:literal, $name:literal, $fmt:ident, $min:literal..=$max:literal, $rep:literal;)*) => {
        impl OptionNumber {
            $($(#[$doc])* pub const $konst: Self = Self($num);)*

            /// The registry entry of this number, if the stack knows it.
            pub fn info(self) -> Option<&'static OptionInfo> {
                match self.0 {
                    $($num => Some(&OptionInfo {
                        name: $name,
                        format: ValueFormat::$fmt,
                        min_len: $min,
                        max_len: $max,
                        repeatable: $rep,
                    }),)*
                    _ => None,
                }
            }
        }
    };
}

options! {
    /// If-Match, RFC 7252 §5.10.8.1.
    IF_MATCH = 1, "If-Match", Opaque, 0..=8, true;
    /// Uri-Host, RFC 7252 §5.10.1.
    URI_HOST = 3, "Uri-Host", String, 1..=255, false;
    /// ETag, RFC 7252 §5.10.6.
    ETAG = 4, "ETag", Opaque, 1..=8, true;
    /// If-None-Match, RFC 7252 §5.10.8.2.
    IF_NONE_MATCH = 5, "If-None-Match", Empty, 0..=0, false;
    /// Observe, RFC 7641 §2.
    OBSERVE = 6, "Observe", Uint, 0..=3, false;
    /// Uri-Port, RFC 7252 §5.10.1.
    URI_PORT = 7, "Uri-Port", Uint, 0..=2, false;
    /// Location-Path, RFC 7252 §5.10.7.
    LOCATION_PATH = 8, "Location-Path", String, 0..=255, true;
    /// OSCORE, RFC 8613 §2.
    OSCORE = 9, "OSCORE", Opaque, 0..=255, false;
    /// Uri-Path, RFC 7252 §5.10.1.
    URI_PATH = 11, "Uri-Path", String, 0..=255, true;
    /// Content-Format, RFC 7252 §5.10.3.
    CONTENT_FORMAT = 12, "Content-Format", Uint, 0..=2, false;
    /// Max-Age, RFC 7252 §5.10.5.
    MAX_AGE = 14, "Max-Age", Uint, 0..=4, false;
    /// Uri-Query, RFC 7252 §5.10.1.
    URI_QUERY = 15, "Uri-Query", String, 0..=255, true;
    /// Hop-Limit, RFC 8768 §3.
    HOP_LIMIT = 16, "Hop-Limit", Uint, 1..=1, false;
    /// Accept, RFC 7252 §5.10.4.
    ACCEPT = 17, "Accept", Uint, 0..=2, false;
    /// Q-Block1, RFC 9177 §4.
    Q_BLOCK1 = 19, "Q-Block1", Uint, 0..=3, false;
    /// Location-Query, RFC 7252 §5.10.7.
    LOCATION_QUERY = 20, "Location-Query", String, 0..=255, true;
    /// Block2, RFC 7959 §2.1.
    BLOCK2 = 23, "Block2", Uint, 0..=3, false;
    /// Block1, RFC 7959 §2.1.
    BLOCK1 = 27, "Block1", Uint, 0..=3, false;
    /// Size2, RFC 7959 §4.
    SIZE2 = 28, "Size2", Uint, 0..=4, false;
    /// Q-Block2, RFC 9177 §4.
    Q_BLOCK2 = 31, "Q-Block2", Uint, 0..=3, true;
    /// Proxy-Uri, RFC 7252 §5.10.2.
    PROXY_URI = 35, "Proxy-Uri", String, 1..=1034, false;
    /// Proxy-Scheme, RFC 7252 §5.10.2.
    PROXY_SCHEME = 39, "Proxy-Scheme", String, 1..=255, false;
    /// Size1, RFC 7252 §5.10.9 and RFC 7959 §4.
    SIZE1 = 60, "Size1", Uint, 0..=4, false;
    /// Echo, RFC 9175 §2.2.
    ECHO = 252, "Echo", Opaque, 1..=40, false;
    /// No-Response, RFC 7967 §2.
    NO_RESPONSE = 258, "No-Response", Uint, 0..=1, false;
    /// Request-Tag, RFC 9175 §3.2.
    REQUEST_TAG = 292, "Request-Tag", Opaque, 0..=8, true;
}

impl OptionNumber {
    /// RFC 7252 §5.4.1: odd numbers are critical.
    pub fn is_critical(self) -> bool {
        self.0 & 1 == 1
    }

    /// RFC 7252 §5.4.2: bit 1 marks options a proxy must understand.
    pub fn is_unsafe(self) -> bool {
        self.0 & 2 == 2
    }

    /// RFC 7252 §5.4.2: NoCacheKey is `number & 0x1e == 0x1c`.
    pub fn is_no_cache_key(self) -> bool {
        self.0 & 0x1e == 0x1c
    }

    /// Whether `value` has an allowed length for this option. Unknown options accept
    /// anything (their rules are not ours to check).
    pub fn accepts_len(self, len: usize) -> bool {
        self.info()
            .is_none_or(|i| (i.min_len as usize..=i.max_len as usize).contains(&len))
    }
}

impl fmt::Display for OptionNumber {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.info() {
            Some(info) => f.write_str(info.name),
            None => write!(f, "Option {}", self.0),
        }
    }
}

/// Encodes `v` as a minimal-length big-endian uint (RFC 7252 §3.2: zero is the empty value).
pub fn encode_uint(v: u32) -> Vec<u8> {
    let bytes = v.to_be_bytes();
    let skip = bytes.iter().take_while(|b| **b == 0).count();
    bytes[skip..].to_vec()
}

/// Decodes a big-endian uint of at most 4 bytes; longer values give `None`.
pub fn decode_uint(value: &[u8]) -> Option<u32> {
    if value.len() > 4 {
        return None;
    }
    Some(value.iter().fold(0u32, |acc, b| (acc << 8) | u32::from(*b)))
}

/// The value of a Block1, Block2, Q-Block1 or Q-Block2 option (RFC 7959 §2.2).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct BlockOpt {
    /// Block number, 20 bits at most.
    pub num: u32,
    /// More blocks follow.
    pub more: bool,
    /// Size exponent: the block holds `2^(szx + 4)` bytes. 7 is reserved (BERT).
    pub szx: u8,
}

impl BlockOpt {
    /// The largest block number a 3-byte option can carry.
    pub const MAX_NUM: u32 = (1 << 20) - 1;
    /// The largest block size exponent for UDP (1024 bytes).
    pub const MAX_SZX: u8 = 6;

    /// Block size in bytes for an exponent.
    pub fn size_of(szx: u8) -> usize {
        1usize << (u32::from(szx.min(Self::MAX_SZX)) + 4)
    }

    /// The exponent of the largest block size that is at most `bytes` (16 B minimum).
    pub fn szx_for(bytes: usize) -> u8 {
        let mut szx = Self::MAX_SZX;
        while szx > 0 && Self::size_of(szx) > bytes {
            szx -= 1;
        }
        szx
    }

    /// This block's size in bytes.
    pub fn size(self) -> usize {
        Self::size_of(self.szx)
    }

    /// Byte offset of this block in the body.
    pub fn offset(self) -> usize {
        self.num as usize * self.size()
    }

    /// Decodes the option value. `None` for a value longer than 3 bytes or SZX 7 (BERT,
    /// which only exists over reliable transports).
    pub fn decode(value: &[u8]) -> Option<Self> {
        if value.len() > 3 {
            return None;
        }
        let v = decode_uint(value)?;
        let szx = (v & 0x7) as u8;
        if szx == 7 {
            return None;
        }
        Some(Self {
            num: v >> 4,
            more: v & 0x8 != 0,
            szx,
        })
    }

    /// Encodes the option value. Numbers above 20 bits are truncated by the caller's
    /// contract: the stack never builds one (bodies are bounded well below 1 GiB).
    pub fn encode(self) -> Vec<u8> {
        encode_uint(self.as_uint())
    }

    /// The option value as a uint.
    pub fn as_uint(self) -> u32 {
        ((self.num & Self::MAX_NUM) << 4) | (u32::from(self.more) << 3) | u32::from(self.szx & 7)
    }
}

impl fmt::Display for BlockOpt {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}/{}/{}", self.num, u8::from(self.more), self.size())
    }
}

/// One option as it appears on the wire.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct CoapOption {
    /// The option number.
    pub number: OptionNumber,
    /// The raw value.
    pub value: OptionValue,
}

/// The raw value of an option. Values of up to [`OptionValue::INLINE`] bytes (every
/// uint, block, ETag and token-sized option, and most path segments) are kept inline, so
/// decoding, copying and building messages allocate once per message rather than once per
/// option; longer values live on the heap.
#[derive(Clone)]
pub struct OptionValue(ValueRepr);

#[derive(Clone)]
enum ValueRepr {
    Inline {
        len: u8,
        buf: [u8; OptionValue::INLINE],
    },
    Heap(Vec<u8>),
}

impl OptionValue {
    /// The longest value kept inline.
    pub const INLINE: usize = 22;

    /// A value holding a copy of `bytes`.
    pub fn new(bytes: &[u8]) -> Self {
        if bytes.len() <= Self::INLINE {
            let mut buf = [0u8; Self::INLINE];
            buf[..bytes.len()].copy_from_slice(bytes);
            Self(ValueRepr::Inline {
                len: bytes.len() as u8,
                buf,
            })
        } else {
            Self(ValueRepr::Heap(bytes.to_vec()))
        }
    }

    /// The bytes it holds on the heap (0 when inline).
    pub(crate) fn heap(&self) -> usize {
        match &self.0 {
            ValueRepr::Inline { .. } => 0,
            ValueRepr::Heap(v) => v.capacity(),
        }
    }

    /// The bytes.
    pub fn as_slice(&self) -> &[u8] {
        match &self.0 {
            ValueRepr::Inline { len, buf } => &buf[..usize::from(*len)],
            ValueRepr::Heap(v) => v,
        }
    }
}

impl std::ops::Deref for OptionValue {
    type Target = [u8];

    fn deref(&self) -> &[u8] {
        self.as_slice()
    }
}

impl AsRef<[u8]> for OptionValue {
    fn as_ref(&self) -> &[u8] {
        self.as_slice()
    }
}

impl PartialEq for OptionValue {
    fn eq(&self, other: &Self) -> bool {
        self.as_slice() == other.as_slice()
    }
}

impl Eq for OptionValue {}

impl std::hash::Hash for OptionValue {
    fn hash<H: std::hash::Hasher>(&self, state: &mut H) {
        self.as_slice().hash(state);
    }
}

impl fmt::Debug for OptionValue {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        self.as_slice().fmt(f)
    }
}

/// The options of a message, kept sorted by number; options with the same number keep
/// their relative order (RFC 7252 §5.4.5: repeated options are ordered).
///
/// Up to [`Options::INLINE`] options live inside the value, so decoding a block-wise
/// message or building the next block's request allocates nothing for its options.
#[derive(Debug, Clone, Default, PartialEq, Eq, Hash)]
pub struct Options {
    list: SmallVec<[CoapOption; Self::INLINE]>,
}

impl Options {
    /// How many options are kept without a heap allocation: a block-wise request's path
    /// segments and block option, or a response's ETag, Content-Format, Block2 and Size2.
    pub const INLINE: usize = 6;

    /// No options.
    pub fn new() -> Self {
        Self::default()
    }

    /// Replaces the options with those of a checked message, which come sorted.
    pub(crate) fn fill_in_wire_order<'a>(
        &mut self,
        options: impl Iterator<Item = (OptionNumber, &'a [u8])>,
    ) {
        self.list.clear();
        for (number, value) in options {
            self.list.push(CoapOption {
                number,
                value: OptionValue::new(value),
            });
        }
    }

    /// The bytes the list holds: itself, the spilled list and the values on the heap.
    pub(crate) fn held(&self) -> usize {
        let list = if self.list.spilled() {
            self.list.capacity() * size_of::<CoapOption>()
        } else {
            0
        };
        size_of::<Self>() + list + self.list.iter().map(|o| o.value.heap()).sum::<usize>()
    }

    /// All options in wire order.
    pub fn iter(&self) -> impl Iterator<Item = &CoapOption> {
        self.list.iter()
    }

    /// Number of option instances.
    pub fn len(&self) -> usize {
        self.list.len()
    }

    /// Whether there are no options.
    pub fn is_empty(&self) -> bool {
        self.list.is_empty()
    }

    /// Appends an instance of `number` after the existing instances of the same number.
    pub fn push(&mut self, number: OptionNumber, value: impl AsRef<[u8]>) {
        let at = self.list.partition_point(|o| o.number <= number);
        self.list.insert(
            at,
            CoapOption {
                number,
                value: OptionValue::new(value.as_ref()),
            },
        );
    }

    /// Replaces all instances of `number` with one value.
    pub fn set(&mut self, number: OptionNumber, value: impl AsRef<[u8]>) {
        self.remove(number);
        self.push(number, value);
    }

    /// Replaces all instances of `number` with one uint value.
    pub fn set_uint(&mut self, number: OptionNumber, value: u32) {
        let bytes = value.to_be_bytes();
        let skip = bytes.iter().take_while(|b| **b == 0).count();
        self.set(number, &bytes[skip..]);
    }

    /// Removes every instance of `number`.
    pub fn remove(&mut self, number: OptionNumber) {
        self.list.retain(|o| o.number != number);
    }

    /// Whether at least one instance of `number` is present.
    pub fn contains(&self, number: OptionNumber) -> bool {
        self.list.iter().any(|o| o.number == number)
    }

    /// The values of every instance of `number`, in order.
    pub fn values(&self, number: OptionNumber) -> impl Iterator<Item = &[u8]> {
        self.list
            .iter()
            .filter(move |o| o.number == number)
            .map(|o| o.value.as_slice())
    }

    /// The first value of `number`.
    pub fn first(&self, number: OptionNumber) -> Option<&[u8]> {
        self.values(number).next()
    }

    /// The first value of `number` as a uint, if it is a valid one.
    pub fn uint(&self, number: OptionNumber) -> Option<u32> {
        self.first(number).and_then(decode_uint)
    }

    /// The first value of `number` as a block option, if present and valid.
    pub fn block(&self, number: OptionNumber) -> Option<BlockOpt> {
        self.first(number).and_then(BlockOpt::decode)
    }

    /// Sets a block option.
    pub fn set_block(&mut self, number: OptionNumber, block: BlockOpt) {
        self.set_uint(number, block.as_uint());
    }

    /// Block1 (RFC 7959).
    pub fn block1(&self) -> Option<BlockOpt> {
        self.block(OptionNumber::BLOCK1)
    }

    /// Block2 (RFC 7959).
    pub fn block2(&self) -> Option<BlockOpt> {
        self.block(OptionNumber::BLOCK2)
    }

    /// Content-Format.
    pub fn content_format(&self) -> Option<ContentFormat> {
        self.uint(OptionNumber::CONTENT_FORMAT)
            .and_then(|v| u16::try_from(v).ok())
            .map(ContentFormat)
    }

    /// Accept.
    pub fn accept(&self) -> Option<ContentFormat> {
        self.uint(OptionNumber::ACCEPT)
            .and_then(|v| u16::try_from(v).ok())
            .map(ContentFormat)
    }

    /// The first ETag.
    pub fn etag(&self) -> Option<&[u8]> {
        self.first(OptionNumber::ETAG)
    }

    /// The Uri-Path segments, each decoded as UTF-8 (invalid bytes are replaced).
    pub fn uri_path(&self) -> impl Iterator<Item = std::borrow::Cow<'_, str>> {
        self.values(OptionNumber::URI_PATH)
            .map(String::from_utf8_lossy)
    }

    /// The Uri-Path joined with `/` and a leading `/`, e.g. `/cams/pointclouds`.
    pub fn path_string(&self) -> String {
        let mut s = String::new();
        for seg in self.uri_path() {
            s.push('/');
            s.push_str(&seg);
        }
        if s.is_empty() {
            s.push('/');
        }
        s
    }

    /// Sets the Uri-Path from a `/`-separated path; empty segments from leading or doubled
    /// slashes are skipped.
    pub fn set_path(&mut self, path: &str) {
        self.remove(OptionNumber::URI_PATH);
        for seg in path.split('/').filter(|s| !s.is_empty()) {
            self.push(OptionNumber::URI_PATH, seg.as_bytes());
        }
    }

    /// The Uri-Query items.
    pub fn uri_query(&self) -> impl Iterator<Item = std::borrow::Cow<'_, str>> {
        self.values(OptionNumber::URI_QUERY)
            .map(String::from_utf8_lossy)
    }

    /// The first option that makes the message unprocessable under RFC 7252 §5.4.1 and
    /// §5.4.3: a critical option that is unknown or has a value length outside its
    /// registered range, or a critical non-repeatable option given twice (§5.4.5).
    pub fn first_bad_critical(&self) -> Option<OptionNumber> {
        let mut prev: Option<OptionNumber> = None;
        for o in &self.list {
            let repeated = prev == Some(o.number);
            prev = Some(o.number);
            if !o.number.is_critical() {
                continue;
            }
            match o.number.info() {
                None => return Some(o.number),
                Some(info) => {
                    if !o.number.accepts_len(o.value.len()) || (repeated && !info.repeatable) {
                        return Some(o.number);
                    }
                }
            }
        }
        None
    }

    /// Drops elective options whose value length is outside their registered range
    /// (RFC 7252 §5.4.3: treated like an unrecognized elective option, i.e. ignored), and
    /// repeated instances of non-repeatable elective options (§5.4.5).
    pub fn drop_bad_elective(&mut self) {
        let mut prev: Option<OptionNumber> = None;
        self.list.retain(|o| {
            let repeated = prev == Some(o.number);
            prev = Some(o.number);
            if o.number.is_critical() {
                return true;
            }
            match o.number.info() {
                None => true,
                Some(info) => (info.repeatable || !repeated) && o.number.accepts_len(o.value.len()),
            }
        });
    }

    /// A byte string identifying the request for block-wise state: every option except
    /// those that change between the blocks of one transfer (Block1/2, Q-Block1/2, Size1/2,
    /// Observe, and Echo, which a client may carry on one block only, RFC 9175 §2.3).
    /// Request-Tag stays in, so that differently tagged bodies never mix
    /// (RFC 9175 §3.3).
    pub(crate) fn block_key(&self) -> SmallVec<[u8; 64]> {
        let mut key = SmallVec::with_capacity(self.list.iter().map(|o| 4 + o.value.len()).sum());
        for o in &self.list {
            if matches!(
                o.number,
                OptionNumber::BLOCK1
                    | OptionNumber::BLOCK2
                    | OptionNumber::Q_BLOCK1
                    | OptionNumber::Q_BLOCK2
                    | OptionNumber::SIZE1
                    | OptionNumber::SIZE2
                    | OptionNumber::OBSERVE
                    | OptionNumber::ETAG
                    | OptionNumber::ECHO
            ) {
                continue;
            }
            let [n0, n1] = o.number.0.to_be_bytes();
            let [l0, l1] = (o.value.len() as u16).to_be_bytes();
            key.extend_from_slice(&[n0, n1, l0, l1]);
            key.extend_from_slice(&o.value);
        }
        key
    }
}

impl FromIterator<CoapOption> for Options {
    fn from_iter<I: IntoIterator<Item = CoapOption>>(iter: I) -> Self {
        let mut list: SmallVec<[CoapOption; Self::INLINE]> = iter.into_iter().collect();
        list.sort_by_key(|o| o.number);
        Self { list }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rfc7252_5_4_6_option_classes() {
        assert!(OptionNumber::URI_PATH.is_critical());
        assert!(!OptionNumber::ETAG.is_critical());
        assert!(OptionNumber::PROXY_URI.is_unsafe());
        assert!(OptionNumber::SIZE1.is_no_cache_key());
        assert!(!OptionNumber::MAX_AGE.is_no_cache_key());
    }

    #[test]
    fn rfc7252_3_2_uint_is_minimal() {
        assert_eq!(encode_uint(0), Vec::<u8>::new());
        assert_eq!(encode_uint(60), vec![60]);
        assert_eq!(encode_uint(0x0100), vec![1, 0]);
        assert_eq!(decode_uint(&[0, 0, 1]), Some(1));
        assert_eq!(decode_uint(&[1, 2, 3, 4, 5]), None);
    }

    #[test]
    fn rfc7959_2_2_block_option_encoding() {
        let b = BlockOpt {
            num: 5,
            more: true,
            szx: 6,
        };
        assert_eq!(b.encode(), vec![0x5e]);
        assert_eq!(BlockOpt::decode(&[0x5e]), Some(b));
        assert_eq!(
            BlockOpt::decode(&[]),
            Some(BlockOpt {
                num: 0,
                more: false,
                szx: 0
            })
        );
        assert_eq!(
            BlockOpt::decode(&[0x07]),
            None,
            "SZX 7 is reserved for BERT"
        );
        assert_eq!(BlockOpt::decode(&[1, 2, 3, 4]), None);
        let big = BlockOpt {
            num: BlockOpt::MAX_NUM,
            more: false,
            szx: 6,
        };
        assert_eq!(BlockOpt::decode(&big.encode()), Some(big));
        assert_eq!(b.offset(), 5 * 1024);
        assert_eq!(BlockOpt::szx_for(1024), 6);
        assert_eq!(BlockOpt::szx_for(1000), 5);
        assert_eq!(BlockOpt::szx_for(3), 0);
    }

    #[test]
    fn rfc7252_5_4_5_repeated_options_keep_order() {
        let mut o = Options::new();
        o.push(OptionNumber::URI_PATH, "b");
        o.push(OptionNumber::CONTENT_FORMAT, [0u8; 0]);
        o.push(OptionNumber::URI_PATH, "c");
        o.push(OptionNumber::URI_HOST, "h");
        let nums: Vec<u16> = o.iter().map(|o| o.number.0).collect();
        assert_eq!(nums, [3, 11, 11, 12]);
        assert_eq!(o.path_string(), "/b/c");
    }

    #[test]
    fn rfc7252_5_4_1_unknown_critical_is_bad_unknown_elective_is_not() {
        let mut o = Options::new();
        o.push(OptionNumber(2050), "x");
        assert_eq!(o.first_bad_critical(), None);
        o.push(OptionNumber(2051), "x");
        assert_eq!(o.first_bad_critical(), Some(OptionNumber(2051)));
    }

    #[test]
    fn rfc7252_5_4_3_bad_length_critical_is_bad_elective_is_dropped() {
        let mut o = Options::new();
        o.push(OptionNumber::ETAG, [0u8; 9]);
        o.push(OptionNumber::MAX_AGE, [1u8; 5]);
        o.push(OptionNumber::URI_PORT, [1u8; 3]);
        assert_eq!(o.first_bad_critical(), Some(OptionNumber::URI_PORT));
        o.drop_bad_elective();
        assert_eq!(o.len(), 1);
    }

    #[test]
    fn rfc7252_5_4_5_repeated_non_repeatable_critical_is_bad() {
        let mut o = Options::new();
        o.push(OptionNumber::BLOCK2, [0u8]);
        o.push(OptionNumber::BLOCK2, [0x10u8]);
        assert_eq!(o.first_bad_critical(), Some(OptionNumber::BLOCK2));
    }

    #[test]
    fn option_values_short_and_long_keep_their_bytes() {
        for len in [0, 1, OptionValue::INLINE, OptionValue::INLINE + 1, 300] {
            let bytes: Vec<u8> = (0..len).map(|i| i as u8 ^ 0xa5).collect();
            let mut o = Options::new();
            o.push(OptionNumber::URI_PATH, &bytes);
            o.set_uint(OptionNumber::SIZE2, 0x0001_0203);
            assert_eq!(
                o.values(OptionNumber::URI_PATH).next(),
                Some(&bytes[..]),
                "{len} bytes"
            );
            assert_eq!(o.uint(OptionNumber::SIZE2), Some(0x0001_0203));
            assert_eq!(o.clone(), o);
        }
        assert_ne!(OptionValue::new(b"a"), OptionValue::new(b"ab"));
    }
}
