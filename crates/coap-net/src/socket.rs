//! UDP sockets for CoAP: IPv4 and IPv6, multicast membership, and for each received
//! datagram whether it was sent to a group (so a request sent to a group is known as one)
//! and whether it arrived over the loopback interface (so "this machine" is known by where
//! a datagram came in, never by what its source address looks like).
//!
//! A server's sockets, and any socket that joins a group, read each datagram's IP_PKTINFO
//! / IPV6_PKTINFO: its destination address and the index of the interface it arrived on
//! ([`Socket::read_arrivals`]). A source address proves nothing: an IPv6 frame from
//! `::ffff:127.0.0.1` arriving on a network interface is delivered to a socket bound to
//! `[::]`, and with `route_localnet` so is an IPv4 one from 127.0.0.1. The arrival
//! interface cannot be forged by a remote sender: only this machine's own traffic comes in
//! over loopback. It costs a control message per datagram (about 0.4 µs of a 1.5 µs
//! receive, docs/design.md, "Who is this machine"), so a socket that only sends requests
//! and joins no group receives with a plain `recvfrom`.
//!
//! On Linux, sockets are made to receive only the groups they joined themselves
//! (IP_MULTICAST_ALL off), not those another socket on the same port joined.

use std::io::{self, IoSliceMut};
use std::net::{IpAddr, Ipv4Addr, Ipv6Addr, SocketAddr, SocketAddrV6};
use std::sync::OnceLock;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use socket2::{Domain, Protocol, SockRef, Socket as RawSocket, Type};

/// The receive buffer: room for the largest datagram. Each socket thread zeroes its
/// buffer once, when it starts.
pub const RECV_BUFFER: usize = 1 << 16;

/// One received datagram: its first `len` bytes of the receive buffer.
#[derive(Debug, Clone, Copy)]
pub struct Received {
    /// Sender.
    pub peer: SocketAddr,
    /// Its length.
    pub len: usize,
    /// Whether it was addressed to a multicast group.
    pub multicast: bool,
    /// Whether it arrived over a loopback interface, that is from a program on this
    /// machine; `None` when the socket does not read arrivals (false when it does and the
    /// kernel did not say).
    pub loopback: Option<bool>,
}

impl Received {
    /// A source address that only this machine may use (127.0.0.0/8, ::1, or an IPv4-mapped
    /// 127.x) on a datagram that did not come in over loopback: forged. Nothing can reach a
    /// remote sender at such an address, and an answer would go to a program of this
    /// machine instead, so such datagrams are dropped, not answered.
    pub fn forged_loopback(&self) -> bool {
        self.loopback == Some(false) && self.peer.ip().to_canonical().is_loopback()
    }
}

/// A UDP socket bound for CoAP. Receives block (up to the read timeout): the socket's own
/// thread waits in the receive itself, with no poller in between (see `driver`).
#[derive(Debug)]
pub struct Socket {
    io: std::net::UdpSocket,
    local: SocketAddr,
    /// Whether each datagram's destination and arrival interface are read.
    arrivals: AtomicBool,
}

/// The indexes of this machine's loopback interfaces (IFF_LOOPBACK), read once. Empty if
/// they cannot be read: then no datagram counts as this machine's, which refuses local
/// programs rather than admitting remote ones.
fn loopback_interfaces() -> &'static [u32] {
    static LOOPBACK: OnceLock<Vec<u32>> = OnceLock::new();
    LOOPBACK.get_or_init(|| {
        use nix::net::if_::{InterfaceFlags, if_nametoindex};
        let all = match nix::ifaddrs::getifaddrs() {
            Ok(all) => all,
            Err(e) => {
                tracing::warn!(error = %e, "the loopback interface is unknown: no datagram counts as this machine's");
                return Vec::new();
            }
        };
        let mut found: Vec<u32> = all
            .filter(|i| i.flags.contains(InterfaceFlags::IFF_LOOPBACK))
            .filter_map(|i| if_nametoindex(i.interface_name.as_str()).ok())
            .collect();
        found.sort_unstable();
        found.dedup();
        if found.is_empty() {
            tracing::warn!("no loopback interface: no datagram counts as this machine's");
        }
        found
    })
}

/// Room for one IP_PKTINFO or IPV6_PKTINFO control message, aligned for its header.
#[repr(C, align(8))]
struct Control([u8; 64]);

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
            local,
            arrivals: AtomicBool::new(false),
        };
        socket.queue_errors();
        // Only a wildcard-bound socket can receive a group's datagrams without having
        // joined it itself.
        if local.ip().is_unspecified() {
            socket.only_own_groups();
        }
        Ok(socket)
    }

    /// From now on, reads each datagram's destination (whether it was sent to a group) and
    /// the interface it arrived on (whether it came from this machine). A server's sockets
    /// need both; a socket joining a group reads them from its join.
    pub fn read_arrivals(&self) -> io::Result<()> {
        use nix::sys::socket::{setsockopt, sockopt};
        if self.arrivals.load(Ordering::Acquire) {
            return Ok(());
        }
        match self.local {
            SocketAddr::V4(_) => setsockopt(&self.io, sockopt::Ipv4PacketInfo, &true),
            SocketAddr::V6(_) => setsockopt(&self.io, sockopt::Ipv6RecvPacketInfo, &true),
        }
        .map_err(io::Error::from)?;
        self.arrivals.store(true, Ordering::Release);
        Ok(())
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

    /// Makes the socket receive only the groups it joins itself, where that can be asked
    /// for (elsewhere its destinations still tell a group's datagrams apart).
    #[cfg(target_os = "linux")]
    fn only_own_groups(&self) {
        let raw = SockRef::from(&self.io);
        let set = match self.local {
            SocketAddr::V4(_) => raw.set_multicast_all_v4(false),
            SocketAddr::V6(_) => raw.set_multicast_all_v6(false),
        };
        if let Err(e) = set {
            tracing::debug!(error = %e, "the socket also receives other sockets' groups");
        }
    }

    #[cfg(not(target_os = "linux"))]
    fn only_own_groups(&self) {}

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
        socket.read_arrivals()?;
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

    /// Waits until a datagram can be read or `timeout` has passed (then `false`), with
    /// the precision of the kernel's high-resolution timers (`ppoll`). A receive's read
    /// timeout is counted in the kernel's ticks instead: a 1 ms timeout ends 4-12 ms
    /// later on a kernel built with HZ=250, measured on our 2-core machine.
    #[cfg(target_os = "linux")]
    pub fn wait_readable(&self, timeout: Duration) -> io::Result<bool> {
        use std::os::fd::AsFd as _;

        use nix::poll::{PollFd, PollFlags, ppoll};
        use nix::sys::time::TimeSpec;

        let mut fds = [PollFd::new(self.io.as_fd(), PollFlags::POLLIN)];
        match ppoll(&mut fds, Some(TimeSpec::from_duration(timeout)), None) {
            Ok(n) => Ok(n > 0),
            Err(nix::errno::Errno::EINTR) => Ok(false),
            Err(e) => Err(e.into()),
        }
    }

    /// Without `ppoll`: reports a datagram as readable (the receive then waits for it
    /// up to its read timeout).
    #[cfg(not(target_os = "linux"))]
    pub fn wait_readable(&self, _timeout: Duration) -> io::Result<bool> {
        Ok(true)
    }

    /// Waits for a datagram (up to the read timeout: then an error of kind `WouldBlock`)
    /// and writes it into `buf`. A datagram longer than `buf` is cut to its length.
    pub fn recv(&self, buf: &mut [u8]) -> io::Result<Received> {
        use std::os::fd::AsRawFd as _;

        use nix::sys::socket::{ControlMessageOwned, MsgFlags, SockaddrStorage, recvmsg};

        if !self.arrivals.load(Ordering::Acquire) {
            let (len, peer) = self.io.recv_from(buf)?;
            return Ok(Received {
                peer,
                len,
                multicast: self.local.ip().is_multicast(),
                loopback: None,
            });
        }
        let mut control = Control([0; 64]);
        let mut iov = [IoSliceMut::new(buf)];
        let msg = recvmsg::<SockaddrStorage>(
            self.io.as_raw_fd(),
            &mut iov,
            Some(&mut control.0),
            MsgFlags::empty(),
        )
        .map_err(io::Error::from)?;
        let peer = msg
            .address
            .and_then(|a| {
                a.as_sockaddr_in()
                    .map(|v4| SocketAddr::V4((*v4).into()))
                    .or_else(|| a.as_sockaddr_in6().map(|v6| SocketAddr::V6((*v6).into())))
            })
            .ok_or_else(|| io::Error::other("a datagram without a sender's IP address"))?;
        let mut received = Received {
            peer,
            len: msg.bytes,
            multicast: self.local.ip().is_multicast(),
            loopback: Some(false),
        };
        for c in msg.cmsgs().into_iter().flatten() {
            let (destination, interface) = match c {
                ControlMessageOwned::Ipv4PacketInfo(i) => (
                    IpAddr::from(Ipv4Addr::from(u32::from_be(i.ipi_addr.s_addr))),
                    u32::try_from(i.ipi_ifindex).ok(),
                ),
                ControlMessageOwned::Ipv6PacketInfo(i) => (
                    IpAddr::from(Ipv6Addr::from(i.ipi6_addr.s6_addr)),
                    Some(i.ipi6_ifindex),
                ),
                _ => continue,
            };
            received.multicast |= is_multicast(destination);
            received.loopback = Some(interface.is_some_and(|i| loopback_interfaces().contains(&i)));
        }
        Ok(received)
    }

    /// Joins a multicast group; `interface` is an IPv6 interface index (0: the default) and
    /// is ignored for IPv4, which joins on the interface the routing table picks. The
    /// socket reads arrivals from then on ([`Socket::read_arrivals`]).
    pub fn join(&self, group: IpAddr, interface: u32) -> io::Result<()> {
        self.read_arrivals()?;
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
