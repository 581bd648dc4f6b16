//! Message deduplication (RFC 7252 §4.5): CON and NON message IDs are remembered for
//! EXCHANGE_LIFETIME / NON_LIFETIME with the reply that was sent, so a duplicate gets the
//! same reply again and never reaches the application twice.

use std::collections::hash_map::Entry as MapEntry;
use std::collections::{HashMap, VecDeque};
use std::net::SocketAddr;

use crate::peer_key::MidKey;
use std::time::Instant;

use crate::config::Limits;
use crate::msg::{BlockOpt, Message, OptionNumber, Token};

/// What was done with a remembered message.
#[derive(Debug, Clone)]
pub(crate) enum Seen {
    /// Handed to the application, no reply yet (the incoming request's id).
    Pending(u64),
    /// This reply was sent; a duplicate gets it again.
    Replied(Box<Message>),
    /// Nothing to send again (a NON request answered separately, or a dropped message).
    Silent,
}

/// What tells a duplicate from a new message that reuses a message ID: the token, the
/// block options and the Observe value. A fast client's message IDs come round within
/// EXCHANGE_LIFETIME during a long block-wise transfer (RFC 7252 §4.4 would hold it to
/// 265 messages a second), while its token stays the same from block to block; and a
/// busy server's message IDs come round while it notifies an observer, whose
/// notifications all carry one token and differ in their Observe value.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Fingerprint {
    token: Token,
    blocks: (Option<BlockOpt>, Option<BlockOpt>),
    observe: Option<u32>,
}

impl Fingerprint {
    pub(crate) fn of(msg: &Message) -> Self {
        Self {
            token: msg.token,
            blocks: (msg.options.block1(), msg.options.block2()),
            observe: msg.options.uint(OptionNumber::OBSERVE),
        }
    }
}

struct Entry {
    fingerprint: Fingerprint,
    expires: Instant,
    seen: Seen,
    /// What the entry counts against the byte limit ([`size`]).
    bytes: usize,
}

/// The bytes an entry holds, counted once when it is stored: the entry itself with its
/// key and its place in the order, and a remembered reply (the message, its options and
/// payload).
fn size(seen: &Seen) -> usize {
    const ENTRY: usize =
        size_of::<(MidKey, Entry)>() + size_of::<(Instant, SocketAddr, u16)>() + 16;
    ENTRY
        + match seen {
            Seen::Replied(m) => size_of::<Message>() + m.options.held() + m.payload.len(),
            Seen::Pending(_) | Seen::Silent => 0,
        }
}

/// Bounded store of recently received message IDs per peer.
pub(crate) struct Dedup {
    entries: HashMap<MidKey, Entry>,
    /// Insertion order for expiry and eviction; stale keys are skipped.
    order: VecDeque<(Instant, SocketAddr, u16)>,
    bytes: usize,
}

impl Dedup {
    pub(crate) fn new() -> Self {
        Self {
            entries: HashMap::new(),
            order: VecDeque::new(),
            bytes: 0,
        }
    }

    fn expire(&mut self, now: Instant, limits: &Limits) {
        while let Some(&(expires, peer, mid)) = self.order.front() {
            let over = self.entries.len() > limits.dedup_entries || self.bytes > limits.dedup_bytes;
            if expires > now && !over {
                break;
            }
            self.order.pop_front();
            if self
                .entries
                .get(&MidKey(peer, mid))
                .is_some_and(|e| e.expires == expires)
            {
                self.remove(peer, mid);
            }
        }
    }

    fn remove(&mut self, peer: SocketAddr, mid: u16) {
        if let Some(e) = self.entries.remove(&MidKey(peer, mid)) {
            self.bytes -= e.bytes;
        }
    }

    /// The earlier handling of this message, if it is a duplicate. A message ID reused
    /// with a different token or block is a new message: ID space wraps after 65,536
    /// messages, and a fast client can get there within EXCHANGE_LIFETIME.
    pub(crate) fn check(
        &mut self,
        now: Instant,
        peer: SocketAddr,
        mid: u16,
        fingerprint: Fingerprint,
        limits: &Limits,
    ) -> Option<&Seen> {
        self.expire(now, limits);
        match self.entries.entry(MidKey(peer, mid)) {
            MapEntry::Occupied(e) if e.get().fingerprint == fingerprint => Some(&e.into_mut().seen),
            MapEntry::Occupied(e) => {
                self.bytes -= e.remove().bytes;
                None
            }
            MapEntry::Vacant(_) => None,
        }
    }

    /// Remembers a message until `expires`.
    pub(crate) fn insert(
        &mut self,
        now: Instant,
        (peer, mid): (SocketAddr, u16),
        fingerprint: Fingerprint,
        expires: Instant,
        seen: Seen,
        limits: &Limits,
    ) {
        self.remove(peer, mid);
        let bytes = size(&seen);
        self.bytes += bytes;
        self.entries.insert(
            MidKey(peer, mid),
            Entry {
                fingerprint,
                expires,
                seen,
                bytes,
            },
        );
        self.order.push_back((expires, peer, mid));
        self.expire(now, limits);
    }

    /// Records the reply to a remembered message, keeping its lifetime.
    pub(crate) fn set_reply(&mut self, peer: SocketAddr, mid: u16, seen: Seen) {
        let Some(e) = self.entries.get_mut(&MidKey(peer, mid)) else {
            return;
        };
        let bytes = size(&seen);
        self.bytes = self.bytes - e.bytes + bytes;
        e.bytes = bytes;
        e.seen = seen;
    }

    #[cfg(test)]
    pub(crate) fn len(&self) -> usize {
        self.entries.len()
    }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use bytes::Bytes;

    use super::*;

    fn peer() -> SocketAddr {
        SocketAddr::from(([127, 0, 0, 1], 5683))
    }

    /// A GET with this token, and this Block2 number when given.
    fn get(token: u8, block2: Option<u32>) -> Fingerprint {
        let mut m = Message::empty(crate::msg::Type::Con, 7);
        m.token = Token::new(&[token]).unwrap();
        if let Some(num) = block2 {
            let block = BlockOpt {
                num,
                more: false,
                szx: 6,
            };
            m.options.set_block(OptionNumber::BLOCK2, block);
        }
        Fingerprint::of(&m)
    }

    #[test]
    fn rfc7252_4_5_duplicate_within_lifetime_is_recognised() {
        let now = crate::test_epoch();
        let l = Limits::default();
        let mut d = Dedup::new();
        let t = get(1, None);
        d.insert(
            now,
            (peer(), 7),
            t,
            now + Duration::from_secs(247),
            Seen::Replied(Box::new(Message::empty(crate::msg::Type::Ack, 7))),
            &l,
        );
        assert!(matches!(
            d.check(now, peer(), 7, t, &l),
            Some(Seen::Replied(_))
        ));
        assert!(
            d.check(now + Duration::from_secs(248), peer(), 7, t, &l)
                .is_none()
        );
        assert_eq!(d.len(), 0);
    }

    #[test]
    fn reused_message_id_with_new_token_or_block_is_new() {
        let now = crate::test_epoch();
        let l = Limits::default();
        for (first, again) in [
            (get(1, None), get(2, None)),
            (get(1, Some(0)), get(1, Some(65536))),
        ] {
            let mut d = Dedup::new();
            let lifetime = now + Duration::from_secs(247);
            d.insert(now, (peer(), 7), first, lifetime, Seen::Silent, &l);
            assert!(d.check(now, peer(), 7, again, &l).is_none());
            assert_eq!(d.len(), 0, "the older message is forgotten");
        }
    }

    #[test]
    fn dedup_store_is_bounded() {
        let now = crate::test_epoch();
        let reply = |mid| {
            let mut m = Message::empty(crate::msg::Type::Ack, mid);
            m.code = crate::msg::Code::CONTENT;
            m.payload = Bytes::from(vec![0; 15]);
            Seen::Replied(Box::new(m))
        };
        // An entry holds far more than its reply's 20 bytes on the wire.
        let each = size(&reply(0));
        assert!(each > size_of::<Message>() + 15);
        let l = Limits {
            dedup_entries: 10,
            dedup_bytes: 5 * each,
            ..Limits::default()
        };
        let mut d = Dedup::new();
        for mid in 0..50u16 {
            let reply = reply(mid);
            d.insert(
                now,
                (peer(), mid),
                get(0, None),
                now + Duration::from_secs(247),
                reply,
                &l,
            );
        }
        assert!(
            d.len() <= 5,
            "the bytes of five entries hold five, got {}",
            d.len()
        );
        assert!(
            d.check(now, peer(), 49, get(0, None), &l).is_some(),
            "newest kept"
        );
    }
}
