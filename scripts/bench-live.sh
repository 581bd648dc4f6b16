#!/bin/sh
# Live streams on loopback (docs/benchmarks.md, "Live streams"): `coapcam monitor --live`
# against `coapcam serve` (the synthetic D415, 1280x720 at 30 frames a second), color as
# JPEG and depth as RVL+zstd, one client and four at once (one feed shared), each run
# SECONDS long: the frames per second and the capture-to-client latency (p50, p95) each
# client saw, and the server's CPU time over the run from /proc/PID/stat (user + system),
# in all and per stream.
#
# Usage: scripts/bench-live.sh [BIN] [SECONDS]
#   BIN      the coapcam binary (default target/debug/coapcam)
#   SECONDS  how long each run lasts (default 10)
set -eu
BIN=${1:-target/debug/coapcam}
SECS=${2:-10}
state=$(mktemp -d)
pid=""
trap 'kill $pid 2>/dev/null || true; rm -rf "$state"' EXIT
# A server of its own for each run: a client stopped by a signal sends no Reset, so its
# stream lasts until a confirmable notification goes unacknowledged, and would be
# counted in the next run's CPU time.
start() {
    rm -rf "$state/s" && mkdir "$state/s"
    "$BIN" serve --bind 127.0.0.1:0 --state-dir "$state/s" --duration 600 2>"$state/err" &
    pid=$!
    addr=""
    for _ in $(seq 200); do
        addr=$(sed -n 's/^coapcam: serving on \([0-9.:]*\).*/\1/p' "$state/err" | head -n 1)
        [ -n "$addr" ] && return
        sleep 0.1
    done
    echo "the server printed no address" >&2
    exit 1
}
ticks=$(getconf CLK_TCK)
cpu() { awk '{print $14 + $15}' "/proc/$pid/stat"; }
echo "load average before: $(cut -d' ' -f1-3 /proc/loadavg)"
printf '%-6s %7s  %s\n' stream clients "per client: fps, latency p50/p95 ms; server CPU"
for stream in color depth; do
    for clients in 1 4; do
        start
        c0=$(cpu)
        t0=$(date +%s.%N)
        monitors=""
        for i in $(seq "$clients"); do
            timeout -s INT "$SECS" "$BIN" monitor "$stream" --live --json \
                --server "coap://$addr" >"$state/m$i" 2>/dev/null &
            monitors="$monitors $!"
        done
        for m in $monitors; do wait "$m" || true; done
        c1=$(cpu)
        t1=$(date +%s.%N)
        kill "$pid"
        wait "$pid" || true
        line=""
        for i in $(seq "$clients"); do
            line="$line $(tail -n 1 "$state/m$i" | python3 -c '
import json, sys
live = json.loads(sys.stdin.read())["live"]
print("%.1f fps %.1f/%.1f;" % (live.get("fps", 0), live.get("latency_p50_ms", 0), live.get("latency_p95_ms", 0)))')"
        done
        python3 - "$stream" "$clients" "$c0" "$c1" "$t0" "$t1" "$ticks" "$line" <<'EOF'
import sys
stream, n, c0, c1, t0, t1, ticks, line = sys.argv[1:]
secs = float(t1) - float(t0)
cpu = (float(c1) - float(c0)) / float(ticks) / secs * 100
print("%-6s %7s %s server %.0f %% of a core, %.0f %% per stream" % (stream, n, line, cpu, cpu / int(n)))
EOF
    done
done
echo "load average after: $(cut -d' ' -f1-3 /proc/loadavg)"
