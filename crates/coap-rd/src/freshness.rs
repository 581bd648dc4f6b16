//! The directory's own Echo values (RFC 9175 §2.3), sans-IO: proof, per request, that
//! the sender receives at its source address now.
//!
//! The CoAP layer's address check remembers a verified address for minutes, so anyone
//! can forge a request from an address it verified (a station's server socket, which
//! registers from there). The directory asks more of the requests that change a
//! registration, and of lookups whose answer is larger than three times the request
//! (`service`): each must carry an Echo value the directory made for that very address
//! (IP and port) within [`VALIDITY_MS`]; without one it answers 4.01 with a new value,
//! and the client sends the request again with it (coapcam's and libcoap's clients do
//! this on their own).
//!
//! A value is the time it was made (milliseconds since the UNIX epoch, 8 bytes) and a
//! keyed 64-bit SipHash of that time and the address (8 bytes): no state per sender.
//! The key comes from the OS (`RandomState`), so nobody can make a value without
//! receiving one. Its 16 bytes tell it from the CoAP layer's 12-byte values.

use std::hash::{BuildHasher, RandomState};
use std::net::SocketAddr;

/// How long an Echo value is good for, milliseconds: one request's round trips.
pub const VALIDITY_MS: u64 = 30_000;

/// Bytes of a value: the time (8) and the MAC (8).
pub const ECHO_LEN: usize = 16;

/// Makes and checks the directory's Echo values.
#[derive(Debug, Default)]
pub struct Freshness {
    key: RandomState,
}

impl Freshness {
    /// A new key.
    #[must_use]
    pub fn new() -> Self {
        Self::default()
    }

    fn mac(&self, peer: SocketAddr, t: u64) -> u64 {
        self.key.hash_one((peer, t))
    }

    /// The value to challenge `peer` with at `now_ms`.
    #[must_use]
    pub fn value(&self, now_ms: u64, peer: SocketAddr) -> [u8; ECHO_LEN] {
        let mut v = [0u8; ECHO_LEN];
        v[..8].copy_from_slice(&now_ms.to_be_bytes());
        v[8..].copy_from_slice(&self.mac(peer, now_ms).to_be_bytes());
        v
    }

    /// Whether `echo` is a value made for `peer` no more than [`VALIDITY_MS`] before
    /// `now_ms` (and not after it).
    #[must_use]
    pub fn is_fresh(&self, now_ms: u64, peer: SocketAddr, echo: Option<&[u8]>) -> bool {
        let Some(value) = echo.and_then(|e| <[u8; ECHO_LEN]>::try_from(e).ok()) else {
            return false;
        };
        let (t, mac) = value.split_at(8);
        let t = u64::from_be_bytes(t.try_into().unwrap_or_default());
        let mac = u64::from_be_bytes(mac.try_into().unwrap_or_default());
        now_ms.checked_sub(t).is_some_and(|age| age <= VALIDITY_MS) && mac == self.mac(peer, t)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const T0: u64 = 1_800_000_000_000;

    fn addr(s: &str) -> SocketAddr {
        s.parse().expect("an address")
    }

    #[test]
    fn a_value_proves_only_its_own_address_and_only_while_fresh() {
        let f = Freshness::new();
        let station = addr("[fd00::3]:5683");
        let v = f.value(T0, station);
        assert!(f.is_fresh(T0, station, Some(&v)));
        assert!(f.is_fresh(T0 + VALIDITY_MS, station, Some(&v)));
        assert!(!f.is_fresh(T0 + VALIDITY_MS + 1, station, Some(&v)));
        // Not before it was made (a clock set back), not for another port or address.
        assert!(!f.is_fresh(T0 - 1, station, Some(&v)));
        assert!(!f.is_fresh(T0, addr("[fd00::3]:5684"), Some(&v)));
        assert!(!f.is_fresh(T0, addr("[fd00::4]:5683"), Some(&v)));
        // Nothing, a changed MAC or time, another length, another key's value.
        assert!(!f.is_fresh(T0, station, None));
        let mut forged = v;
        forged[15] ^= 1;
        assert!(!f.is_fresh(T0, station, Some(&forged)));
        let mut moved = v;
        moved[7] ^= 1;
        assert!(!f.is_fresh(T0, station, Some(&moved)));
        assert!(!f.is_fresh(T0, station, Some(&v[..12])));
        assert!(!Freshness::new().is_fresh(T0, station, Some(&v)));
    }
}
