//! Address verification (RFC 9175 §2.4, item 3): a server must not become an amplifier
//! for a peer whose source address it has not seen answer. Until a peer has returned an
//! Echo value the server gave it, the server sends that peer at most three times the
//! bytes of each request; its requests wait for a round trip that proves the address
//! (but for a bounded number of GETs sent to a group, see below).
//!
//! The Echo value is stateless: the time it was made (whole seconds since the endpoint's
//! first datagram) and a keyed 64-bit SipHash of that time and the peer's address, so a
//! spoofed source costs the server no state. The key is the one piece of randomness not
//! drawn from `rng_seed`: it must be unpredictable, so it comes from the OS
//! (`RandomState`). A verified peer is remembered for `verified_lifetime` after the Echo
//! value that proved it, up to
//! [`Limits::verified_peers`](crate::config::Limits::verified_peers) of them. Only a proof
//! renews it: any request refreshing it would let whoever spoofs a once-verified address
//! keep it open for reflection as long as they like.
//!
//! How much work an unverified peer may cause is decided before any: a unicast request
//! is challenged before the application sees it, and a GET sent to a group is handed
//! over only while the application's time spent on such requests stays within
//! [`Limits::unverified_group_work`](crate::config::Limits::unverified_group_work) a
//! second (`may_work_for_group`, a bucket of time shared by all peers), so that a member
//! can stay silent when its answer is an error (RFC 7390 §2.7).
//!
//! Loopback peers count as verified: the transport hands over a datagram with a loopback
//! source only when it came in over the loopback interface (coap-net drops the others:
//! the kernel delivers an IPv6 frame from `::ffff:127.0.0.1` arriving on any interface).

use std::hash::{BuildHasher, RandomState};
use std::net::SocketAddr;
use std::time::{Duration, Instant};

use crate::peer_key::{FastMap, PeerKey};

/// Seconds an Echo value stays good: long enough for a request that a lossy path makes a
/// client retransmit for most of MAX_TRANSMIT_SPAN.
const ECHO_VALIDITY_SECS: u32 = 60;
/// Bytes of an Echo value: the time (4) and the MAC (8).
pub(super) const ECHO_LEN: usize = 12;

/// The verifier's state.
pub(super) struct AddressCheck {
    key: RandomState,
    epoch: Option<Instant>,
    /// Verified peers and when they were last heard from.
    verified: FastMap<PeerKey, Instant>,
    /// The application's time (seconds) that group requests of unverified peers may
    /// still take (negative: overdrawn by the last one), and when it was last filled.
    group_credit: f64,
    group_filled: Option<Instant>,
}

impl AddressCheck {
    pub(super) fn new() -> Self {
        Self {
            key: RandomState::new(),
            epoch: None,
            verified: FastMap::default(),
            group_credit: 0.0,
            group_filled: None,
        }
    }

    /// Whether the application may work on one more request that an unverified peer
    /// sent to a group: while the time such requests took stays within `per_second` of
    /// every second (a bucket of time filled at that rate, up to ten seconds' worth, full
    /// at first). The caller charges what each took ([`AddressCheck::charge_group_work`]).
    pub(super) fn may_work_for_group(&mut self, now: Instant, per_second: Duration) -> bool {
        let rate = per_second.as_secs_f64();
        let full = 10.0 * rate;
        self.group_credit = match self.group_filled {
            None => full,
            Some(at) => {
                let elapsed = now.saturating_duration_since(at).as_secs_f64();
                (self.group_credit + elapsed * rate).min(full)
            }
        };
        self.group_filled = Some(now);
        self.group_credit > 0.0
    }

    /// A request that [`AddressCheck::may_work_for_group`] let through took `took`.
    pub(super) fn charge_group_work(&mut self, took: Duration) {
        self.group_credit -= took.as_secs_f64();
    }

    fn secs(&mut self, now: Instant) -> u32 {
        let epoch = *self.epoch.get_or_insert(now);
        u32::try_from(now.saturating_duration_since(epoch).as_secs()).unwrap_or(u32::MAX)
    }

    fn mac(&self, peer: SocketAddr, t: u32) -> u64 {
        self.key.hash_one((peer, t))
    }

    /// The Echo value to challenge `peer` with.
    pub(super) fn echo(&mut self, now: Instant, peer: SocketAddr) -> [u8; ECHO_LEN] {
        let t = self.secs(now);
        let mut value = [0u8; ECHO_LEN];
        value[..4].copy_from_slice(&t.to_be_bytes());
        value[4..].copy_from_slice(&self.mac(peer, t).to_be_bytes());
        value
    }

    /// Whether `peer` may be sent more than three times what it sent: it returned a fresh
    /// Echo value made for it, now or within `lifetime`. Only a fresh Echo value renews
    /// the verification; other requests, which anyone can send in its name, do not.
    pub(super) fn is_verified(
        &mut self,
        now: Instant,
        peer: SocketAddr,
        echo: Option<&[u8]>,
        lifetime: Duration,
        limit: usize,
    ) -> bool {
        if peer.ip().to_canonical().is_loopback() {
            return true;
        }
        let fresh = echo.is_some_and(|e| self.echo_is_good(now, peer, e));
        if fresh {
            self.remember(now, peer, lifetime, limit);
            return true;
        }
        self.verified
            .get(&PeerKey(peer))
            .is_some_and(|proved| now.saturating_duration_since(*proved) < lifetime)
    }

    fn echo_is_good(&mut self, now: Instant, peer: SocketAddr, echo: &[u8]) -> bool {
        let Ok(value) = <[u8; ECHO_LEN]>::try_from(echo) else {
            return false;
        };
        let t = u32::from_be_bytes([value[0], value[1], value[2], value[3]]);
        let mac = u64::from_be_bytes(value[4..].try_into().unwrap_or_default());
        let age = self.secs(now).checked_sub(t);
        age.is_some_and(|a| a <= ECHO_VALIDITY_SECS) && mac == self.mac(peer, t)
    }

    /// Adds (or renews) a verified peer; at the limit, peers proved more than `lifetime`
    /// ago go first, then the one proved longest ago.
    fn remember(&mut self, now: Instant, peer: SocketAddr, lifetime: Duration, limit: usize) {
        if self.verified.len() >= limit && !self.verified.contains_key(&PeerKey(peer)) {
            self.verified
                .retain(|_, seen| now.saturating_duration_since(*seen) < lifetime);
        }
        if self.verified.len() >= limit.max(1)
            && !self.verified.contains_key(&PeerKey(peer))
            && let Some(oldest) = self
                .verified
                .iter()
                .min_by_key(|(_, seen)| **seen)
                .map(|(k, _)| *k)
        {
            self.verified.remove(&oldest);
        }
        self.verified.insert(PeerKey(peer), now);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const LIFE: Duration = Duration::from_secs(600);

    fn peer(n: u8) -> SocketAddr {
        SocketAddr::from(([192, 0, 2, n], 40000))
    }

    #[test]
    fn an_echo_verifies_only_the_peer_it_was_made_for_and_only_while_fresh() {
        let mut check = AddressCheck::new();
        let t0 = crate::test_epoch();
        assert!(!check.is_verified(t0, peer(1), None, LIFE, 8));
        let echo = check.echo(t0, peer(1));
        assert!(!check.is_verified(t0, peer(2), Some(&echo), LIFE, 8));
        let mut forged = echo;
        forged[11] ^= 1;
        assert!(!check.is_verified(t0, peer(1), Some(&forged), LIFE, 8));
        let late = t0 + Duration::from_secs(u64::from(ECHO_VALIDITY_SECS) + 1);
        assert!(!check.is_verified(late, peer(1), Some(&echo), LIFE, 8));
        assert!(check.is_verified(t0 + Duration::from_secs(5), peer(1), Some(&echo), LIFE, 8));
        // Remembered without an Echo for LIFE after the proof; requests without one do
        // not extend it, a new Echo does.
        assert!(check.is_verified(t0 + Duration::from_secs(500), peer(1), None, LIFE, 8));
        assert!(!check.is_verified(t0 + Duration::from_secs(605), peer(1), None, LIFE, 8));
        let at = t0 + Duration::from_secs(700);
        let echo = check.echo(at, peer(1));
        assert!(check.is_verified(at, peer(1), Some(&echo), LIFE, 8));
        assert!(check.is_verified(at + Duration::from_secs(599), peer(1), None, LIFE, 8));
        assert!(!check.is_verified(at + Duration::from_secs(600), peer(1), None, LIFE, 8));
    }

    #[test]
    fn unverified_group_work_is_bounded_in_time_per_second() {
        let t0 = crate::test_epoch();
        let ms = Duration::from_millis;
        let mut check = AddressCheck::new();
        // Ten seconds' worth of 50 ms at first: 500 ms. Two requests of 300 ms pass (the
        // second overdraws), a third waits.
        assert!(check.may_work_for_group(t0, ms(50)));
        check.charge_group_work(ms(300));
        assert!(check.may_work_for_group(t0 + ms(300), ms(50)));
        check.charge_group_work(ms(300));
        // 500 - 600 + 0.6 s x 50 ms/s = -70 ms: refilled after 1.4 s more.
        assert!(!check.may_work_for_group(t0 + ms(600), ms(50)));
        assert!(!check.may_work_for_group(t0 + ms(1900), ms(50)));
        assert!(check.may_work_for_group(t0 + ms(2100), ms(50)));
        // Never more than ten seconds' worth after a long quiet.
        let mut quiet = AddressCheck::new();
        assert!(quiet.may_work_for_group(t0, ms(50)));
        let later = t0 + Duration::from_secs(600);
        assert!(quiet.may_work_for_group(later, ms(50)));
        quiet.charge_group_work(ms(501));
        assert!(!quiet.may_work_for_group(later, ms(50)));
        // Zero allows none.
        assert!(!AddressCheck::new().may_work_for_group(t0, Duration::ZERO));
    }

    #[test]
    fn loopback_is_verified_and_the_table_stays_bounded() {
        let mut check = AddressCheck::new();
        let t0 = crate::test_epoch();
        assert!(check.is_verified(t0, "127.0.0.1:1".parse().unwrap(), None, LIFE, 2));
        assert!(check.is_verified(t0, "[::ffff:127.0.0.1]:1".parse().unwrap(), None, LIFE, 2));
        assert!(check.is_verified(t0, "[::1]:1".parse().unwrap(), None, LIFE, 2));
        for n in 1..=5 {
            let at = t0 + Duration::from_secs(u64::from(n));
            let echo = check.echo(at, peer(n));
            assert!(check.is_verified(at, peer(n), Some(&echo), LIFE, 2));
            assert!(check.verified.len() <= 2);
        }
        // The two proved last are kept.
        let later = t0 + Duration::from_secs(6);
        assert!(check.is_verified(later, peer(5), None, LIFE, 2));
        assert!(check.is_verified(later, peer(4), None, LIFE, 2));
        assert!(!check.is_verified(later, peer(1), None, LIFE, 2));
    }
}
