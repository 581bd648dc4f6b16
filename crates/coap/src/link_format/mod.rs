//! RFC 6690 CoRE Link Format: the `application/link-format` payload of `/.well-known/core`.
//!
//! A payload is a comma-separated list of links, each a target URI in angle brackets followed
//! by `;`-separated attributes:
//!
//! ```text
//! </sensors/temp>;rt="temperature-c";if="sensor";obs,</firmware/v2.1>;rt="firmware";sz=262144
//! ```
//!
//! [`parse`] reads such a payload into [`Link`]s, [`write_links`] (and [`Link`]'s `Display`)
//! writes one, and [`Filter`] implements the `/.well-known/core?name=value` query filter of
//! RFC 6690 §4.1.
//!
//! The parser is a single forward pass over the input (linear time), never panics, and is
//! lenient about whitespace (spaces, tabs and line breaks) between links and around `;`,
//! which RFC 6690 §5 uses in its examples "for readability".
//!
//! ```
//! use coap::link_format::{self, Filter, Link};
//!
//! let links = link_format::parse(r#"</cams>;ct=40;title="Cameras", </cams/840412060746/color>;rt="coapcam.color";obs"#)?;
//! assert_eq!(links[1].rt().collect::<Vec<_>>(), ["coapcam.color"]);
//! assert!(links[1].obs());
//!
//! let filter = Filter::parse("href=/cams/*")?;
//! assert_eq!(links.iter().filter(|l| filter.matches(l)).count(), 1);
//! assert_eq!(link_format::write_links(&links), r#"</cams>;ct=40;title="Cameras",</cams/840412060746/color>;rt="coapcam.color";obs"#);
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

use std::fmt::{self, Write as _};

use crate::content_format::ContentFormat;

/// One link of a link-format document (RFC 6690 §2): a target and its attributes.
///
/// Attributes keep their order and may repeat. A value is stored unquoted and unescaped;
/// `None` is a valueless attribute such as `obs`.
///
/// For the written form to parse back, `target` must not contain `>` (a URI-reference never
/// does; the writer escapes it as `%3E`) and attribute names must be RFC 6690 `parmname`s
/// (ASCII letters, digits and ``!#$&+-.^_`|~``, optionally ending in `*`).
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct Link {
    /// The target URI-reference, written between `<` and `>`.
    pub target: String,
    /// The attributes (`link-param`s) in document order: name and optional value.
    pub attrs: Vec<(String, Option<String>)>,
}

/// Attributes whose value is a space-separated list, matched item by item by [`Filter`].
///
/// RFC 6690 §3.1 (`rt`), §3.2 (`if`), RFC 8288 §3.3 (`rel`, `rev`), RFC 7252 §7.2.1 (`ct`).
const LIST_ATTRS: &[&str] = &["rt", "if", "ct", "rel", "rev"];

/// Attributes the writer always quotes, following the style of the RFC 6690 §5 examples.
///
/// `anchor` and `title` must be quoted (RFC 6690 §2); `rt`, `if`, `rel` and `rev` may be
/// quoted and must be once they hold more than one item.
const QUOTED_ATTRS: &[&str] = &["anchor", "title", "rt", "if", "rel", "rev"];

impl Link {
    /// A link to `target` with no attributes.
    #[must_use]
    pub fn new(target: impl Into<String>) -> Self {
        Self {
            target: target.into(),
            attrs: Vec::new(),
        }
    }

    /// Appends the attribute `name=value`.
    #[must_use]
    pub fn with_attr(mut self, name: impl Into<String>, value: impl Into<String>) -> Self {
        self.attrs.push((name.into(), Some(value.into())));
        self
    }

    /// Appends the valueless attribute `name`.
    #[must_use]
    pub fn with_flag(mut self, name: impl Into<String>) -> Self {
        self.attrs.push((name.into(), None));
        self
    }

    /// Appends a resource type, `rt` (RFC 6690 §3.1); several types are space-separated.
    #[must_use]
    pub fn with_rt(self, rt: impl Into<String>) -> Self {
        self.with_attr("rt", rt)
    }

    /// Appends an interface description, `if` (RFC 6690 §3.2).
    #[must_use]
    pub fn with_if(self, interface: impl Into<String>) -> Self {
        self.with_attr("if", interface)
    }

    /// Appends a content-format hint, `ct` (RFC 7252 §7.2.1).
    #[must_use]
    pub fn with_ct(self, ct: ContentFormat) -> Self {
        self.with_attr("ct", ct.0.to_string())
    }

    /// Appends a maximum size estimate in bytes, `sz` (RFC 6690 §3.3).
    #[must_use]
    pub fn with_sz(self, size_bytes: u64) -> Self {
        self.with_attr("sz", size_bytes.to_string())
    }

    /// Appends a human-readable title, `title` (RFC 8288 §3.4.1, RFC 6690 §2).
    #[must_use]
    pub fn with_title(self, title: impl Into<String>) -> Self {
        self.with_attr("title", title)
    }

    /// Marks the resource observable, `obs` (RFC 7641 §6).
    #[must_use]
    pub fn with_obs(self) -> Self {
        self.with_flag("obs")
    }

    /// The value of the first attribute called `name` (ASCII case-insensitive) that has a
    /// value.
    #[must_use]
    pub fn attr(&self, name: &str) -> Option<&str> {
        self.attrs
            .iter()
            .filter(|(n, _)| n.eq_ignore_ascii_case(name))
            .find_map(|(_, v)| v.as_deref())
    }

    /// Whether an attribute called `name` is present, with or without a value.
    #[must_use]
    pub fn has_attr(&self, name: &str) -> bool {
        self.attrs.iter().any(|(n, _)| n.eq_ignore_ascii_case(name))
    }

    /// Every resource type (`rt`, RFC 6690 §3.1), across repeated attributes and
    /// space-separated lists.
    pub fn rt(&self) -> impl Iterator<Item = &str> {
        self.list_items("rt")
    }

    /// Every interface description (`if`, RFC 6690 §3.2).
    pub fn interfaces(&self) -> impl Iterator<Item = &str> {
        self.list_items("if")
    }

    /// Every content format (`ct`, RFC 7252 §7.2.1); items that are not a number in
    /// 0-65535 are skipped.
    pub fn ct(&self) -> impl Iterator<Item = ContentFormat> {
        self.list_items("ct")
            .filter_map(|item| item.parse::<u16>().ok().map(ContentFormat))
    }

    /// The maximum size estimate in bytes (`sz`, RFC 6690 §3.3), if present and a number.
    #[must_use]
    pub fn sz(&self) -> Option<u64> {
        self.attr("sz").and_then(|v| v.parse().ok())
    }

    /// The title (`title`, RFC 6690 §2).
    #[must_use]
    pub fn title(&self) -> Option<&str> {
        self.attr("title")
    }

    /// Whether the resource is marked observable (`obs`, RFC 7641 §6).
    #[must_use]
    pub fn obs(&self) -> bool {
        self.has_attr("obs")
    }

    fn list_items<'a>(&'a self, name: &'a str) -> impl Iterator<Item = &'a str> {
        self.attrs
            .iter()
            .filter(move |(n, _)| n.eq_ignore_ascii_case(name))
            .filter_map(|(_, v)| v.as_deref())
            .flat_map(str::split_ascii_whitespace)
    }
}

impl fmt::Display for Link {
    /// Writes the link in link-format (RFC 6690 §2), quoting values where needed.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_char('<')?;
        for piece in self.target.split_inclusive('>') {
            match piece.strip_suffix('>') {
                Some(head) => {
                    f.write_str(head)?;
                    f.write_str("%3E")?;
                }
                None => f.write_str(piece)?,
            }
        }
        f.write_char('>')?;
        for (name, value) in &self.attrs {
            f.write_char(';')?;
            f.write_str(name)?;
            let Some(value) = value else { continue };
            f.write_char('=')?;
            let must_quote = value.is_empty()
                || !value.bytes().all(is_ptoken_byte)
                || QUOTED_ATTRS.iter().any(|q| q.eq_ignore_ascii_case(name));
            if must_quote {
                f.write_char('"')?;
                for c in value.chars() {
                    if c == '"' || c == '\\' {
                        f.write_char('\\')?;
                    }
                    f.write_char(c)?;
                }
                f.write_char('"')?;
            } else {
                f.write_str(value)?;
            }
        }
        Ok(())
    }
}

/// Writes `links` as one link-format document, separated by `,` (RFC 6690 §2).
#[must_use]
pub fn write_links(links: &[Link]) -> String {
    let mut out = String::new();
    for (i, link) in links.iter().enumerate() {
        if i > 0 {
            out.push(',');
        }
        // NOTE: writing to a String cannot fail.
        let _ = write!(out, "{link}");
    }
    out
}

/// Why a link-format document did not parse, and where.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("invalid link-format at byte {offset}: {kind}")]
pub struct ParseError {
    /// What was wrong.
    pub kind: ParseErrorKind,
    /// Byte offset into the input where the problem was found.
    pub offset: usize,
}

/// The kinds of [`ParseError`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum ParseErrorKind {
    /// A link must start with `<`.
    #[error("expected '<' to start a link")]
    ExpectedLink,
    /// The `<` of a target has no matching `>`.
    #[error("target has no closing '>'")]
    UnterminatedTarget,
    /// After `;` comes an attribute name (letters, digits, ``!#$&+-.^_`|~*``).
    #[error("expected an attribute name after ';'")]
    ExpectedAttrName,
    /// After `=` comes a token or a quoted string.
    #[error("expected a token or a quoted string after '='")]
    ExpectedValue,
    /// A quoted string has no closing `"`.
    #[error("quoted string has no closing '\"'")]
    UnterminatedQuotedString,
    /// After a link comes `,`, `;` or the end of the document.
    #[error("expected ',' or ';' or the end of the document")]
    ExpectedSeparator,
}

/// Parses a link-format document (RFC 6690 §2) into its links.
///
/// An empty (or all-whitespace) document is an empty list. Values are unquoted and
/// unescaped (`\"` → `"`, `\\` → `\`).
///
/// # Errors
///
/// [`ParseError`] with the offending byte offset if the document does not follow the
/// RFC 6690 grammar (with whitespace allowed between links and around `;`).
pub fn parse(input: &str) -> Result<Vec<Link>, ParseError> {
    let mut p = Parser { input, pos: 0 };
    let mut links = Vec::new();
    p.skip_ws();
    if p.peek().is_none() {
        return Ok(links);
    }
    loop {
        links.push(p.link()?);
        p.skip_ws();
        match p.peek() {
            None => return Ok(links),
            Some(b',') => {
                p.pos += 1;
                p.skip_ws();
            }
            Some(_) => return Err(p.error(ParseErrorKind::ExpectedSeparator)),
        }
    }
}

struct Parser<'a> {
    input: &'a str,
    pos: usize,
}

impl Parser<'_> {
    fn peek(&self) -> Option<u8> {
        self.input.as_bytes().get(self.pos).copied()
    }

    fn error(&self, kind: ParseErrorKind) -> ParseError {
        ParseError {
            kind,
            offset: self.pos,
        }
    }

    fn skip_ws(&mut self) {
        while matches!(self.peek(), Some(b' ' | b'\t' | b'\r' | b'\n')) {
            self.pos += 1;
        }
    }

    /// Advances over bytes matching `pred` and returns them. `pred` must accept only ASCII,
    /// so the returned range lies on character boundaries.
    fn take_while(&mut self, pred: impl Fn(u8) -> bool) -> &str {
        let start = self.pos;
        while self.peek().is_some_and(&pred) {
            self.pos += 1;
        }
        self.input.get(start..self.pos).unwrap_or_default()
    }

    /// RFC 6690 §2: `link-value = "<" URI-Reference ">" *( ";" link-param )`.
    fn link(&mut self) -> Result<Link, ParseError> {
        if self.peek() != Some(b'<') {
            return Err(self.error(ParseErrorKind::ExpectedLink));
        }
        let start = self.pos + 1;
        let rest = self.input.get(start..).unwrap_or_default();
        let Some(len) = rest.find('>') else {
            return Err(self.error(ParseErrorKind::UnterminatedTarget));
        };
        let target = rest.get(..len).unwrap_or_default().to_owned();
        self.pos = start + len + 1;
        let mut attrs = Vec::new();
        loop {
            self.skip_ws();
            if self.peek() != Some(b';') {
                return Ok(Link { target, attrs });
            }
            self.pos += 1;
            self.skip_ws();
            attrs.push(self.param()?);
        }
    }

    /// RFC 6690 §2: `link-extension = ( parmname [ "=" ( ptoken / quoted-string ) ] )`
    /// (and the specific params, which are all of that shape).
    fn param(&mut self) -> Result<(String, Option<String>), ParseError> {
        let name = self.take_while(is_parmname_byte).to_owned();
        if name.is_empty() {
            return Err(self.error(ParseErrorKind::ExpectedAttrName));
        }
        if self.peek() != Some(b'=') {
            return Ok((name, None));
        }
        self.pos += 1;
        let value = if self.peek() == Some(b'"') {
            self.quoted_string()?
        } else {
            let token = self.take_while(is_ptoken_byte);
            if token.is_empty() {
                return Err(self.error(ParseErrorKind::ExpectedValue));
            }
            token.to_owned()
        };
        Ok((name, Some(value)))
    }

    /// RFC 2616 §2.2: `quoted-string = DQUOTE *( qdtext / quoted-pair ) DQUOTE`,
    /// `quoted-pair = "\" CHAR`. Called with `pos` on the opening quote.
    fn quoted_string(&mut self) -> Result<String, ParseError> {
        let open = self.pos;
        let body = self.input.get(open + 1..).unwrap_or_default();
        let mut value = String::new();
        let mut chars = body.char_indices();
        while let Some((i, c)) = chars.next() {
            match c {
                '"' => {
                    self.pos = open + 1 + i + 1;
                    return Ok(value);
                }
                '\\' => match chars.next() {
                    Some((_, escaped)) => value.push(escaped),
                    None => break,
                },
                _ => value.push(c),
            }
        }
        self.pos = open;
        Err(self.error(ParseErrorKind::UnterminatedQuotedString))
    }
}

/// RFC 6690 §2 `parmname` (RFC 5987 `attr-char` without `%` and `'`), plus `*` for the
/// `ext-name-star` form such as `title*`.
fn is_parmname_byte(b: u8) -> bool {
    b.is_ascii_alphanumeric() || b"!#$&+-.^_`|~*".contains(&b)
}

/// RFC 6690 §2 `ptokenchar`.
fn is_ptoken_byte(b: u8) -> bool {
    b.is_ascii_alphanumeric() || b"!#$%&'()*+-./:<=>?@[]^_`{|}~".contains(&b)
}

/// A `/.well-known/core` query filter (RFC 6690 §4.1).
///
/// A query is `name=value`, where `name` is `href` (the link target) or an attribute name.
/// A value ending in `*` matches as a prefix; otherwise the match is exact. For attributes
/// whose value is a space-separated list (`rt`, `if`, `ct`, `rel`, `rev`) a link matches if
/// any item (or the whole value) matches. A name without `=` matches links that have the
/// attribute at all, and a valueless attribute such as `obs` counts as an empty value.
///
/// Several `&`-separated parameters must all match, as in RFC 9176 §7; an empty query
/// matches every link. Names and values are percent-decoded; a `*` written as `%2A` is a
/// literal character, not a wildcard.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct Filter {
    terms: Vec<Term>,
}

#[derive(Debug, Clone, PartialEq, Eq)]
struct Term {
    name: String,
    pattern: Pattern,
}

#[derive(Debug, Clone, PartialEq, Eq)]
enum Pattern {
    Present,
    Exact(String),
    Prefix(String),
}

impl Pattern {
    fn matches(&self, value: &str) -> bool {
        match self {
            Self::Present => true,
            Self::Exact(want) => value == want,
            Self::Prefix(prefix) => value.starts_with(prefix.as_str()),
        }
    }
}

/// Why a `/.well-known/core` query is not a valid filter.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum FilterError {
    /// A `%` not followed by two hex digits.
    #[error(
        "bad percent-encoding at byte {offset} of the query: '%' must be followed by two hex digits"
    )]
    BadPercentEncoding {
        /// Byte offset of the `%` in the query.
        offset: usize,
    },
    /// The decoded bytes are not UTF-8.
    #[error("query parameter at byte {offset} is not UTF-8 after percent-decoding")]
    NotUtf8 {
        /// Byte offset of the parameter in the query.
        offset: usize,
    },
    /// A parameter such as `=value` has no name.
    #[error(
        "query parameter at byte {offset} has no name: use href=... or an attribute such as rt=..."
    )]
    EmptyName {
        /// Byte offset of the parameter in the query.
        offset: usize,
    },
}

impl Filter {
    /// Parses the query part of a `/.well-known/core` request, without the `?`
    /// (a leading `?` is ignored), e.g. `rt=coapcam.*` or `href=/cams*&obs`.
    ///
    /// # Errors
    ///
    /// [`FilterError`] for bad percent-encoding, non-UTF-8 text or a parameter without
    /// a name.
    pub fn parse(query: &str) -> Result<Self, FilterError> {
        let skip = usize::from(query.starts_with('?'));
        let mut terms = Vec::new();
        let mut offset = skip;
        for param in query.get(skip..).unwrap_or_default().split('&') {
            let start = offset;
            offset += param.len() + 1;
            if param.is_empty() {
                continue;
            }
            let (raw_name, raw_value) = match param.split_once('=') {
                Some((n, v)) => (n, Some(v)),
                None => (param, None),
            };
            let name = percent_decode(raw_name, start)?;
            if name.is_empty() {
                return Err(FilterError::EmptyName { offset: start });
            }
            let value_start = start + raw_name.len() + 1;
            let pattern = match raw_value {
                None => Pattern::Present,
                Some(v) => match v.strip_suffix('*') {
                    Some(prefix) => Pattern::Prefix(percent_decode(prefix, value_start)?),
                    None => Pattern::Exact(percent_decode(v, value_start)?),
                },
            };
            terms.push(Term { name, pattern });
        }
        Ok(Self { terms })
    }

    /// Whether `link` passes the filter (RFC 6690 §4.1).
    #[must_use]
    pub fn matches(&self, link: &Link) -> bool {
        self.terms.iter().all(|term| term.matches(link))
    }
}

impl Term {
    fn matches(&self, link: &Link) -> bool {
        if self.name.eq_ignore_ascii_case("href") {
            return self.pattern.matches(&link.target);
        }
        let is_list = LIST_ATTRS
            .iter()
            .any(|l| l.eq_ignore_ascii_case(&self.name));
        link.attrs
            .iter()
            .filter(|(n, _)| n.eq_ignore_ascii_case(&self.name))
            .any(|(_, value)| {
                let value = value.as_deref().unwrap_or_default();
                self.pattern.matches(value)
                    || (is_list
                        && value
                            .split_ascii_whitespace()
                            .any(|item| self.pattern.matches(item)))
            })
    }
}

/// Percent-decodes `s` (RFC 3986 §2.1); `offset` is where `s` starts in the query, for errors.
fn percent_decode(s: &str, offset: usize) -> Result<String, FilterError> {
    let bytes = s.as_bytes();
    let mut out = Vec::with_capacity(bytes.len());
    let mut i = 0;
    while let Some(&b) = bytes.get(i) {
        if b == b'%' {
            let hex = |j: usize| bytes.get(j).and_then(|&h| char::from(h).to_digit(16));
            let (Some(hi), Some(lo)) = (hex(i + 1), hex(i + 2)) else {
                return Err(FilterError::BadPercentEncoding { offset: offset + i });
            };
            // NOTE: hi and lo are hex digits (< 16), so the sum fits in a byte.
            out.push(u8::try_from(hi * 16 + lo).unwrap_or_default());
            i += 3;
        } else {
            out.push(b);
            i += 1;
        }
    }
    String::from_utf8(out).map_err(|_| FilterError::NotUtf8 { offset })
}

#[cfg(test)]
mod tests;
