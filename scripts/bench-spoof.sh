#!/usr/bin/env bash
# bench-spoof.sh [COAPCAM] [SECONDS] [GETS]: what a flood of GETs from unverified sources
# costs the server (issue 32, item 3). Run it inside scripts/netns-run (root), which gives
# the addresses fd00::2-9 on a veth:
#   sudo scripts/netns-run scripts/bench-spoof.sh target/release/coapcam
# A server on [::]:5683 (one synthetic camera) grabs a color frame and a point cloud
# once; then
#   - its CPU time over SECONDS (default 10) quiet, then over SECONDS of a flood: 1,000
#     GETs a second of the point cloud (an answer made anew each time), sent from
#     fd00::3-9 and never answered (as forged sources would be);
#   - GETS (default 15) GETs of the color frame (2,764,810 B) over [::1] before any
#     flood, then GETS pairs, one with the flood paused and one in it, alternating (so
#     that the machine's other load weighs on both alike); each timed by the client's
#     wall clock.
# With GROUP=1 the flood goes to the group ff02::fd on the veth (NON, as group requests
# are), which the server joins. Prints the server's CPU share and the GETs' median, p95
# and max for both.
set -euo pipefail
bin=${1:-target/release/coapcam}
secs=${2:-10}
gets=${3:-15}
[ "${COAPCAM_NETNS:-}" = 1 ] || { echo "run inside scripts/netns-run" >&2; exit 2; }
dir=$(mktemp -d)
group=()
[ "${GROUP:-0}" = 1 ] && group=(--group ff02::fd --group-interface "$COAPCAM_MC6_IF")
"$bin" serve --bind '[::]:5683' --state-dir "$dir/state" --results "$dir/results.sqlite" \
  "${group[@]}" >"$dir/serve.log" 2>&1 &
pid=$!
trap 'kill $pid 2>/dev/null || true; rm -rf "$dir"' EXIT
for _ in $(seq 100); do
  "$bin" get 'coap://[::1]/cams' -o "$dir/cams" 2>/dev/null && break
  sleep 0.1
done
sn=$(grep -oE '[0-9]{12}' "$dir/cams" | head -1)
[ -n "$sn" ] || { echo "no camera in /cams: $(cat "$dir/cams")" >&2; exit 1; }
"$bin" post "coap://[::1]/cams/$sn/pointcloud" -o "$dir/grab.bin"
"$bin" post "coap://[::1]/cams/$sn/color" -o "$dir/grab.bin"
python3 - "$bin" "$pid" "$sn" "$secs" "$gets" <<'EOF'
import os, socket, statistics, struct, subprocess, sys, threading, time

bin, pid, sn, secs, gets = sys.argv[1], int(sys.argv[2]), sys.argv[3], float(sys.argv[4]), int(sys.argv[5])
tick = os.sysconf("SC_CLK_TCK")
uri = f"coap://[::1]/cams/{sn}/color"

def cpu():
    fields = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / tick  # utime + stime

group = os.environ.get("GROUP", "0") == "1"
ifindex = int(os.environ.get("COAPCAM_MC6_IF", "0"))
target = ("ff02::fd", 5683, 0, ifindex) if group else ("fd00::2", 5683)

def coap_get(mid, path):
    # GET (NON to a group, else CON), 2-byte token, Uri-Path options.
    out = bytearray([0x52 if group else 0x42, 0x01]) + struct.pack(">H", mid) + struct.pack(">H", mid)
    prev = 0
    for seg in path:
        s = seg.encode()
        delta = 11 - prev
        prev = 11
        assert len(s) < 13
        out += bytes([(delta << 4) | len(s)]) + s
    return bytes(out)

def flood(stop, on, sent):
    socks = []
    for n in range(3, 10):
        s = socket.socket(socket.AF_INET6, socket.SOCK_DGRAM)
        s.bind((f"fd00::{n}", 0))
        if group:
            s.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_MULTICAST_IF, ifindex)
        s.setblocking(False)
        socks.append(s)
    i = 0
    while not stop.is_set():
        if not on.wait(0.1):
            continue
        # 1,000 a second, sent 10 every 10 ms.
        start, first = time.monotonic(), i
        while on.is_set() and not stop.is_set():
            delay = start + (i - first) / 1000.0 - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            for _ in range(10):
                msg = coap_get(i & 0xFFFF, ["cams", sn, "pointcloud"])
                try:
                    socks[i % len(socks)].sendto(msg, target)
                except BlockingIOError:
                    pass
                i += 1
            sent[0] = i

def cpu_share():
    c0, t0 = cpu(), time.monotonic()
    time.sleep(secs)
    return (cpu() - c0) / (time.monotonic() - t0)

def get():
    t = time.monotonic()
    r = subprocess.run([bin, "get", uri, "-o", "/dev/stdout"], capture_output=True, timeout=120)
    took = time.monotonic() - t
    if r.returncode != 0:
        print(f"GET failed: {r.stderr.decode()[:300]}", file=sys.stderr)
        return took, 0
    return took, len(r.stdout)

def summary(times):
    times = sorted(times)
    p95 = times[min(len(times) - 1, round(0.95 * (len(times) - 1)))]
    return f"median {statistics.median(times):.3f} s, p95 {p95:.3f} s, max {times[-1]:.3f} s"

stop, on, sent = threading.Event(), threading.Event(), [0]
t = threading.Thread(target=flood, args=(stop, on, sent))
t.start()
quiet_cpu = cpu_share()
baseline = [get()[0] for _ in range(gets)]
on.set()
time.sleep(1)
flood_cpu = cpu_share()
# The GETs alternate, quiet then in the flood, so that the machine's other load weighs
# on both alike.
times = {False: [], True: []}
sizes = set()
for _ in range(gets):
    for flooding in (False, True):
        (on.set if flooding else on.clear)()
        time.sleep(0.5)
        took, size = get()
        times[flooding].append(took)
        sizes.add(size)
stop.set()
t.join()
print(f"server CPU: quiet {100 * quiet_cpu:.1f} %, flood {100 * flood_cpu:.1f} % of a core "
      f"({sent[0]:,} spoofed GETs in all)")
print(f"GET of {sorted(sizes)} B x{gets}: before any flood {summary(baseline)}; "
      f"between floods {summary(times[False])}; in the flood {summary(times[True])}")
EOF
