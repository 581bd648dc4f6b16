//! UDP sockets for CoAP: IPv4 and IPv6, multicast membership, and the destination address
//! of every received datagram (so a request sent to a group is known as one).

use std::io::{self, IoSliceMut};
use std::net::{IpAddr, Ipv4Addr, Ipv6Addr, SocketAddr, SocketAddrV6};
use std::task::{Context, Poll};

use quinn_udp::{RecvMeta, UdpSockRef, UdpSocketState};
use socket2::{Domain, Protocol, Socket as RawSocket, Type};
use tokio::io::Interest;

/// The largest datagram a CoAP endpoint receives (the IPv4 UDP maximum).
pub const MAX_DATAGRAM: usize = 65_507;

/// A receive buffer this large (two halves of 64 KiB, each above [`MAX_DATAGRAM`]) takes
/// two datagrams per call to [`Socket::poll_recv`]. When only one was waiting the socket
/// is known to be drained, and the next wait goes straight to the poller instead of first
/// trying a receive that finds nothing (one system call less per datagram in a
/// stop-and-wait exchange). At 128 KiB a zeroed buffer comes from fresh pages (glibc by
/// default maps allocations this large), so only the pages datagrams reach become
/// resident, and nothing is cleared up front.
pub const RECV_BUFFER: usize = 2 << 16;

/// One received datagram.
#[derive(Debug, Clone, Copy)]
pub struct Received {
    /// Sender.
    pub peer: SocketAddr,
    /// Offset and length in the receive buffer.
    pub range: (usize, usize),
    /// Whether it was addressed to a multicast group.
    pub multicast: bool,
}

/// A UDP socket bound for CoAP.
#[derive(Debug)]
pub struct Socket {
    io: tokio::net::UdpSocket,
    state: UdpSocketState,
    local: SocketAddr,
}

impl Socket {
    /// Binds `addr`. Address reuse is on, so several servers on one host can share a
    /// multicast port; an IPv6 wildcard bind is IPv6-only, so `0.0.0.0:5683` and
    /// `[::]:5683` can be bound side by side.
    pub fn bind(addr: SocketAddr) -> io::Result<Self> {
        let raw = RawSocket::new(Domain::for_address(addr), Type::DGRAM, Some(Protocol::UDP))?;
        raw.set_reuse_address(true)?;
        if addr.is_ipv6() {
            raw.set_only_v6(true)?;
        }
        raw.set_nonblocking(true)?;
        raw.bind(&addr.into())?;
        let std: std::net::UdpSocket = raw.into();
        let io = tokio::net::UdpSocket::from_std(std)?;
        let state = UdpSocketState::new(UdpSockRef::from(&io))?;
        let local = io.local_addr()?;
        Ok(Self { io, state, local })
    }

    /// A socket that receives the datagrams sent to `group` on `port`: bound to the group
    /// address itself (so it sees no unicast traffic) and joined on `interface` (an IPv6
    /// interface index; for IPv4 the routing table picks the interface).
    pub fn bind_group(group: IpAddr, port: u16, interface: u32) -> io::Result<Self> {
        let addr = match group {
            IpAddr::V4(g) => SocketAddr::from((g, port)),
            IpAddr::V6(g) => SocketAddr::V6(SocketAddrV6::new(g, port, 0, interface)),
        };
        let socket = Self::bind(addr)?;
        socket.join(group, interface)?;
        Ok(socket)
    }

    /// The bound address.
    pub fn local_addr(&self) -> SocketAddr {
        self.local
    }

    /// Polls for datagrams (for a set of sockets polled together). A `buf` of
    /// [`RECV_BUFFER`] bytes or more takes two datagrams per call.
    pub fn poll_recv(
        &self,
        cx: &mut Context<'_>,
        buf: &mut [u8],
        out: &mut Vec<Received>,
    ) -> Poll<io::Result<()>> {
        loop {
            std::task::ready!(self.io.poll_recv_ready(cx))?;
            let mut meta = [RecvMeta::default(), RecvMeta::default()];
            let half = if buf.len() >= RECV_BUFFER {
                buf.len() / 2
            } else {
                buf.len()
            };
            let k = if half < buf.len() { 2 } else { 1 };
            let mut got = 0;
            let r = self.io.try_io(Interest::READABLE, || {
                let (first, second) = buf.split_at_mut(half);
                let mut slices = [IoSliceMut::new(first), IoSliceMut::new(second)];
                got = self.state.recv(
                    UdpSockRef::from(&self.io),
                    &mut slices[..k],
                    &mut meta[..k],
                )?;
                if got < k {
                    // Fewer than asked for: the socket is drained. Saying so lets tokio
                    // clear its readiness now rather than after a receive that finds
                    // nothing; a datagram arriving meanwhile sets it again.
                    return Err(io::ErrorKind::WouldBlock.into());
                }
                Ok(())
            });
            if got > 0 {
                split(&meta[..got], half, out);
                return Poll::Ready(Ok(()));
            }
            match r {
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => {}
                Err(e) => return Poll::Ready(Err(e)),
                // Only with datagrams, which returned above.
                Ok(()) => {
                    out.clear();
                    return Poll::Ready(Ok(()));
                }
            }
        }
    }

    /// Joins a multicast group; `interface` is an IPv6 interface index (0: the default) and
    /// is ignored for IPv4, which joins on the interface the routing table picks.
    pub fn join(&self, group: IpAddr, interface: u32) -> io::Result<()> {
        match group {
            IpAddr::V4(g) => self.io.join_multicast_v4(g, Ipv4Addr::UNSPECIFIED),
            IpAddr::V6(g) => self.io.join_multicast_v6(&g, interface),
        }
    }

    /// Leaves a multicast group.
    pub fn leave(&self, group: IpAddr, interface: u32) -> io::Result<()> {
        match group {
            IpAddr::V4(g) => self.io.leave_multicast_v4(g, Ipv4Addr::UNSPECIFIED),
            IpAddr::V6(g) => self.io.leave_multicast_v6(&g, interface),
        }
    }

    /// Multicast sends go out on this interface (IPv4 address or IPv6 interface index) and
    /// loop back to local listeners.
    pub fn set_multicast_interface(
        &self,
        v4: Option<Ipv4Addr>,
        v6_index: Option<u32>,
    ) -> io::Result<()> {
        let raw = socket2::SockRef::from(&self.io);
        match self.local {
            SocketAddr::V4(_) => {
                raw.set_multicast_loop_v4(true)?;
                if let Some(a) = v4 {
                    raw.set_multicast_if_v4(&a)?;
                }
            }
            SocketAddr::V6(_) => {
                raw.set_multicast_loop_v6(true)?;
                if let Some(i) = v6_index {
                    raw.set_multicast_if_v6(i)?;
                }
            }
        }
        Ok(())
    }

    /// Sends one datagram.
    pub async fn send_to(&self, data: &[u8], peer: SocketAddr) -> io::Result<()> {
        self.io.send_to(data, peer).await.map(|_| ())
    }

    /// Waits for datagrams and writes them into `buf`, filling `out` with one entry per
    /// datagram (the kernel may hand several same-sized datagrams over at once).
    pub async fn recv(&self, buf: &mut [u8], out: &mut Vec<Received>) -> io::Result<()> {
        std::future::poll_fn(|cx| self.poll_recv(cx, buf, out)).await
    }
}

/// One entry per datagram; the i-th buffer starts at `i * slice_len`, and a GRO-coalesced
/// buffer holds several datagrams of `stride` bytes.
fn split(meta: &[RecvMeta], slice_len: usize, out: &mut Vec<Received>) {
    out.clear();
    for (i, m) in meta.iter().enumerate() {
        let multicast = m.dst_ip.is_some_and(is_multicast);
        let stride = m.stride.max(1);
        let base = i * slice_len;
        let mut start = 0;
        while start < m.len {
            let len = stride.min(m.len - start);
            out.push(Received {
                peer: m.addr,
                range: (base + start, len),
                multicast,
            });
            start += stride;
        }
    }
}

fn is_multicast(ip: IpAddr) -> bool {
    match ip {
        IpAddr::V4(a) => a.is_multicast(),
        IpAddr::V6(a) => a.is_multicast() || a.to_ipv4_mapped().is_some_and(|v4| v4.is_multicast()),
    }
}

/// The "All CoAP Nodes" groups (RFC 7252 §12.8).
pub mod groups {
    use super::*;

    /// IPv4 224.0.1.187.
    pub const ALL_COAP_V4: Ipv4Addr = Ipv4Addr::new(224, 0, 1, 187);
    /// IPv6 link-local ff02::fd.
    pub const ALL_COAP_V6_LINK: Ipv6Addr = Ipv6Addr::new(0xff02, 0, 0, 0, 0, 0, 0, 0xfd);
    /// IPv6 site-local ff05::fd.
    pub const ALL_COAP_V6_SITE: Ipv6Addr = Ipv6Addr::new(0xff05, 0, 0, 0, 0, 0, 0, 0xfd);
}
