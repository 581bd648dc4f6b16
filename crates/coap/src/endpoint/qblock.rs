//! RFC 9177 Q-Block1 and Q-Block2, the parts both sides share: what a request's Q-Block2
//! options ask for, the missing-blocks payload of a 4.08, the NON timers, and the server
//! side's state (a body being sent set by set, a body being received in any order).
//!
//! A body goes in *sets* of MAX_PAYLOADS blocks, as NON messages. The receiver confirms
//! a whole set ('Continue': a 2.31 for Q-Block1, a request for the next set's first
//! block with M for Q-Block2) and asks for missing blocks (a 4.08 listing them, or a
//! request with one Q-Block2 option per block); without a 'Continue' the sender waits
//! NON_TIMEOUT_RANDOM before the next set. The RFC's timers are 2-3 s; here they follow
//! the path's round-trip estimate once there is one (`congestion::RttEstimator`), as
//! RFC 7252 §4.8.1 allows with congestion control, and keep the RFC's values until then.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use crate::block::BlockKey;
use crate::msg::{BlockOpt, Options, Token};

/// Content-Format of a 4.08's list of missing blocks (RFC 9177 §12.3).
pub(super) const MISSING_BLOCKS_CBOR_SEQ: u32 = 272;

/// NON_MAX_RETRANSMIT (RFC 9177 §7.2): unanswered requests for missing blocks before a
/// partial body is given up.
pub(super) const NON_MAX_RETRANSMIT: u32 = 4;

/// The blocks a request's Q-Block2 options ask for (RFC 9177 §4.4), ascending, each once,
/// for a body whose last block is `last`: M unset asks for that block; M set for that
/// block and the rest of its set (for block 0, the whole body's first set; the sets after
/// follow by 'Continue' or timer). `None` when the options are not in increasing order
/// without duplicates (the server answers 4.00).
pub(super) fn asked_blocks(opts: &[BlockOpt], max_payloads: u32, last: u32) -> Option<Vec<u32>> {
    if opts.windows(2).any(|w| w[0].num >= w[1].num) {
        return None;
    }
    let mut nums: Vec<u32> = Vec::new();
    for o in opts {
        let end = if o.more {
            (o.num / max_payloads + 1) * max_payloads - 1
        } else {
            o.num
        };
        let start = nums.last().map_or(o.num, |&l| o.num.max(l + 1));
        nums.extend(start..=end.min(last));
    }
    Some(nums)
}

/// The number of the last block of a body of `len` bytes in blocks of exponent `szx`.
pub(super) fn last_block(len: usize, szx: u8) -> u32 {
    (len.saturating_sub(1) / BlockOpt::size_of(szx)) as u32
}

/// Whether a request's Q-Block2 options are a 'Continue' (RFC 9177 §4.4): one option with
/// M set and a NUM that starts a set other than the first; returns the set.
pub(super) fn continue_set(opts: &[BlockOpt], max_payloads: u32) -> Option<u32> {
    match opts {
        [o] if o.more && o.num > 0 && o.num % max_payloads == 0 => Some(o.num / max_payloads),
        _ => None,
    }
}

/// The payload of a 4.08 listing missing blocks: a CBOR sequence of unsigned integers,
/// no array around them (RFC 9177 §5).
pub(super) fn encode_missing(nums: &[u32]) -> Vec<u8> {
    let mut out = Vec::with_capacity(nums.len() * 3);
    for &n in nums {
        match n {
            0..=23 => out.push(n as u8),
            24..=0xff => out.extend_from_slice(&[24, n as u8]),
            0x100..=0xffff => {
                out.push(25);
                out.extend_from_slice(&(n as u16).to_be_bytes());
            }
            _ => {
                out.push(26);
                out.extend_from_slice(&n.to_be_bytes());
            }
        }
    }
    out
}

/// The block numbers of a 4.08's CBOR sequence; `None` unless they are unsigned
/// integers in increasing order without duplicates (RFC 9177 §5: such a 4.08 is dropped).
pub(super) fn decode_missing(mut data: &[u8]) -> Option<Vec<u32>> {
    let mut nums: Vec<u32> = Vec::new();
    while let Some((&head, rest)) = data.split_first() {
        if head >> 5 != 0 {
            return None;
        }
        let (n, rest) = match head & 0x1f {
            v @ 0..=23 => (u32::from(v), rest),
            24 => (u32::from(*rest.first()?), rest.get(1..)?),
            25 => (
                u32::from(u16::from_be_bytes(rest.get(..2)?.try_into().ok()?)),
                rest.get(2..)?,
            ),
            26 => (
                u32::from_be_bytes(rest.get(..4)?.try_into().ok()?),
                rest.get(4..)?,
            ),
            _ => return None,
        };
        if nums.last().is_some_and(|&l| l >= n) {
            return None;
        }
        nums.push(n);
        data = rest;
    }
    (!nums.is_empty()).then_some(nums)
}

/// NON_TIMEOUT_RANDOM for a body: the path's probe timeout (`SRTT + 4 RTTVAR`, bounded)
/// once it has a round-trip estimate, else the RFC's `ACK_TIMEOUT * U[1, factor]`
/// (`unit`: a uniform sample in [0, 1)).
pub(super) fn non_timeout(
    estimate: Option<Duration>,
    ack_timeout: Duration,
    factor: f64,
    unit: f64,
) -> Duration {
    estimate.unwrap_or_else(|| ack_timeout.mul_f64(1.0 + (factor - 1.0) * unit))
}

/// NON_RECEIVE_TIMEOUT after `tries` unanswered requests for missing blocks: twice
/// NON_TIMEOUT (RFC 9177 §7.2: 4 s), or the path's probe timeout once it has an
/// estimate; doubling with each try.
pub(super) fn receive_timeout(
    estimate: Option<Duration>,
    ack_timeout: Duration,
    tries: u32,
) -> Duration {
    estimate.unwrap_or(ack_timeout * 2) * (1 << tries.min(6))
}

/// How long an incomplete Q-Block1 body may go without a block before the server drops
/// it: NON_RECEIVE_TIMEOUT · (2^NON_MAX_RETRANSMIT − 1) with the RFC's timers (60 s), so
/// that a sender that keeps them is not given up on sooner because the server's own
/// timers follow the round trip.
pub(super) fn stale_after(ack_timeout: Duration) -> Duration {
    ack_timeout * 2 * ((1 << NON_MAX_RETRANSMIT) - 1)
}

/// A body the server sends with Q-Block2, set by set: the next set goes when the client
/// confirms the last ('Continue') or NON_TIMEOUT_RANDOM after it.
#[derive(Debug)]
pub(super) struct QSend {
    pub(super) peer: std::net::SocketAddr,
    pub(super) key: BlockKey,
    /// The token of the latest request for this body (the sets answer it).
    pub(super) token: Token,
    pub(super) szx: u8,
    /// The next set to send, and the body's last block.
    pub(super) next_set: u32,
    pub(super) last: u32,
    /// When the last set went, and whether a 'Continue' asked for it (then the time to
    /// the next 'Continue' is a round trip).
    pub(super) sent_at: Instant,
    pub(super) asked: bool,
    /// NON_TIMEOUT_RANDOM, drawn once per body.
    pub(super) timeout: Duration,
    /// When the armed timer fires.
    pub(super) at: Instant,
}

/// A body the server receives with Q-Block1, in any order.
#[derive(Debug)]
pub(super) struct QUpload {
    pub(super) key: BlockKey,
    pub(super) body: Vec<u8>,
    /// Which blocks arrived, and how many.
    pub(super) got: Vec<bool>,
    pub(super) count: u32,
    pub(super) szx: u8,
    /// The token of the body's latest request (the 2.31s and 4.08s answer it).
    pub(super) token: Token,
    /// The highest block whose arrival sent a 4.08 at once: a set's first block with
    /// earlier blocks missing, or its last block with blocks of the set missing.
    pub(super) reported: Option<u32>,
    /// When the latest block arrived, when a 2.31 last went, and the receive timer.
    pub(super) heard: Instant,
    pub(super) continued_at: Option<Instant>,
    pub(super) at: Instant,
    /// 4.08s sent since the latest block arrived.
    pub(super) tries: u32,
    /// The blocks the latest 4.08 listed: once they are all in, the next 4.08 goes at
    /// once (RFC 9177 §5) rather than after NON_RECEIVE_TIMEOUT.
    pub(super) listed: Vec<u32>,
    /// The body was complete and went to the application; blocks that come after are
    /// dropped.
    pub(super) done: bool,
}

impl QUpload {
    /// The missing blocks below `end`, lowest first, at most `max`.
    pub(super) fn missing(&self, end: u32, max: usize) -> Vec<u32> {
        (0..end.min(self.got.len() as u32))
            .filter(|&n| !self.got[n as usize])
            .take(max)
            .collect()
    }

    /// One past the highest block that arrived.
    pub(super) fn received_end(&self) -> u32 {
        self.got
            .iter()
            .rposition(|&g| g)
            .map_or(0, |n| n as u32 + 1)
    }

    /// One past the set of the lowest missing block: the end of what a 4.08 lists when
    /// the body stopped arriving (the gaps, then the rest of that set, which may be the
    /// next set when the 2.31 was lost).
    pub(super) fn stalled_end(&self, max_payloads: u32) -> u32 {
        let first = self.got.iter().position(|&g| !g).unwrap_or(self.got.len()) as u32;
        (first / max_payloads + 1) * max_payloads
    }

    /// Whether every block of set `set` arrived (`max_payloads` blocks a set).
    pub(super) fn set_complete(&self, set: u32, max_payloads: u32) -> bool {
        let start = (set * max_payloads) as usize;
        let end = (start + max_payloads as usize).min(self.got.len());
        self.got[start..end].iter().all(|&g| g)
    }

    /// Whether a block before set `set` is missing.
    pub(super) fn gap_before(&self, set: u32, max_payloads: u32) -> bool {
        let end = ((set * max_payloads) as usize).min(self.got.len());
        self.got[..end].iter().any(|&g| !g)
    }
}

/// A response body being fetched with Q-Block2.
#[derive(Debug)]
pub(super) struct QDown {
    pub(super) szx: u8,
    pub(super) last: u32,
    pub(super) total: usize,
    pub(super) got: Vec<bool>,
    /// Blocks that arrived ahead of the next one to deliver.
    pub(super) ahead: BTreeMap<u32, Vec<u8>>,
    pub(super) next_deliver: u32,
    /// Sets asked for so far (the first set by the first request).
    pub(super) asked_sets: u32,
    /// The highest set a block arrived from.
    pub(super) seen_set: u32,
    /// When the latest 'Continue' went, until its set's first block arrives.
    pub(super) continued_at: Option<Instant>,
    pub(super) heard: Instant,
    pub(super) tries: u32,
    /// When the armed timer fires.
    pub(super) at: Option<Instant>,
    /// Tokens of the requests sent for this body (all routed to the request).
    pub(super) tokens: Vec<Token>,
}

/// A request body being sent with Q-Block1.
#[derive(Debug)]
pub(super) struct QUp {
    /// The request's options with its Request-Tag.
    pub(super) options: Options,
    pub(super) szx: u8,
    pub(super) blocks: u32,
    /// The next block never sent.
    pub(super) next_new: u32,
    /// Block 0 went as a CON and is not acknowledged yet.
    pub(super) probing: bool,
    /// NON_TIMEOUT_RANDOM, drawn once.
    pub(super) timeout: Duration,
    /// When the latest set went (its 2.31 gives a round trip).
    pub(super) set_sent: Option<Instant>,
    /// Message ID and token of the last block sent, to send it again.
    pub(super) last_sent: Option<(u32, u16, Token)>,
    pub(super) tries: u32,
    pub(super) at: Option<Instant>,
    pub(super) tokens: Vec<Token>,
}

#[cfg(test)]
mod tests {
    use super::*;

    fn b(num: u32, more: bool) -> BlockOpt {
        BlockOpt { num, more, szx: 6 }
    }

    #[test]
    fn rfc9177_4_4_what_q_block2_options_ask_for() {
        // NUM 0 with M: the first set.
        assert_eq!(
            asked_blocks(&[b(0, true)], 10, 100),
            Some((0..10).collect())
        );
        // A 'Continue' (NUM a multiple of MAX_PAYLOADS, M set).
        assert_eq!(continue_set(&[b(20, true)], 10), Some(2));
        assert_eq!(
            asked_blocks(&[b(20, true)], 10, 24),
            Some((20..=24).collect())
        );
        // Another NUM with M: that block and the rest of its set.
        assert_eq!(
            asked_blocks(&[b(13, true)], 10, 100),
            Some((13..20).collect())
        );
        // M unset: just those blocks; overlaps are sent once.
        assert_eq!(
            asked_blocks(&[b(3, false), b(5, true), b(7, false)], 10, 100),
            Some(vec![3, 5, 6, 7, 8, 9])
        );
        assert_eq!(continue_set(&[b(3, false), b(10, true)], 10), None);
        // Not increasing: a 4.00.
        assert_eq!(asked_blocks(&[b(5, false), b(3, false)], 10, 100), None);
        assert_eq!(asked_blocks(&[b(5, false), b(5, false)], 10, 100), None);
    }

    #[test]
    fn rfc9177_5_missing_blocks_are_a_cbor_sequence() {
        let nums = [0, 23, 24, 255, 256, 65535, 65536, 1 << 19];
        let bytes = encode_missing(&nums);
        assert_eq!(&bytes[..5], &[0x00, 0x17, 0x18, 0x18, 0x18]);
        assert_eq!(decode_missing(&bytes), Some(nums.to_vec()));
        // RFC 9177 §10.1.3's example lists blocks 2 and 3: 0x02 0x03.
        assert_eq!(decode_missing(&[0x02, 0x03]), Some(vec![2, 3]));
        // Not ascending, duplicated, not uints, truncated, empty: dropped.
        assert_eq!(decode_missing(&[0x03, 0x02]), None);
        assert_eq!(decode_missing(&[0x02, 0x02]), None);
        assert_eq!(decode_missing(&[0x82, 0x02, 0x03]), None);
        assert_eq!(decode_missing(&[0x19, 0x01]), None);
        assert_eq!(decode_missing(&[]), None);
    }

    #[test]
    fn rfc9177_7_2_timers_are_the_rfcs_until_there_is_an_estimate() {
        let ack = Duration::from_secs(2);
        assert_eq!(non_timeout(None, ack, 1.5, 0.0), Duration::from_secs(2));
        assert_eq!(
            non_timeout(None, ack, 1.5, 0.5),
            Duration::from_millis(2500)
        );
        assert_eq!(receive_timeout(None, ack, 0), Duration::from_secs(4));
        assert_eq!(receive_timeout(None, ack, 2), Duration::from_secs(16));
        let est = Some(Duration::from_millis(60));
        assert_eq!(non_timeout(est, ack, 1.5, 0.9), Duration::from_millis(60));
        assert_eq!(receive_timeout(est, ack, 1), Duration::from_millis(120));
    }
}
