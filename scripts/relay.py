#!/usr/bin/env python3
"""A second link emulator, independent of the `netem` crate: a UDP relay that delays
every datagram by exactly the configured one-way delay and loses it with a seeded
probability, per direction.

Written apart from coapcam on purpose: a benchmark that only ever meets its own
emulator tells us about the emulator. It shares nothing with `netem` (no tokio, no
millisecond timer wheel): it waits in select(2), whose timeout has microsecond
resolution, with the process's timer slack set to 1 microsecond (prctl
PR_SET_TIMERSLACK), and it sends each datagram when the monotonic clock has passed its
due time, in order of due time. There is no jitter and no rate limit, so the order of a
direction is kept.

Clients send to the listen address; each client address gets a socket of its own
towards the server, so the server's answers on that socket go back to that client.

    relay.py --forward 127.0.0.1:5683 --delay-ms 10 --loss 0.02 --seed 7

prints `listening HOST:PORT` on standard output once bound (port 0 picks a free one),
relays until SIGTERM or SIGINT (or --duration), then prints its counters as one JSON
object on standard error. With --log FILE every datagram is written there as
`time_us dir len fate` (dir: up = client to server, down = server to client; fate:
sent or lost; time since the relay started, when it arrived).

Loss: one generator per direction (Python's Mersenne Twister, seeded from --seed and
the direction's name), one draw per datagram in arrival order, so a replay with the
same seed and the same arrival order per direction loses the same datagrams.
"""

import argparse
import ctypes
import heapq
import json
import random
import select
import signal
import socket
import sys
import time

PR_SET_TIMERSLACK = 29
MAX_DATAGRAM = 65535
# Clients at once; a client beyond it is dropped (each costs a socket).
MAX_CLIENTS = 256
RECV_BUFFER = 4 << 20


def parse_addr(text):
    host, _, port = text.rpartition(":")
    if not host or not port.isdigit():
        raise argparse.ArgumentTypeError(f"{text!r}: expected HOST:PORT")
    return (host.strip("[]"), int(port))


def probability(text):
    p = float(text)
    if not 0.0 <= p <= 1.0:
        raise argparse.ArgumentTypeError(f"{text}: a probability is between 0 and 1")
    return p


def milliseconds(text):
    ms = float(text)
    if not 0.0 <= ms <= 3_600_000:
        raise argparse.ArgumentTypeError(f"{text}: 0 to 3,600,000 ms")
    return ms


def fine_timer_slack():
    """Asks the kernel to wake this process within 1 us of its timeouts (Linux)."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(PR_SET_TIMERSLACK, 1, 0, 0, 0)
    except (OSError, AttributeError):
        pass


def udp_socket(family, bind):
    s = socket.socket(family, socket.SOCK_DGRAM)
    try:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECV_BUFFER)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, RECV_BUFFER)
    except OSError:
        pass
    s.bind(bind)
    s.setblocking(False)
    return s


class Direction:
    def __init__(self, name, delay_s, loss, seed):
        self.name = name
        self.delay = delay_s
        self.loss = loss
        self.rng = random.Random(f"{seed}/{name}")
        self.datagrams = 0
        self.lost = 0
        self.bytes = 0

    def fate(self, length):
        """True when the datagram goes on; one draw per datagram whatever the loss."""
        self.datagrams += 1
        draw = self.rng.random()
        if draw < self.loss:
            self.lost += 1
            return False
        self.bytes += length
        return True

    def counters(self):
        return {
            "datagrams": self.datagrams,
            "lost": self.lost,
            "delivered_bytes": self.bytes,
            "delay_ms": self.delay * 1000.0,
            "loss": self.loss,
        }


def main():
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--listen", type=parse_addr, default=("127.0.0.1", 0),
                        help="address clients send to (default 127.0.0.1:0)")
    parser.add_argument("--forward", type=parse_addr, required=True,
                        help="the server's address")
    parser.add_argument("--delay-ms", type=milliseconds, default=0.0,
                        help="one-way delay each way, milliseconds (fractions allowed)")
    parser.add_argument("--loss", type=probability, default=0.0,
                        help="loss probability each way, 0 to 1")
    parser.add_argument("--loss-up", type=probability, help="client to server (overrides --loss)")
    parser.add_argument("--loss-down", type=probability, help="server to client (overrides --loss)")
    parser.add_argument("--seed", type=int, default=1, help="seed of the loss draws")
    parser.add_argument("--duration", type=float, help="stop after this many seconds")
    parser.add_argument("--log", help="write every datagram's arrival and fate to this file")
    args = parser.parse_args()

    fine_timer_slack()
    family = socket.AF_INET6 if ":" in args.listen[0] else socket.AF_INET
    fwd_family = socket.AF_INET6 if ":" in args.forward[0] else socket.AF_INET
    listen = udp_socket(family, args.listen)
    host, port = listen.getsockname()[:2]
    print(f"listening {'[' + host + ']' if ':' in host else host}:{port}", flush=True)

    delay = args.delay_ms / 1000.0
    up = Direction("up", delay, args.loss if args.loss_up is None else args.loss_up, args.seed)
    down = Direction("down", delay, args.loss if args.loss_down is None else args.loss_down,
                     args.seed)
    log = open(args.log, "w") if args.log else None

    upstream = {}  # client address -> socket towards the server
    client_of = {}  # upstream socket's fileno -> client address
    readers = [listen]
    queue = []  # (due, seq, socket, data, destination)
    seq = 0
    dropped_clients = 0

    class Stop(Exception):
        pass

    def on_signal(_signum, _frame):
        # Raised, not flagged: Python retries an interrupted select(2) by itself (PEP
        # 475), so a flag would only be seen at the next datagram.
        raise Stop()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    start = time.monotonic()
    end = start + args.duration if args.duration else None

    def take(direction, sock, data, dest, now):
        nonlocal seq
        ok = direction.fate(len(data))
        if log:
            fate = "sent" if ok else "lost"
            log.write(f"{int((now - start) * 1e6)} {direction.name} {len(data)} {fate}\n")
        if ok:
            seq += 1
            heapq.heappush(queue, (now + direction.delay, seq, sock, data, dest))

    try:
        while True:
            now = time.monotonic()
            while queue and queue[0][0] <= now:
                _, _, sock, data, dest = heapq.heappop(queue)
                try:
                    sock.sendto(data, dest)
                except OSError:
                    pass  # a full buffer or an unreachable peer: the datagram is gone
            if end is not None and now >= end:
                break
            timeout = None
            if queue:
                timeout = max(0.0, queue[0][0] - now)
            if end is not None:
                timeout = min(timeout if timeout is not None else end - now, max(0.0, end - now))
            try:
                ready, _, _ = select.select(readers, [], [], timeout)
            except InterruptedError:
                continue
            now = time.monotonic()
            for r in ready:
                # Several datagrams per wake-up, each stamped with the time it was read.
                for _ in range(64):
                    try:
                        data, peer = r.recvfrom(MAX_DATAGRAM)
                    except (BlockingIOError, InterruptedError):
                        break
                    except OSError:
                        break  # an ICMP error queued on an upstream socket
                    now = time.monotonic()
                    if r is listen:
                        s = upstream.get(peer)
                        if s is None:
                            if len(upstream) >= MAX_CLIENTS:
                                dropped_clients += 1
                                continue
                            bind = ("::", 0) if fwd_family == socket.AF_INET6 else ("0.0.0.0", 0)
                            if args.forward[0] in ("127.0.0.1", "::1"):
                                bind = (args.forward[0], 0)
                            s = udp_socket(fwd_family, bind)
                            upstream[peer] = s
                            client_of[s.fileno()] = peer
                            readers.append(s)
                        take(up, s, data, args.forward, now)
                    else:
                        take(down, listen, data, client_of[r.fileno()], now)
    except Stop:
        pass

    if log:
        log.close()
    counters = {
        "up": up.counters(),
        "down": down.counters(),
        "clients": len(upstream),
        "clients_dropped": dropped_clients,
        "seconds": time.monotonic() - start,
    }
    print(json.dumps(counters), file=sys.stderr, flush=True)


if __name__ == "__main__":
    main()
