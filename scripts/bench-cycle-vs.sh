#!/usr/bin/env bash
# The edge measure cycle of two coapcam builds side by side, in one run: each binary
# serves the two-camera demo scene (scenes/demo.toml) on its own free loopback port, both
# are prepared as `demo` prepares (floor not sent, spatial filter on), and then RUNS times
# (default 15) each binary's `measure --server ... --edge --json` runs as a new process,
# alternating OLD NEW, NEW OLD, ... so that both see the same load. Prints, per binary,
# the median, 95th percentile and largest wall time of the whole command (process start
# to exit) and of the server's `measure_ms` (grab, merge, measure, pictures), the ratio
# NEW / OLD of each, the median of the run-by-run ratios, and the load average before and
# after (a shared machine moves both builds alike, but not evenly within one run).
#   scripts/bench-cycle-vs.sh OLD_BIN NEW_BIN [RUNS]
# e.g. a build of the issue's baseline against this checkout's release build:
#   git worktree add /tmp/base 9f3ffaa --detach && (cd /tmp/base && cargo build --release -p coapcam)
#   cargo build --release -p coapcam
#   scripts/bench-cycle-vs.sh /tmp/base/target/release/coapcam target/release/coapcam 15
set -euo pipefail
cd "$(dirname "$0")/.."
if [ $# -lt 2 ] || [ $# -gt 3 ]; then
    sed -n '2,16p' "$0" | sed 's/^# \{0,1\}//' >&2
    exit 2
fi
old="$(realpath "$1")"
new="$(realpath "$2")"
runs="${3:-15}"
for bin in "$old" "$new"; do
    [ -x "$bin" ] || { echo "bench-cycle-vs: $bin is not an executable" >&2; exit 2; }
done
work="$(mktemp -d)"
trap 'kill $(jobs -p) 2>/dev/null || true; rm -rf "$work"' EXIT

free_port() { python3 -c 'import socket; s=socket.socket(socket.AF_INET, socket.SOCK_DGRAM); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'; }

# serve NAME BIN PORT: starts BIN's server of the demo scene on PORT.
serve() {
    "$2" serve --scene scenes/demo.toml --bind "127.0.0.1:$3" \
        --state-dir "$work/$1-state" --duration 3600 >"$work/$1-serve.out" 2>"$work/$1-serve.log" &
}
old_port="$(free_port)"
new_port="$(free_port)"
serve old "$old" "$old_port"
serve new "$new" "$new_port"
old_uri="coap://127.0.0.1:$old_port"
new_uri="coap://127.0.0.1:$new_port"
# prepare BIN URI: waits for the server, prepares its cameras, and runs one cycle that is
# not counted (the first after a start pays for what is set up once).
prepare() {
    for _ in $(seq 50); do
        "$1" get "$2/.well-known/core" >/dev/null 2>&1 && break
        sleep 0.1
    done
    "$1" measure --server "$2" --prepare --clouds >/dev/null 2>>"$work/prepare.log"
    "$1" measure --server "$2" --edge --json >/dev/null
}
prepare "$old" "$old_uri"
prepare "$new" "$new_uri"

# once NAME BIN URI: one timed cycle, appended to NAME.jsonl with its wall time.
once() {
    local name="$1" bin="$2" uri="$3" start end doc
    start=$(date +%s%N)
    doc="$("$bin" measure --server "$uri" --edge --json)"
    end=$(date +%s%N)
    echo "${doc%\}},\"process_ms\":$(((end - start) / 1000000))}" >>"$work/$name.jsonl"
}
load_before="$(cut -d' ' -f1-3 /proc/loadavg)"
for i in $(seq "$runs"); do
    if [ $((i % 2)) -eq 1 ]; then
        once old "$old" "$old_uri"
        once new "$new" "$new_uri"
    else
        once new "$new" "$new_uri"
        once old "$old" "$old_uri"
    fi
done
load_after="$(cut -d' ' -f1-3 /proc/loadavg)"

python3 - "$work/old.jsonl" "$work/new.jsonl" "$old" "$new" "$load_before" "$load_after" <<'PY'
import json, math, statistics, sys
old_path, new_path, old_bin, new_bin, load_before, load_after = sys.argv[1:]
docs = {k: [json.loads(l) for l in open(p)] for k, p in (("old", old_path), ("new", new_path))}

def p95(v):
    s = sorted(v)
    return s[math.ceil(0.95 * len(s)) - 1]

def stats(v):
    return statistics.median(v), p95(v), max(v)

def dims(ds):
    seen = {(round(d["length_mm"]), round(d["width_mm"]), round(d["height_mm"]))
            for d in ds if d.get("parcel") == "measured"}
    other = sum(d.get("parcel") != "measured" for d in ds)
    text = ", ".join("x".join(map(str, t)) for t in sorted(seen))
    return text + (f"; {other} not measured" if other else "")

print(f"old: {old_bin}\nnew: {new_bin}")
print(f"{len(docs['old'])} cycles each, alternating; load average {load_before} before, {load_after} after\n")
print("| build | whole command ms: median / p95 / max | measure_ms: median / p95 / max | mm |")
print("|---|---:|---:|---|")
for k in ("old", "new"):
    w = stats([d["process_ms"] for d in docs[k]])
    m = stats([d["measure_ms"] for d in docs[k]])
    print(f"| {k} | {w[0]:.1f} / {w[1]:.1f} / {w[2]:.1f} | {m[0]:.1f} / {m[1]:.1f} / {m[2]:.1f} | {dims(docs[k])} |")
print("\n| new / old | median | p95 | max | median of the run-by-run ratios |")
print("|---|---:|---:|---:|---:|")
for field, name in (("process_ms", "whole command"), ("measure_ms", "measure_ms")):
    a = stats([d[field] for d in docs["old"]])
    b = stats([d[field] for d in docs["new"]])
    paired = statistics.median(n[field] / o[field] for o, n in zip(docs["old"], docs["new"]))
    print(f"| {name} | {b[0] / a[0]:.2f} | {b[1] / a[1]:.2f} | {b[2] / a[2]:.2f} | {paired:.2f} |")
PY
