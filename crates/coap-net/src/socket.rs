//! UDP sockets for CoAP: IPv4 and IPv6, multicast membership, and whether each received
//! datagram was sent to a group (so a request sent to a group is known as one).
//!
//! A socket bound to one address, unicast or a group's, knows every datagram's destination
//! from its bind, and receives with a plain `recvfrom`. Only a wildcard-bound socket that
//! joins a group must read each datagram's destination (IP_PKTINFO, through quinn-udp's
//! `recvmmsg`): that costs about 0.3 µs per datagram, a fifth of a loopback round trip's
//! system time, so it is set up at the first join. Until then such a socket receives no
//! group's datagrams: on Linux, sockets are made to receive only the groups they joined
//! themselves (IP_MULTICAST_ALL off), not those another socket on the same port joined.

use std::io::{self, IoSliceMut};
use std::net::{IpAddr, Ipv4Addr, Ipv6Addr, SocketAddr, SocketAddrV6};
use std::sync::OnceLock;
use std::time::Duration;

use quinn_udp::{RecvMeta, UdpSockRef, UdpSocketState};
use socket2::{Domain, Protocol, SockRef, Socket as RawSocket, Type};

/// The receive buffer: room for the largest datagram, or for several same-sized ones the
/// kernel coalesced (GRO, asked for together with destinations). Each socket thread
/// zeroes its buffer once, when it starts.
pub const RECV_BUFFER: usize = 1 << 16;

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

/// A UDP socket bound for CoAP. Receives block (up to the read timeout): the socket's own
/// thread waits in the receive itself, with no poller in between (see `driver`).
#[derive(Debug)]
pub struct Socket {
    io: std::net::UdpSocket,
    /// quinn-udp's receive state, once datagrams' destinations must be read (a wildcard
    /// socket joined a group).
    destinations: OnceLock<UdpSocketState>,
    local: SocketAddr,
}

/// The index of the interface that has the IPv6 address `addr`.
fn interface_of(addr: Ipv6Addr) -> io::Result<u32> {
    let found = nix::ifaddrs::getifaddrs()
        .map_err(io::Error::from)?
        .find(|i| {
            i.address
                .as_ref()
                .and_then(|a| a.as_sockaddr_in6())
                .is_some_and(|a| a.ip() == addr)
        })
        .map(|i| nix::net::if_::if_nametoindex(i.interface_name.as_str()));
    match found {
        Some(index) => index.map_err(io::Error::from),
        None => Err(io::Error::new(
            io::ErrorKind::AddrNotAvailable,
            format!("no interface has {addr}"),
        )),
    }
}

/// The receive buffer a socket asks the kernel for: 4 MiB.
const RECV_SOCKET_BUFFER: usize = 4 << 20;

impl Socket {
    /// Binds `addr`. Only a group address is bound with address reuse, so that several
    /// servers on one host can each receive a group's datagrams; a unicast or wildcard
    /// address is this socket's alone, and binding one that is taken fails with
    /// `AddrInUse` (with reuse on, a second server would bind it as well and take the
    /// first one's traffic). An IPv6 wildcard bind is IPv6-only, so `0.0.0.0:5683` and
    /// `[::]:5683` can be bound side by side.
    pub fn bind(addr: SocketAddr) -> io::Result<Self> {
        let raw = RawSocket::new(Domain::for_address(addr), Type::DGRAM, Some(Protocol::UDP))?;
        if addr.ip().is_multicast() {
            raw.set_reuse_address(true)?;
        }
        if addr.is_ipv6() {
            raw.set_only_v6(true)?;
        }
        // A server with many clients (or a client with a window of blocks in flight)
        // receives bursts; the kernel's default buffer (about 200 KB) drops them while the
        // endpoint's thread is busy. The kernel caps this at net.core.rmem_max.
        if let Err(e) = raw.set_recv_buffer_size(RECV_SOCKET_BUFFER) {
            tracing::debug!(error = %e, "the socket keeps the kernel's receive buffer size");
        }
        raw.bind(&addr.into())?;
        let local: SocketAddr = raw
            .local_addr()?
            .as_socket()
            .ok_or_else(|| io::Error::other("bound to a non-IP address"))?;
        let socket = Self {
            io: raw.into(),
            destinations: OnceLock::new(),
            local,
        };
        socket.queue_errors();
        // Only a wildcard-bound socket can receive a group's datagrams without having
        // joined it itself; where that cannot be turned off, it reads every destination.
        if local.ip().is_unspecified() && !socket.only_own_groups() {
            socket.read_destinations()?;
        }
        Ok(socket)
    }

    /// Asks the kernel to queue the ICMP errors the socket's datagrams cause (IP_RECVERR):
    /// an unconnected socket is otherwise never told that a port is unreachable. A
    /// receive then fails once per queued error, and [`Socket::unreachable`] reads them.
    #[cfg(target_os = "linux")]
    fn queue_errors(&self) {
        use nix::sys::socket::{setsockopt, sockopt};
        let set = match self.local {
            SocketAddr::V4(_) => setsockopt(&self.io, sockopt::Ipv4RecvErr, &true),
            SocketAddr::V6(_) => setsockopt(&self.io, sockopt::Ipv6RecvErr, &true),
        };
        if let Err(e) = set {
            tracing::debug!(error = %e, "ICMP errors are not reported on this socket");
        }
    }

    #[cfg(not(target_os = "linux"))]
    fn queue_errors(&self) {}

    /// The destinations of earlier datagrams that the network answered with ICMP "port
    /// unreachable" (nothing listens there), read from the socket's error queue; other
    /// errors are read and dropped. Empty where the queue cannot be read.
    #[cfg(target_os = "linux")]
    pub fn unreachable(&self) -> Vec<SocketAddr> {
        use std::os::fd::AsRawFd as _;

        use nix::errno::Errno;
        use nix::libc;
        use nix::sys::socket::{ControlMessageOwned, MsgFlags, SockaddrStorage, recvmsg};

        let mut peers = Vec::new();
        let mut data = [0u8; 64];
        let mut control = nix::cmsg_space!(libc::sock_extended_err, libc::sockaddr_in6);
        // At most a bounded number per call: the queue holds what arrived so far.
        for _ in 0..64 {
            let mut iov = [IoSliceMut::new(&mut data)];
            let got = recvmsg::<SockaddrStorage>(
                self.io.as_raw_fd(),
                &mut iov,
                Some(&mut control),
                MsgFlags::MSG_ERRQUEUE | MsgFlags::MSG_DONTWAIT,
            );
            let Ok(msg) = got else { break };
            let refused = msg.cmsgs().into_iter().flatten().any(|c| match c {
                ControlMessageOwned::Ipv4RecvErr(e, _) | ControlMessageOwned::Ipv6RecvErr(e, _) => {
                    e.ee_errno == Errno::ECONNREFUSED as u32
                }
                _ => false,
            });
            let destination = msg.address.and_then(|a| {
                a.as_sockaddr_in()
                    .map(|v4| SocketAddr::V4((*v4).into()))
                    .or_else(|| a.as_sockaddr_in6().map(|v6| SocketAddr::V6((*v6).into())))
            });
            if let (true, Some(peer)) = (refused, destination) {
                peers.push(peer);
            }
        }
        peers
    }

    #[cfg(not(target_os = "linux"))]
    pub fn unreachable(&self) -> Vec<SocketAddr> {
        Vec::new()
    }

    /// Makes the socket receive only the groups it joins itself; false where that cannot
    /// be asked for.
    #[cfg(target_os = "linux")]
    fn only_own_groups(&self) -> bool {
        let raw = SockRef::from(&self.io);
        match self.local {
            SocketAddr::V4(_) => raw.set_multicast_all_v4(false).is_ok(),
            SocketAddr::V6(_) => raw.set_multicast_all_v6(false).is_ok(),
        }
    }

    #[cfg(not(target_os = "linux"))]
    fn only_own_groups(&self) -> bool {
        false
    }

    /// From now on, reads each datagram's destination address. quinn-udp asks for it (and
    /// for coalesced receives) and makes the socket non-blocking; receives here block.
    fn read_destinations(&self) -> io::Result<()> {
        if self.destinations.get().is_none() {
            let state = UdpSocketState::new(UdpSockRef::from(&self.io))?;
            self.io.set_nonblocking(false)?;
            let _ = self.destinations.set(state);
        }
        Ok(())
    }

    /// A socket that receives the datagrams sent to `group` on `port` for a server bound
    /// to the unicast address `on`: bound to the group address itself (so it sees no
    /// unicast traffic) and joined on the interface that has `on`, so a server bound to
    /// 127.0.0.1 listens to the group on loopback only, never on the interface of the
    /// default route. An IPv6 `interface` index other than 0 is taken as given.
    pub fn bind_group(group: IpAddr, port: u16, interface: u32, on: IpAddr) -> io::Result<Self> {
        let interface = match (group, on) {
            (IpAddr::V6(_), IpAddr::V6(a)) if interface == 0 => interface_of(a)?,
            _ => interface,
        };
        let addr = match group {
            IpAddr::V4(g) => SocketAddr::from((g, port)),
            IpAddr::V6(g) => SocketAddr::V6(SocketAddrV6::new(g, port, 0, interface)),
        };
        let socket = Self::bind(addr)?;
        match (group, on) {
            (IpAddr::V4(g), IpAddr::V4(a)) => socket.io.join_multicast_v4(&g, &a)?,
            _ => socket.join(group, interface)?,
        }
        Ok(socket)
    }

    /// The bound address.
    pub fn local_addr(&self) -> SocketAddr {
        self.local
    }

    /// How long [`Socket::recv`] waits at most (`None`: without end).
    pub fn set_read_timeout(&self, timeout: Option<Duration>) -> io::Result<()> {
        self.io.set_read_timeout(timeout)
    }

    /// Waits for a datagram (up to the read timeout: then an error of kind `WouldBlock`)
    /// and writes it into `buf`, filling `out` with one entry per datagram (the kernel may
    /// hand several same-sized datagrams over at once).
    pub fn recv(&self, buf: &mut [u8], out: &mut Vec<Received>) -> io::Result<()> {
        let Some(state) = self.destinations.get() else {
            let (len, peer) = self.io.recv_from(buf)?;
            out.clear();
            out.push(Received {
                peer,
                range: (0, len),
                multicast: self.local.ip().is_multicast(),
            });
            return Ok(());
        };
        let mut meta = [RecvMeta::default()];
        let mut slices = [IoSliceMut::new(buf)];
        let got = state.recv(UdpSockRef::from(&self.io), &mut slices, &mut meta)?;
        split(&meta[..got], out);
        Ok(())
    }

    /// Joins a multicast group; `interface` is an IPv6 interface index (0: the default) and
    /// is ignored for IPv4, which joins on the interface the routing table picks. Call it
    /// from the thread that receives: a wildcard socket starts reading destinations here,
    /// and a receive already waiting on another thread would not.
    pub fn join(&self, group: IpAddr, interface: u32) -> io::Result<()> {
        if self.local.ip().is_unspecified() {
            self.read_destinations()?;
        }
        match group {
            IpAddr::V4(g) => self.io.join_multicast_v4(&g, &Ipv4Addr::UNSPECIFIED),
            IpAddr::V6(g) => self.io.join_multicast_v6(&g, interface),
        }
    }

    /// Leaves a multicast group.
    pub fn leave(&self, group: IpAddr, interface: u32) -> io::Result<()> {
        match group {
            IpAddr::V4(g) => self.io.leave_multicast_v4(&g, &Ipv4Addr::UNSPECIFIED),
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
        let raw = SockRef::from(&self.io);
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
    pub fn send_to(&self, data: &[u8], peer: SocketAddr) -> io::Result<()> {
        self.io.send_to(data, peer).map(|_| ())
    }
}

/// One entry per datagram; a GRO-coalesced buffer holds several datagrams of `stride`
/// bytes.
fn split(meta: &[RecvMeta], out: &mut Vec<Received>) {
    out.clear();
    for m in meta {
        let multicast = m.dst_ip.is_some_and(is_multicast);
        let stride = m.stride.max(1);
        let mut start = 0;
        if m.len == 0 {
            // An empty datagram is one too (the driver's wake-ups are empty).
            out.push(Received {
                peer: m.addr,
                range: (0, 0),
                multicast,
            });
        }
        while start < m.len {
            let len = stride.min(m.len - start);
            out.push(Received {
                peer: m.addr,
                range: (start, len),
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
