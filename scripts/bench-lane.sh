#!/usr/bin/env bash
# scripts/bench-lane.sh [RUNS] [STILL_MS]: how long after a parcel stands still its MQTT
# message arrives. Plays scenes/lane.toml (parcels still at 3 s and 12 s) with
# `serve --auto-measure --mqtt` against a mosquitto on 127.0.0.1:18830 and prints, per
# parcel, the message's arrival minus the moment it stood still, in seconds. The clock
# starts before the server process does, so each figure is an upper bound.
set -euo pipefail
cd "$(dirname "$0")/.."
RUNS=${1:-4}; STILL_MS=${2:-600}
cargo build --release -q
BIN=${CARGO_TARGET_DIR:-target}/release/coapcam
w=$(mktemp -d)
mosquitto -p 18830 > "$w/broker.log" 2>&1 & broker=$!
trap 'kill $broker 2>/dev/null; rm -rf "$w"' EXIT
sleep 0.5
for r in $(seq "$RUNS"); do
  mosquitto_sub -h 127.0.0.1 -p 18830 -t 'coapcam/+/measurements' -F '%U' > "$w/msgs.$r" &
  sub=$!
  sleep 0.3
  t0=$(date +%s.%N)
  "$BIN" serve --scene scenes/lane.toml --auto-measure --still-ms "$STILL_MS" \
    --mqtt mqtt://127.0.0.1:18830 --bind 127.0.0.1:0 --state-dir "$w/state.$r" \
    --station-name "bench$r" --duration 19 > "$w/serve.$r" 2>&1
  kill "$sub"
  python3 - "$t0" "$w/msgs.$r" <<'PY'
import sys
t0 = float(sys.argv[1])
arrivals = [float(l) for l in open(sys.argv[2]) if l.strip()]
for t, still in zip(arrivals, [3.0, 12.0]):
    print(f"{t - t0 - still:.3f}")
PY
done
