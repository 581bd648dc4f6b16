//! netem: a userspace UDP link emulator, the relay behind `coapcam netem`.
//!
//! Clients send to the listen address; each datagram goes on to the forward address from a socket of its
//! own per client address (created on the client's first datagram), so that whatever the
//! server answers on that socket goes back to that client from the listen socket.
//!
//! Each direction ("up" = client -> server, "down" = server -> client) has its own loss
//! probability, delay, jitter, rate limit and random generator. The decisions live in
//! [`Link`], which takes the arrival time as an argument and reads no clock, so it is
//! tested without sockets; [`Netem::run`] is the driver: one task, one timer heap of
//! pending datagrams, one `sleep_until` on the earliest.
//!
//! Per datagram, in this order:
//! 1. two draws from the direction's ChaCha8 generator (seeded by the configuration's seed, one stream per
//!    direction): the loss draw, then the jitter draw. Both are taken whatever the outcome,
//!    so a replay with the same seed and the same arrival order per direction makes the same
//!    decisions, and changing the loss leaves the jitter of every datagram as it was;
//! 2. lost with the direction's probability;
//! 3. dropped as an overflow when the direction already holds the queue limit's datagrams;
//! 4. rate limit: it leaves the serializer at `max(arrival, previous departure) +
//!    len / rate` (payload bytes only, no header overhead);
//! 5. then it is delivered `delay ± jitter` later (uniform, clamped at zero, like the
//!    kernel's netem). Jitter reorders datagrams whose delays differ by more than
//!    their spacing; with no jitter the order of a direction is kept.
//!
//! Datagrams that the OS drops before netem reads them (a burst beyond the 4 MiB receive
//! buffer it asks for) are not counted; nor are bytes of UDP/IP headers.

mod link;
mod relay;

pub use link::{Counters, Dir, DirConfig, DirCounters, Fate, Link, LinkConfig};
pub use relay::{DeliveredBytes, MAX_CLIENTS, Netem, NetemError};
