#!/usr/bin/env bash
# 200 concurrent clients against one release `coapcam serve` for 60 s (`coapcam bench
# load`: discovery, uploads, grabs, observers), then the server's peak resident memory.
# Extra arguments go to `serve` (e.g. --grab-memory 64).
#   scripts/bench-load.sh [SERVE-FLAG...]
set -euo pipefail
cd "$(dirname "$0")/.."
cargo build --release --quiet
bin="${CARGO_TARGET_DIR:-target}/release/coapcam"
work="$(mktemp -d)"
trap 'kill $(jobs -p) 2>/dev/null || true; rm -rf "$work"' EXIT
mkdir "$work/files"
port="$(python3 -c 'import socket; s=socket.socket(socket.AF_INET, socket.SOCK_DGRAM); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')"
"$bin" serve --bind "127.0.0.1:$port" --static "$work/files" --writable \
    --state-dir "$work/state" --duration 3600 "$@" 2>"$work/serve.log" &
server=$!
for _ in $(seq 50); do
    "$bin" get "coap://127.0.0.1:$port/.well-known/core" >/dev/null 2>&1 && break
    sleep 0.1
done
status=0
"$bin" bench load --server "coap://127.0.0.1:$port" --clients 200 --duration 60 || status=$?
echo "server peak RSS: $(awk '/VmHWM/ {printf "%d MiB", $2 / 1024}' "/proc/$server/status")"
exit "$status"
