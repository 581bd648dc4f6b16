//! The CoAP Content-Format registry (RFC 7252 §12.3): numbers, media types and short names.
//!
//! A [`ContentFormat`] is the 16-bit number carried in the Content-Format and Accept options.
//! The registry below holds the registered formats coapcam speaks or is likely to meet, with
//! the media type IANA registers for each. Numbers outside the table are still valid content
//! formats; they just have no name here (an application names its own, e.g. from the
//! experimental range 65000-65535).
//!
//! ```
//! use coap::content_format::ContentFormat;
//!
//! let cf: ContentFormat = "png".parse()?;
//! assert_eq!(cf, ContentFormat::IMAGE_PNG);
//! assert_eq!(cf.to_string(), "image/png");
//! assert_eq!("application/json".parse::<ContentFormat>()?, ContentFormat::JSON);
//! assert_eq!("65100".parse::<ContentFormat>()?.media_type(), None);
//! # Ok::<(), coap::content_format::ParseError>(())
//! ```

use std::fmt;
use std::str::FromStr;

/// A CoAP Content-Format number (RFC 7252 §5.10.3, §12.3).
///
/// Any `u16` is a valid content format; the associated constants name the registered ones
/// this crate knows.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct ContentFormat(pub u16);

impl ContentFormat {
    /// 0: `text/plain; charset=utf-8` (RFC 7252 §12.3).
    pub const TEXT_PLAIN: Self = Self(0);
    /// 16: `application/cose; cose-type="cose-encrypt0"` (RFC 9052).
    pub const COSE_ENCRYPT0: Self = Self(16);
    /// 17: `application/cose; cose-type="cose-mac0"` (RFC 9052).
    pub const COSE_MAC0: Self = Self(17);
    /// 18: `application/cose; cose-type="cose-sign1"` (RFC 9052).
    pub const COSE_SIGN1: Self = Self(18);
    /// 21: `image/gif`.
    pub const IMAGE_GIF: Self = Self(21);
    /// 22: `image/jpeg`.
    pub const IMAGE_JPEG: Self = Self(22);
    /// 23: `image/png`.
    pub const IMAGE_PNG: Self = Self(23);
    /// 40: `application/link-format` (RFC 6690).
    pub const LINK_FORMAT: Self = Self(40);
    /// 41: `application/xml` (RFC 3023).
    pub const XML: Self = Self(41);
    /// 42: `application/octet-stream` (RFC 2045).
    pub const OCTET_STREAM: Self = Self(42);
    /// 47: `application/exi`.
    pub const EXI: Self = Self(47);
    /// 50: `application/json` (RFC 8259).
    pub const JSON: Self = Self(50);
    /// 51: `application/json-patch+json` (RFC 6902).
    pub const JSON_PATCH: Self = Self(51);
    /// 52: `application/merge-patch+json` (RFC 7396).
    pub const MERGE_PATCH: Self = Self(52);
    /// 60: `application/cbor` (RFC 8949).
    pub const CBOR: Self = Self(60);
    /// 61: `application/cwt` (RFC 8392).
    pub const CWT: Self = Self(61);
    /// 62: `application/multipart-core` (RFC 8710).
    pub const MULTIPART_CORE: Self = Self(62);
    /// 63: `application/cbor-seq` (RFC 8742).
    pub const CBOR_SEQ: Self = Self(63);
    /// 110: `application/senml+json` (RFC 8428).
    pub const SENML_JSON: Self = Self(110);
    /// 112: `application/senml+cbor` (RFC 8428).
    pub const SENML_CBOR: Self = Self(112);
    /// 256: `application/coap-group+json`, the group configuration of RFC 7390 §2.6.2.
    pub const COAP_GROUP_JSON: Self = Self(256);
    /// 272: `application/missing-blocks+cbor-seq` (RFC 9177).
    pub const MISSING_BLOCKS_CBOR_SEQ: Self = Self(272);
    /// 320: `application/senml-etch+json` (RFC 8790).
    pub const SENML_ETCH_JSON: Self = Self(320);
    /// 322: `application/senml-etch+cbor` (RFC 8790).
    pub const SENML_ETCH_CBOR: Self = Self(322);
    /// The registered media type, e.g. `"image/png"`, or `None` for a number this crate does
    /// not know.
    #[must_use]
    pub fn media_type(self) -> Option<&'static str> {
        entry(self).map(|e| e.media_type)
    }

    /// The short name used on the command line (`--accept png`), e.g. `"png"`, or `None`
    /// for a number this crate does not know.
    #[must_use]
    pub fn name(self) -> Option<&'static str> {
        entry(self).map(|e| e.name)
    }

    /// Looks up a media type such as `"application/json"` or `"text/plain;charset=utf-8"`.
    ///
    /// Comparison ignores ASCII case and whitespace, so `"Text/Plain; Charset=UTF-8"` finds
    /// content format 0.
    #[must_use]
    pub fn from_media_type(media_type: &str) -> Option<Self> {
        REGISTRY
            .iter()
            .find(|e| eq_media_type(e.media_type, media_type))
            .map(|e| e.format)
    }

    /// Looks up a short name such as `"json"`, `"png"` or `"jpg"` (ASCII case-insensitive).
    #[must_use]
    pub fn from_name(name: &str) -> Option<Self> {
        REGISTRY
            .iter()
            .find(|e| e.name.eq_ignore_ascii_case(name))
            .map(|e| e.format)
            .or_else(|| {
                ALIASES
                    .iter()
                    .find(|(alias, _)| alias.eq_ignore_ascii_case(name))
                    .map(|&(_, format)| format)
            })
    }

    /// Whether the number is in the experimental range 65000-65535 (RFC 7252 §12.3).
    #[must_use]
    pub fn is_experimental(self) -> bool {
        self.0 >= 65000
    }

    /// Every content format this crate has a name for, in ascending numeric order.
    pub fn known() -> impl Iterator<Item = Self> {
        REGISTRY.iter().map(|e| e.format)
    }
}

impl From<u16> for ContentFormat {
    fn from(value: u16) -> Self {
        Self(value)
    }
}

impl From<ContentFormat> for u16 {
    fn from(value: ContentFormat) -> Self {
        value.0
    }
}

impl fmt::Display for ContentFormat {
    /// Writes the media type when it is known, otherwise the number.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.media_type() {
            Some(media_type) => f.write_str(media_type),
            None => write!(f, "{}", self.0),
        }
    }
}

impl FromStr for ContentFormat {
    type Err = ParseError;

    /// Accepts a number (`"60"`), a media type (`"application/cbor"`) or a short name
    /// (`"cbor"`); surrounding whitespace is ignored.
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let s = s.trim();
        if !s.is_empty() && s.bytes().all(|b| b.is_ascii_digit()) {
            return s
                .parse::<u16>()
                .map(Self)
                .map_err(|_| ParseError::OutOfRange(s.to_owned()));
        }
        Self::from_media_type(s)
            .or_else(|| Self::from_name(s))
            .ok_or_else(|| ParseError::Unknown(s.to_owned()))
    }
}

/// Why a string is not a content format.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum ParseError {
    /// A number that does not fit the 16-bit Content-Format option.
    #[error("content format {0} is out of range (0-65535)")]
    OutOfRange(String),
    /// Neither a number, nor a known media type, nor a known short name.
    #[error(
        "unknown content format {0:?}: use a number (0-65535), a media type such as \
         application/json, or a short name such as json, cbor, png, jpeg, octet-stream, \
         link-format or text"
    )]
    Unknown(String),
}

struct Entry {
    format: ContentFormat,
    media_type: &'static str,
    name: &'static str,
}

const fn e(format: ContentFormat, media_type: &'static str, name: &'static str) -> Entry {
    Entry {
        format,
        media_type,
        name,
    }
}

/// RFC 7252 §12.3 and the IANA "CoAP Content-Formats" registry, in ascending order.
const REGISTRY: &[Entry] = &[
    e(
        ContentFormat::TEXT_PLAIN,
        "text/plain; charset=utf-8",
        "text",
    ),
    e(
        ContentFormat::COSE_ENCRYPT0,
        "application/cose; cose-type=\"cose-encrypt0\"",
        "cose-encrypt0",
    ),
    e(
        ContentFormat::COSE_MAC0,
        "application/cose; cose-type=\"cose-mac0\"",
        "cose-mac0",
    ),
    e(
        ContentFormat::COSE_SIGN1,
        "application/cose; cose-type=\"cose-sign1\"",
        "cose-sign1",
    ),
    e(ContentFormat::IMAGE_GIF, "image/gif", "gif"),
    e(ContentFormat::IMAGE_JPEG, "image/jpeg", "jpeg"),
    e(ContentFormat::IMAGE_PNG, "image/png", "png"),
    e(
        ContentFormat::LINK_FORMAT,
        "application/link-format",
        "link-format",
    ),
    e(ContentFormat::XML, "application/xml", "xml"),
    e(
        ContentFormat::OCTET_STREAM,
        "application/octet-stream",
        "octet-stream",
    ),
    e(ContentFormat::EXI, "application/exi", "exi"),
    e(ContentFormat::JSON, "application/json", "json"),
    e(
        ContentFormat::JSON_PATCH,
        "application/json-patch+json",
        "json-patch+json",
    ),
    e(
        ContentFormat::MERGE_PATCH,
        "application/merge-patch+json",
        "merge-patch+json",
    ),
    e(ContentFormat::CBOR, "application/cbor", "cbor"),
    e(ContentFormat::CWT, "application/cwt", "cwt"),
    e(
        ContentFormat::MULTIPART_CORE,
        "application/multipart-core",
        "multipart-core",
    ),
    e(ContentFormat::CBOR_SEQ, "application/cbor-seq", "cbor-seq"),
    e(
        ContentFormat::SENML_JSON,
        "application/senml+json",
        "senml+json",
    ),
    e(
        ContentFormat::SENML_CBOR,
        "application/senml+cbor",
        "senml+cbor",
    ),
    e(
        ContentFormat::COAP_GROUP_JSON,
        "application/coap-group+json",
        "coap-group+json",
    ),
    e(
        ContentFormat::MISSING_BLOCKS_CBOR_SEQ,
        "application/missing-blocks+cbor-seq",
        "missing-blocks+cbor-seq",
    ),
    e(
        ContentFormat::SENML_ETCH_JSON,
        "application/senml-etch+json",
        "senml-etch+json",
    ),
    e(
        ContentFormat::SENML_ETCH_CBOR,
        "application/senml-etch+cbor",
        "senml-etch+cbor",
    ),
];

/// Extra short names accepted by [`ContentFormat::from_name`], never printed.
const ALIASES: &[(&str, ContentFormat)] = &[
    ("jpg", ContentFormat::IMAGE_JPEG),
    ("octet", ContentFormat::OCTET_STREAM),
    ("bin", ContentFormat::OCTET_STREAM),
    ("link", ContentFormat::LINK_FORMAT),
    ("text/plain", ContentFormat::TEXT_PLAIN),
];

fn entry(format: ContentFormat) -> Option<&'static Entry> {
    REGISTRY
        .binary_search_by_key(&format, |e| e.format)
        .ok()
        .and_then(|i| REGISTRY.get(i))
}

/// Compares two media types ignoring ASCII case and all whitespace.
fn eq_media_type(registered: &str, given: &str) -> bool {
    let mut a = registered.chars().filter(|c| !c.is_whitespace());
    let mut b = given.chars().filter(|c| !c.is_whitespace());
    loop {
        match (a.next(), b.next()) {
            (None, None) => return true,
            (Some(x), Some(y)) if x.eq_ignore_ascii_case(&y) => {}
            _ => return false,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn registry_is_sorted_and_unique() {
        assert!(REGISTRY.windows(2).all(|w| w[0].format < w[1].format));
        for (i, a) in REGISTRY.iter().enumerate() {
            for b in &REGISTRY[i + 1..] {
                assert_ne!(a.name, b.name);
                assert!(!eq_media_type(a.media_type, b.media_type));
            }
        }
    }

    #[test]
    fn iana_numbers_and_media_types() {
        let expected: &[(u16, &str)] = &[
            (0, "text/plain; charset=utf-8"),
            (16, "application/cose; cose-type=\"cose-encrypt0\""),
            (21, "image/gif"),
            (22, "image/jpeg"),
            (23, "image/png"),
            (40, "application/link-format"),
            (41, "application/xml"),
            (42, "application/octet-stream"),
            (47, "application/exi"),
            (50, "application/json"),
            (51, "application/json-patch+json"),
            (52, "application/merge-patch+json"),
            (60, "application/cbor"),
            (61, "application/cwt"),
            (62, "application/multipart-core"),
            (63, "application/cbor-seq"),
            (110, "application/senml+json"),
            (112, "application/senml+cbor"),
            (256, "application/coap-group+json"),
            (272, "application/missing-blocks+cbor-seq"),
            (320, "application/senml-etch+json"),
            (322, "application/senml-etch+cbor"),
        ];
        for &(number, media_type) in expected {
            let cf = ContentFormat(number);
            assert_eq!(cf.media_type(), Some(media_type), "{number}");
            assert_eq!(ContentFormat::from_media_type(media_type), Some(cf));
            assert_eq!(cf.to_string(), media_type);
            assert_eq!(media_type.parse::<ContentFormat>(), Ok(cf));
        }
    }

    #[test]
    fn unknown_number_has_no_name_and_displays_as_number() {
        let cf = ContentFormat(1234);
        assert_eq!(cf.media_type(), None);
        assert_eq!(cf.name(), None);
        assert_eq!(cf.to_string(), "1234");
        assert_eq!("1234".parse::<ContentFormat>(), Ok(cf));
    }

    #[test]
    fn media_type_lookup_ignores_case_and_whitespace() {
        assert_eq!(
            ContentFormat::from_media_type("Text/Plain;Charset=UTF-8"),
            Some(ContentFormat::TEXT_PLAIN)
        );
        assert_eq!(
            ContentFormat::from_media_type("IMAGE/PNG"),
            Some(ContentFormat::IMAGE_PNG)
        );
        assert_eq!(ContentFormat::from_media_type("image/pngx"), None);
        assert_eq!(ContentFormat::from_media_type("image/pn"), None);
        assert_eq!(ContentFormat::from_media_type(""), None);
    }

    #[test]
    fn cli_short_names() {
        let cases: &[(&str, ContentFormat)] = &[
            ("json", ContentFormat::JSON),
            ("cbor", ContentFormat::CBOR),
            ("png", ContentFormat::IMAGE_PNG),
            ("jpeg", ContentFormat::IMAGE_JPEG),
            ("jpg", ContentFormat::IMAGE_JPEG),
            ("octet-stream", ContentFormat::OCTET_STREAM),
            ("link-format", ContentFormat::LINK_FORMAT),
            ("text", ContentFormat::TEXT_PLAIN),
            ("text/plain", ContentFormat::TEXT_PLAIN),
            ("PNG", ContentFormat::IMAGE_PNG),
            (" cbor ", ContentFormat::CBOR),
        ];
        for &(input, expected) in cases {
            assert_eq!(input.parse::<ContentFormat>(), Ok(expected), "{input}");
        }
        assert_eq!(ContentFormat::IMAGE_PNG.name(), Some("png"));
        assert_eq!(ContentFormat(65100).name(), None);
    }

    #[test]
    fn every_known_format_round_trips_through_its_names() {
        for cf in ContentFormat::known() {
            let media_type = cf.media_type().unwrap_or_default();
            let name = cf.name().unwrap_or_default();
            assert_eq!(media_type.parse::<ContentFormat>(), Ok(cf));
            assert_eq!(name.parse::<ContentFormat>(), Ok(cf));
            assert_eq!(cf.0.to_string().parse::<ContentFormat>(), Ok(cf));
            assert_eq!(cf.to_string().parse::<ContentFormat>(), Ok(cf));
        }
    }

    #[test]
    fn parse_errors() {
        assert!(matches!(
            "65536".parse::<ContentFormat>(),
            Err(ParseError::OutOfRange(_))
        ));
        assert!(matches!(
            "99999999999999999999999".parse::<ContentFormat>(),
            Err(ParseError::OutOfRange(_))
        ));
        for bad in ["", "  ", "-1", "+5", "tiff", "image/tiff", "4 2"] {
            assert!(
                matches!(bad.parse::<ContentFormat>(), Err(ParseError::Unknown(_))),
                "{bad:?}"
            );
        }
        let message = "tiff".parse::<ContentFormat>().map_err(|e| e.to_string());
        assert!(message.is_err_and(|m| m.contains("\"tiff\"") && m.contains("png")));
    }

    #[test]
    fn experimental_range() {
        assert!(ContentFormat(65100).is_experimental());
        assert!(ContentFormat(65000).is_experimental());
        assert!(ContentFormat(65535).is_experimental());
        assert!(!ContentFormat(64999).is_experimental());
        assert!(!ContentFormat::JSON.is_experimental());
    }

    proptest::proptest! {
        #[test]
        fn every_number_round_trips_through_display(n in proptest::prelude::any::<u16>()) {
            let cf = ContentFormat(n);
            proptest::prop_assert_eq!(cf.to_string().parse::<ContentFormat>(), Ok(cf));
        }

        #[test]
        fn parse_never_panics(s in proptest::prelude::any::<String>()) {
            let _ = s.parse::<ContentFormat>();
        }
    }

    #[test]
    fn converts_to_and_from_u16() {
        assert_eq!(ContentFormat::from(60), ContentFormat::CBOR);
        assert_eq!(u16::from(ContentFormat::IMAGE_JPEG), 22);
    }
}
