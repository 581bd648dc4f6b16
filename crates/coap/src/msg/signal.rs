//! Signalling messages of CoAP over reliable transports (RFC 8323 §5): codes 7.01 CSM,
//! 7.02 Ping, 7.03 Pong, 7.04 Release and 7.05 Abort, each a [`Signal`] read from and
//! written to a [`Frame`].
//!
//! **Option numbers are per code** (§5.2): number 2 is Max-Message-Size in a CSM, Custody
//! in a Ping or Pong, Alternative-Address in a Release and Bad-CSM-Option in an Abort. So
//! they are constants of their message here ([`Csm::MAX_MESSAGE_SIZE`],
//! [`Signal::CUSTODY`], [`Release::HOLD_OFF`], ...), never entries of the request and
//! response registry of [`option`](super::option), whose [`OptionNumber::info`] would
//! misname them.
//!
//! Every option defined for signalling is elective. As for requests (RFC 7252 §5.4.1,
//! §5.4.3, §5.4.5), an unknown elective option, a value of the wrong length and a second
//! instance of a non-repeatable option are ignored; an unknown critical option is an
//! error, after which the receiver aborts the connection (§5.2), naming the option with
//! Bad-CSM-Option when it came in a CSM (§5.3, [`SignalError::abort`]).
//!
//! The payload of a signalling message is a diagnostic payload (§5.1, RFC 7252 §5.5.2):
//! it stays the frame's, as does the token; [`Signal::to_frame`] takes both.

use bytes::Bytes;

use super::option::decode_uint;
use super::stream::Frame;
use super::{Code, OptionNumber, Options, Token};

/// A signalling message's meaning: its code and what its options say.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Signal {
    /// 7.01: the sender's capabilities and settings, sent first on a connection by each
    /// side and again whenever they change (§5.3).
    Csm(Csm),
    /// 7.02: asks the peer for a Pong (§5.4).
    Ping {
        /// Custody: the sender wants the Pong only once the peer has answered every
        /// request that came before the Ping.
        custody: bool,
    },
    /// 7.03: the answer to a Ping (§5.4).
    Pong {
        /// Custody: the Pong comes after the answers to every request before the Ping.
        custody: bool,
    },
    /// 7.04: the sender wants the connection closed (§5.5).
    Release(Release),
    /// 7.05: the sender is closing the connection because of an error (§5.6).
    Abort(Abort),
}

/// The options of a CSM (RFC 8323 §5.3). A CSM that leaves an option out keeps the
/// setting an earlier CSM gave (or its default), so each is optional here.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Csm {
    /// Max-Message-Size (§5.3.1): the largest message, in bytes, the sender accepts.
    pub max_message_size: Option<u32>,
    /// Block-Wise-Transfer (§5.3.2): the sender supports block-wise transfers, and with
    /// them BERT blocks.
    pub block_wise_transfer: bool,
}

impl Csm {
    /// Max-Message-Size, a uint of 0-4 bytes.
    pub const MAX_MESSAGE_SIZE: OptionNumber = OptionNumber(2);
    /// Block-Wise-Transfer, an empty option.
    pub const BLOCK_WISE_TRANSFER: OptionNumber = OptionNumber(4);
    /// The Max-Message-Size of a peer that has not announced one (§5.3.1).
    pub const DEFAULT_MAX_MESSAGE_SIZE: u32 = 1152;

    /// The Max-Message-Size this CSM announces, or the default.
    pub fn max_message_size_or_default(&self) -> u32 {
        self.max_message_size
            .unwrap_or(Self::DEFAULT_MAX_MESSAGE_SIZE)
    }
}

/// The options of a Release (RFC 8323 §5.5).
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct Release {
    /// Alternative-Address: where the peer may connect instead, each of 1-255 bytes (a
    /// longer or empty one is not written, and ignored when read).
    pub alternative_addresses: Vec<String>,
    /// Hold-Off: how many seconds the peer should wait before connecting again, at most
    /// [`Release::MAX_HOLD_OFF_S`] (a 3-byte uint; larger values are written as that).
    pub hold_off_s: Option<u32>,
}

impl Release {
    /// Alternative-Address, a repeatable string of 1-255 bytes.
    pub const ALTERNATIVE_ADDRESS: OptionNumber = OptionNumber(2);
    /// Hold-Off, a uint of 0-3 bytes.
    pub const HOLD_OFF: OptionNumber = OptionNumber(4);
    /// The largest Hold-Off 3 bytes hold.
    pub const MAX_HOLD_OFF_S: u32 = 0xff_ffff;
}

/// The options of an Abort (RFC 8323 §5.6).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Abort {
    /// Bad-CSM-Option: the CSM option the sender could not accept, which caused the
    /// abort.
    pub bad_csm_option: Option<OptionNumber>,
}

impl Abort {
    /// Bad-CSM-Option, a uint of 0-2 bytes.
    pub const BAD_CSM_OPTION: OptionNumber = OptionNumber(2);
}

/// Why a frame is not a signalling message this stack can read.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum SignalError {
    /// The code is not of class 7: a request, a response or an Empty message.
    #[error("{0} is not a signalling code")]
    NotSignal(Code),
    /// A 7.xx code RFC 8323 does not define.
    #[error("unknown signalling code {0}")]
    UnknownCode(Code),
    /// A critical option the code does not define (§5.2).
    #[error("unknown critical option {} in {code}", number.0)]
    UnknownCritical {
        /// The message's code.
        code: Code,
        /// The option.
        number: OptionNumber,
    },
}

impl SignalError {
    /// The Abort that answers this error, if the connection must end: for an unknown
    /// critical option (§5.2), naming it in Bad-CSM-Option when it came in a CSM (§5.3).
    /// A frame that is not signalling, or of a signalling code RFC 8323 does not define,
    /// is left to the caller.
    pub fn abort(&self) -> Option<Abort> {
        match *self {
            Self::UnknownCritical { code, number } => Some(Abort {
                bad_csm_option: (code == Code::CSM).then_some(number),
            }),
            Self::NotSignal(_) | Self::UnknownCode(_) => None,
        }
    }
}

/// A signalling option's rules: value length and whether it repeats.
struct Rule {
    min: usize,
    max: usize,
    repeatable: bool,
}

/// The rules of option `number` in a message of `code`, if RFC 8323 §5 defines it.
fn rule(code: Code, number: OptionNumber) -> Option<Rule> {
    let (min, max, repeatable) = match (code, number) {
        (Code::CSM, Csm::MAX_MESSAGE_SIZE) => (0, 4, false),
        (Code::CSM, Csm::BLOCK_WISE_TRANSFER) => (0, 0, false),
        (Code::PING | Code::PONG, Signal::CUSTODY) => (0, 0, false),
        (Code::RELEASE, Release::ALTERNATIVE_ADDRESS) => (1, 255, true),
        (Code::RELEASE, Release::HOLD_OFF) => (0, 3, false),
        (Code::ABORT, Abort::BAD_CSM_OPTION) => (0, 2, false),
        _ => return None,
    };
    Some(Rule {
        min,
        max,
        repeatable,
    })
}

/// The values of `number` in `frame` that count: each of the right length, and only the
/// first instance of a non-repeatable option.
fn values(frame: &Frame, number: OptionNumber) -> impl Iterator<Item = &[u8]> {
    let rule = rule(frame.code, number);
    let take = match &rule {
        Some(r) if r.repeatable => usize::MAX,
        Some(_) => 1,
        None => 0,
    };
    frame.options.values(number).take(take).filter(move |v| {
        rule.as_ref()
            .is_some_and(|r| (r.min..=r.max).contains(&v.len()))
    })
}

/// The first value of uint option `number`, if it counts.
fn uint(frame: &Frame, number: OptionNumber) -> Option<u32> {
    values(frame, number).next().and_then(decode_uint)
}

/// Whether empty option `number` is present and counts.
fn flag(frame: &Frame, number: OptionNumber) -> bool {
    values(frame, number).next().is_some()
}

impl Signal {
    /// Custody (§5.4), the empty option of a Ping and of a Pong.
    pub const CUSTODY: OptionNumber = OptionNumber(2);

    /// The code of this signal.
    pub fn code(&self) -> Code {
        match self {
            Self::Csm(_) => Code::CSM,
            Self::Ping { .. } => Code::PING,
            Self::Pong { .. } => Code::PONG,
            Self::Release(_) => Code::RELEASE,
            Self::Abort(_) => Code::ABORT,
        }
    }

    /// Reads a signalling frame's code and options (its token and payload stay the
    /// frame's).
    pub fn decode(frame: &Frame) -> Result<Self, SignalError> {
        let code = frame.code;
        if !code.is_signal() {
            return Err(SignalError::NotSignal(code));
        }
        if !matches!(
            code,
            Code::CSM | Code::PING | Code::PONG | Code::RELEASE | Code::ABORT
        ) {
            return Err(SignalError::UnknownCode(code));
        }
        if let Some(o) = frame
            .options
            .iter()
            .find(|o| o.number.is_critical() && rule(code, o.number).is_none())
        {
            return Err(SignalError::UnknownCritical {
                code,
                number: o.number,
            });
        }
        Ok(match code {
            Code::CSM => Self::Csm(Csm {
                max_message_size: uint(frame, Csm::MAX_MESSAGE_SIZE),
                block_wise_transfer: flag(frame, Csm::BLOCK_WISE_TRANSFER),
            }),
            Code::PING => Self::Ping {
                custody: flag(frame, Self::CUSTODY),
            },
            Code::PONG => Self::Pong {
                custody: flag(frame, Self::CUSTODY),
            },
            Code::RELEASE => Self::Release(Release {
                alternative_addresses: values(frame, Release::ALTERNATIVE_ADDRESS)
                    .filter_map(|v| std::str::from_utf8(v).ok())
                    .map(str::to_owned)
                    .collect(),
                hold_off_s: uint(frame, Release::HOLD_OFF),
            }),
            _ => Self::Abort(Abort {
                bad_csm_option: uint(frame, Abort::BAD_CSM_OPTION)
                    .and_then(|n| u16::try_from(n).ok())
                    .map(OptionNumber),
            }),
        })
    }

    /// The frame of this signal, with `token` and the diagnostic payload `diagnostic`
    /// (empty for none).
    pub fn to_frame(&self, token: Token, diagnostic: Bytes) -> Frame {
        let mut options = Options::new();
        match self {
            Self::Csm(csm) => {
                if let Some(size) = csm.max_message_size {
                    options.set_uint(Csm::MAX_MESSAGE_SIZE, size);
                }
                if csm.block_wise_transfer {
                    options.push(Csm::BLOCK_WISE_TRANSFER, []);
                }
            }
            Self::Ping { custody } | Self::Pong { custody } => {
                if *custody {
                    options.push(Self::CUSTODY, []);
                }
            }
            Self::Release(release) => {
                for address in &release.alternative_addresses {
                    if (1..=255).contains(&address.len()) {
                        options.push(Release::ALTERNATIVE_ADDRESS, address.as_bytes());
                    }
                }
                if let Some(s) = release.hold_off_s {
                    options.set_uint(Release::HOLD_OFF, s.min(Release::MAX_HOLD_OFF_S));
                }
            }
            Self::Abort(abort) => {
                if let Some(number) = abort.bad_csm_option {
                    options.set_uint(Abort::BAD_CSM_OPTION, u32::from(number.0));
                }
            }
        }
        Frame {
            code: self.code(),
            token,
            options,
            payload: diagnostic,
        }
    }
}
