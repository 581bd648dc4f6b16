#!/usr/bin/env bash
# What one HEAD through the HTTP-CoAP proxy moves (docs/threat-model.md): BIN serves a
# 16 MB file of `--static` on 127.0.0.1 with `--http`, and the bytes and packets the
# loopback interface carries while `curl -I` asks the proxy for that file are counted
# (lo's tx counters; every packet on lo is counted once). Runs in a private network
# namespace of its own, so that nothing else moves on its lo:
#   scripts/netns-run scripts/bench-proxy-head.sh [BIN]     (BIN: target/debug/coapcam)
set -euo pipefail
cd "$(dirname "$0")/.."
[ "${COAPCAM_NETNS:-}" = 1 ] || { echo "run it under scripts/netns-run" >&2; exit 2; }
bin=${1:-target/debug/coapcam}
dir=$(mktemp -d)
trap 'kill "$pid" 2>/dev/null || true; rm -rf "$dir"' EXIT
mkdir "$dir/files"
head -c 16000000 /dev/urandom >"$dir/files/big.bin"
"$bin" serve --bind 127.0.0.1:5791 --state-dir "$dir/state" --static "$dir/files" \
    --http 127.0.0.1:8791 2>"$dir/serve.log" &
pid=$!
for _ in $(seq 100); do curl -s -o /dev/null http://127.0.0.1:8791/api/station && break; sleep 0.1; done
stat() { cat "/sys/class/net/lo/statistics/tx_$1"; }
bytes=$(stat bytes) packets=$(stat packets)
curl -s -I -o /dev/null -w 'HEAD: %{http_code}, request %{size_request} B, %{time_total} s\n' \
    http://127.0.0.1:8791/hc/coap://127.0.0.1:5791/files/big.bin
sleep 1
echo "lo: $(($(stat bytes) - bytes)) bytes in $(($(stat packets) - packets)) packets"
