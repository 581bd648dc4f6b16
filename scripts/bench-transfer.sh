#!/usr/bin/env bash
# Block-wise GET benchmark, coapcam against libcoap 4.3.1 in the same run (issue 7).
#
#   scripts/bench-transfer.sh [RUNS]      (default 8 runs per size and pair)
#
# For 921,610, 2,764,810 and 10,032,012 bytes with 1024-byte blocks, it times
#   - coapcam's client against coapcam's server (`serve --no-cameras --static`),
#   - libcoap's coap-client-notls against coap-server-notls -d 10 (the file PUT first),
#   - the round-trip floor: a minimal UDP ping-pong of 1,044-byte datagrams, one per block
#     (blocking receive), timed around its loop,
#   - the same ping-pong on a current-thread tokio runtime ("tokio floor": what waiting
#     for datagrams through tokio's poller costs, before any CoAP work),
# coapcam and libcoap as whole-process wall time, unpinned and with both processes pinned
# to CPU 0.
# Every transfer is compared with the original (cmp); a mismatch aborts the run.
# It prints medians, the ratios, and each server's peak RSS (VmHWM) and private memory
# (RssAnon: heap and stacks, without the mapped pages of the binary and its libraries).
set -euo pipefail
cd "$(dirname "$0")/.."
RUNS=${1:-8}
command -v coap-client-notls >/dev/null || { echo "needs libcoap3-bin (apt-get install libcoap3-bin)" >&2; exit 1; }
command -v taskset >/dev/null || { echo "needs taskset (util-linux)" >&2; exit 1; }

cargo build --release -q -p coapcam
cargo build --release -q -p coap-net --example udp_pingpong
TARGET=${CARGO_TARGET_DIR:-target}
BIN=$TARGET/release/coapcam
PINGPONG=$TARGET/release/examples/udp_pingpong

work=$(mktemp -d)
pids=()
cleanup() { for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done; rm -rf "$work"; }
trap cleanup EXIT
mkdir -p "$work/files"
SIZES=(921610 2764810 10032012)
for s in "${SIZES[@]}"; do head -c "$s" /dev/urandom > "$work/files/body-$s.bin"; done

free_port() { python3 -c 'import socket; s=socket.socket(socket.AF_INET, socket.SOCK_DGRAM); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])'; }
now_ns() { date +%s%N; }
median() { sort -g | awk '{a[NR]=$1} END {if (NR%2) print a[(NR+1)/2]; else printf "%.6f\n", (a[NR/2]+a[NR/2+1])/2}'; }
peak_rss_kb() { awk '/VmHWM/ {print $2}' "/proc/$1/status"; }
# Private memory (heap, stacks: RssAnon), without the mapped pages of binary and libraries.
anon_kb() { awk '/RssAnon/ {print $2}' "/proc/$1/status"; }

# run_mode LABEL PREFIX...: PREFIX is empty (unpinned) or "taskset -c 0".
run_mode() {
  local label=$1; shift
  local pin=("$@")
  local ours_port lc_port pp_port
  ours_port=$(free_port); lc_port=$(free_port); pp_port=$(free_port)
  "${pin[@]}" "$BIN" serve --no-cameras --static "$work/files" --bind "127.0.0.1:$ours_port" 2>/dev/null &
  local ours_pid=$!; pids+=("$ours_pid")
  "${pin[@]}" coap-server-notls -A 127.0.0.1 -p "$lc_port" -d 10 &
  local lc_pid=$!; pids+=("$lc_pid")
  sleep 0.5
  for s in "${SIZES[@]}"; do
    coap-client-notls -m put -b 1024 -f "$work/files/body-$s.bin" "coap://127.0.0.1:$lc_port/body-$s" >/dev/null
  done
  for s in "${SIZES[@]}"; do
    local blocks=$(( (s + 1023) / 1024 ))
    local ours=() lc=() floor=() tfloor=()
    for _ in $(seq "$RUNS"); do
      rm -f "$work/out"
      local t0; t0=$(now_ns)
      "${pin[@]}" "$BIN" get "coap://127.0.0.1:$ours_port/files/body-$s.bin" --block-size 1024 -o "$work/out"
      ours+=("$(( $(now_ns) - t0 ))")
      cmp -s "$work/out" "$work/files/body-$s.bin" || { echo "coapcam: body differs ($s bytes)" >&2; exit 1; }
      rm -f "$work/out"
      t0=$(now_ns)
      "${pin[@]}" coap-client-notls -b 1024 -B 60 "coap://127.0.0.1:$lc_port/body-$s" -o "$work/out"
      lc+=("$(( $(now_ns) - t0 ))")
      cmp -s "$work/out" "$work/files/body-$s.bin" || { echo "libcoap: body differs ($s bytes)" >&2; exit 1; }
      "${pin[@]}" "$PINGPONG" server "127.0.0.1:$pp_port" & local pp=$!
      sleep 0.05
      floor+=("$("${pin[@]}" "$PINGPONG" client "127.0.0.1:$pp_port" "$blocks" 1044)")
      wait "$pp"
      "${pin[@]}" "$PINGPONG" server-tokio "127.0.0.1:$pp_port" & pp=$!
      sleep 0.05
      tfloor+=("$("${pin[@]}" "$PINGPONG" client-tokio "127.0.0.1:$pp_port" "$blocks" 1044)")
      wait "$pp"
    done
    local m_ours m_lc m_floor m_tfloor
    m_ours=$(printf '%s\n' "${ours[@]}" | awk '{print $1/1e9}' | median)
    m_lc=$(printf '%s\n' "${lc[@]}" | awk '{print $1/1e9}' | median)
    m_floor=$(printf '%s\n' "${floor[@]}" | median)
    m_tfloor=$(printf '%s\n' "${tfloor[@]}" | median)
    awk -v l="$label" -v s="$s" -v o="$m_ours" -v c="$m_lc" -v f="$m_floor" -v t="$m_tfloor" \
      'BEGIN {printf "| %-9s | %10d | %8.3f | %8.3f | %8.3f | %8.3f | %6.2f | %6.2f | %6.2f |\n", l, s, o, c, f, t, o/c, o/f, o/t}'
  done
  echo "| $label peak RSS: coapcam server $(peak_rss_kb "$ours_pid") kB, libcoap server $(peak_rss_kb "$lc_pid") kB; private (RssAnon): coapcam $(anon_kb "$ours_pid") kB, libcoap $(anon_kb "$lc_pid") kB |"
  kill "$ours_pid" "$lc_pid" 2>/dev/null || true
  wait "$ours_pid" "$lc_pid" 2>/dev/null || true
}

echo "RFC 7959 GET, 1024-byte blocks, median of $RUNS runs (seconds, whole-process wall time)"
echo
echo "| mode      |      bytes |  coapcam |  libcoap |    floor | tokio floor | ours/libcoap | ours/floor | ours/tokio floor |"
echo "|-----------|-----------:|---------:|---------:|---------:|---------:|-------:|-------:|-------:|"
run_mode unpinned
run_mode "pinned"  taskset -c 0
