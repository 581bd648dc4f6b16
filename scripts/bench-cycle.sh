#!/usr/bin/env bash
# The measurement cycle of the two-camera demo scene, end to end: `coapcam measure --json`
# run as a new process RUNS times (default 10) per case, on loopback and through
# `coapcam netem` (10 ms each way, 2 % loss each way), the clouds measured by the client
# (window and RFC 7959 stop-and-wait transfers) or on the server (--edge). Prints the
# median, smallest and largest `cycle_ms` (request to result, inside the process) and the
# median wall time of the whole process, per case.
#   scripts/bench-cycle.sh [RUNS]
set -euo pipefail
cd "$(dirname "$0")/.."
runs="${1:-10}"
cargo build --release --quiet
bin="${CARGO_TARGET_DIR:-target}/release/coapcam"
work="$(mktemp -d)"
trap 'kill $(jobs -p) 2>/dev/null || true; rm -rf "$work"' EXIT

free_port() { python3 -c 'import socket; s=socket.socket(socket.AF_INET, socket.SOCK_DGRAM); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'; }
server_port="$(free_port)"
link_port="$(free_port)"
"$bin" serve --scene scenes/demo.toml --bind "127.0.0.1:$server_port" \
    --state-dir "$work/state" --duration 3600 2>"$work/serve.log" &
"$bin" netem --listen "127.0.0.1:$link_port" --forward "127.0.0.1:$server_port" \
    --delay-ms 10 --loss 0.02 --seed 7 >"$work/netem.out" 2>"$work/netem.log" &
loopback="coap://127.0.0.1:$server_port"
link="coap://127.0.0.1:$link_port"
for _ in $(seq 50); do
    "$bin" get "$loopback/.well-known/core" >/dev/null 2>&1 && break
    sleep 0.1
done
# As demo does: the floor is not sent, the spatial filter runs.
"$bin" measure --server "$loopback" --prepare --clouds >/dev/null

run_case() {
    local name="$1"
    shift
    : >"$work/case.jsonl"
    for _ in $(seq "$runs"); do
        local start end
        start=$(date +%s%N)
        "$bin" measure "$@" --json >>"$work/case.jsonl"
        end=$(date +%s%N)
        sed -i "\$s/}\$/,\"process_ms\":$(((end - start) / 1000000))}/" "$work/case.jsonl"
    done
    python3 - "$name" "$work/case.jsonl" <<'PY'
import json, statistics, sys
name, path = sys.argv[1], sys.argv[2]
docs = [json.loads(line) for line in open(path)]
cycle = [d["cycle_ms"] for d in docs]
process = [d["process_ms"] for d in docs]
size = statistics.median(d["received_bytes"] for d in docs)
dims = {(round(d["length_mm"]), round(d["width_mm"]), round(d["height_mm"]))
        for d in docs if d["parcel"] == "measured"}
nothing = sum(d["parcel"] != "measured" for d in docs)
print(f"| {name} | {len(docs)} | {statistics.median(cycle):.0f} | {min(cycle):.0f}-{max(cycle):.0f} "
      f"| {statistics.median(process):.0f} | {size:,.0f} | {', '.join('x'.join(map(str, d)) for d in sorted(dims))}"
      + (f", nothing measured in {nothing}" if nothing else "") + " |")
PY
}

echo "| case | runs | cycle_ms median | cycle_ms range | process ms median | bytes received | mm (rounded) |"
echo "|---|---:|---:|---:|---:|---:|---|"
run_case "loopback, clouds" --server "$loopback" --clouds
run_case "loopback, edge" --server "$loopback" --edge
run_case "20 ms + 2 %, clouds (window)" --server "$link" --clouds
run_case "20 ms + 2 %, clouds (stop-and-wait)" --server "$link" --clouds --transfer stop-and-wait
run_case "20 ms + 2 %, edge" --server "$link" --edge
