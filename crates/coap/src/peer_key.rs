//! Map keys made of a peer's address, hashed in two writes. The derived `Hash` of a
//! `SocketAddr` feeds the hasher field by field (family, each address byte run with its
//! length, port, and for IPv6 flow label and scope); these maps are looked up for every
//! block of a transfer, so they hash the address as one 128-bit and one 64-bit word.
//! Equality still compares the whole address.

use std::hash::{Hash, Hasher};
use std::net::SocketAddr;

/// A message exchange: the peer and a message ID.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct MidKey(pub(crate) SocketAddr, pub(crate) u16);

impl Hash for MidKey {
    fn hash<H: Hasher>(&self, state: &mut H) {
        hash_addr(&self.0, self.1, state);
    }
}

/// A peer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct PeerKey(pub(crate) SocketAddr);

impl Hash for PeerKey {
    fn hash<H: Hasher>(&self, state: &mut H) {
        hash_addr(&self.0, 0, state);
    }
}

fn hash_addr<H: Hasher>(addr: &SocketAddr, extra: u16, state: &mut H) {
    let (ip, scope) = match addr {
        SocketAddr::V4(a) => (u128::from(a.ip().to_bits()), u64::from(u32::MAX)),
        SocketAddr::V6(a) => (a.ip().to_bits(), u64::from(a.scope_id())),
    };
    state.write_u128(ip);
    state.write_u64(scope << 32 | u64::from(addr.port()) << 16 | u64::from(extra));
}

/// A map keyed by what this endpoint chose itself (request and observation ids, its own
/// tokens and message IDs, the peers it sends to): a fast seeded hash is enough there.
/// The deduplication store, keyed by message IDs that peers choose, keeps SipHash.
pub(crate) type FastMap<K, V> = std::collections::HashMap<K, V, foldhash::fast::RandomState>;

#[cfg(test)]
mod tests {
    use std::collections::HashSet;

    use super::*;

    #[test]
    fn keys_tell_families_ports_scopes_and_message_ids_apart() {
        let addrs: [SocketAddr; 5] = [
            "127.0.0.1:5683".parse().unwrap(),
            "127.0.0.1:5684".parse().unwrap(),
            "[::ffff:127.0.0.1]:5683".parse().unwrap(),
            "[fe80::1%1]:5683".parse().unwrap(),
            "[fe80::1%2]:5683".parse().unwrap(),
        ];
        let keys: HashSet<MidKey> = addrs
            .iter()
            .flat_map(|&a| [MidKey(a, 1), MidKey(a, 2)])
            .collect();
        assert_eq!(keys.len(), 10);
        assert!(keys.contains(&MidKey(addrs[2], 2)));
        let peers: HashSet<PeerKey> = addrs.iter().map(|&a| PeerKey(a)).collect();
        assert_eq!(peers.len(), 5);
    }
}
