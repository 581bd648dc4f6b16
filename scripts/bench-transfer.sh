#!/usr/bin/env bash
# Block-wise GET benchmark, RFC 7959 stop-and-wait, coapcam (--transfer stop-and-wait)
# against libcoap 4.3.1 in the same run, on loopback (`coapcam bench transfer` compares the
# transfer modes, libcoap and QUIC through emulated links).
#
#   scripts/bench-transfer.sh [RUNS]      (default 8 runs per size and pair)
#
# For 921,610, 2,764,810 and 10,032,012 bytes with 1024-byte blocks, it times
#   - coapcam's client against coapcam's server (`serve --no-cameras --static`),
#   - libcoap's coap-client-notls against coap-server-notls -d 10 (the file PUT first),
#   - the round-trip floor: a minimal blocking UDP ping-pong of 1,044-byte datagrams, one
#     round trip per block,
# all three as whole-process wall time (start to exit, as a user waits for a transfer),
# unpinned and with both processes pinned to CPU 0. The ping-pong client also reports the
# time of its loop alone ("floor loop": round trips without the process start, which
# weighs on the smallest transfer).
# Every size gets fresh servers holding only that body (as anchor-measurements.md did),
# so each peak RSS (VmHWM) is that of one transfer's server; private memory (RssAnon:
# heap and stacks, without the mapped pages of the binary and its libraries) beside it.
# Every transfer is compared with the original (cmp); a mismatch aborts the run.
# A second table gives the CPU time each transfer cost, client and server together (the
# clients' from bash's `time`, the servers' from their threads' schedstat): wall time on
# this kind of machine moves by a quarter from one run to the next, CPU time much less.
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
median() { sort -g | awk '{a[NR]=$1} END {if (NR%2) print a[(NR+1)/2]; else printf "%.6f\n", (a[NR/2]+a[NR/2+1])/2}'; }
peak_rss_kb() { awk '/VmHWM/ {print $2}' "/proc/$1/status"; }
# Private memory (heap, stacks: RssAnon), without the mapped pages of binary and libraries.
anon_kb() { awk '/RssAnon/ {print $2}' "/proc/$1/status"; }
# CPU milliseconds of a running process's threads so far (schedstat counts nanoseconds).
cpu_ms() { cat /proc/"$1"/task/*/schedstat | awk '{s += $1} END {printf "%.3f\n", s / 1e6}'; }
# `time`'s output: user and system seconds with millisecond digits.
TIMEFORMAT='%3U %3S'
# timed FILE CMD...: runs CMD, adding its CPU milliseconds (user + system) to FILE.
timed() {
  local file=$1; shift
  { time "$@" 2>&3; } 3>&2 2> "$work/time.$BASHPID"
  awk '{printf "%.3f\n", ($1 + $2) * 1000}' "$work/time.$BASHPID" >> "$file"
}

# run_mode LABEL PREFIX...: PREFIX is empty (unpinned) or "taskset -c 0".
run_mode() {
  local label=$1; shift
  local pin=("$@")
  for s in "${SIZES[@]}"; do
    local ours_port lc_port pp_port
    ours_port=$(free_port); lc_port=$(free_port); pp_port=$(free_port)
    mkdir -p "$work/only-$s"
    ln -f "$work/files/body-$s.bin" "$work/only-$s/"
    "${pin[@]}" "$BIN" serve --no-cameras --static "$work/only-$s" --bind "127.0.0.1:$ours_port" 2>/dev/null &
    local ours_pid=$!; pids+=("$ours_pid")
    "${pin[@]}" coap-server-notls -A 127.0.0.1 -p "$lc_port" -d 10 &
    local lc_pid=$!; pids+=("$lc_pid")
    sleep 0.5
    coap-client-notls -m put -b 1024 -f "$work/files/body-$s.bin" "coap://127.0.0.1:$lc_port/body-$s" >/dev/null
    local blocks=$(( (s + 1023) / 1024 ))
    local ours=() lc=() floor=() loop=() c0
    rm -f "$work"/cpu-*-*
    for _ in $(seq "$RUNS"); do
      rm -f "$work/out"
      # Microseconds from bash itself: timing a run forks nothing but the run.
      local t0=${EPOCHREALTIME/./}
      c0=$(cpu_ms "$ours_pid")
      timed "$work/cpu-ours-client" "${pin[@]}" "$BIN" get "coap://127.0.0.1:$ours_port/files/body-$s.bin" --block-size 1024 --transfer stop-and-wait -o "$work/out"
      ours+=("$(( ${EPOCHREALTIME/./} - t0 ))")
      awk -v a="$c0" -v b="$(cpu_ms "$ours_pid")" 'BEGIN {print b - a}' >> "$work/cpu-ours-server"
      cmp -s "$work/out" "$work/files/body-$s.bin" || { echo "coapcam: body differs ($s bytes)" >&2; exit 1; }
      rm -f "$work/out"
      t0=${EPOCHREALTIME/./}
      c0=$(cpu_ms "$lc_pid")
      timed "$work/cpu-lc-client" "${pin[@]}" coap-client-notls -b 1024 -B 60 "coap://127.0.0.1:$lc_port/body-$s" -o "$work/out"
      lc+=("$(( ${EPOCHREALTIME/./} - t0 ))")
      awk -v a="$c0" -v b="$(cpu_ms "$lc_pid")" 'BEGIN {print b - a}' >> "$work/cpu-lc-server"
      cmp -s "$work/out" "$work/files/body-$s.bin" || { echo "libcoap: body differs ($s bytes)" >&2; exit 1; }
      timed "$work/cpu-pp-server" "${pin[@]}" "$PINGPONG" server "127.0.0.1:$pp_port" & local pp=$!
      sleep 0.05
      t0=${EPOCHREALTIME/./}
      timed "$work/cpu-pp-client" "${pin[@]}" "$PINGPONG" client "127.0.0.1:$pp_port" "$blocks" 1044 > "$work/loop"
      floor+=("$(( ${EPOCHREALTIME/./} - t0 ))")
      loop+=("$(cat "$work/loop")")
      wait "$pp"
    done
    local m_ours m_lc m_floor m_loop
    m_ours=$(printf '%s\n' "${ours[@]}" | awk '{print $1/1e6}' | median)
    m_lc=$(printf '%s\n' "${lc[@]}" | awk '{print $1/1e6}' | median)
    m_floor=$(printf '%s\n' "${floor[@]}" | awk '{print $1/1e6}' | median)
    m_loop=$(printf '%s\n' "${loop[@]}" | median)
    awk -v l="$label" -v s="$s" -v o="$m_ours" -v c="$m_lc" -v f="$m_floor" -v p="$m_loop" \
      -v ro="$(peak_rss_kb "$ours_pid")" -v rc="$(peak_rss_kb "$lc_pid")" \
      -v ao="$(anon_kb "$ours_pid")" -v ac="$(anon_kb "$lc_pid")" \
      'BEGIN {printf "| %-8s | %10d | %7.3f | %7.3f | %7.3f | %5.2f | %5.2f | %7.3f | %5.2f | %6.1f (%4.1f) | %6.1f (%4.1f) |\n", \
        l, s, o, c, f, o/c, o/f, p, o/p, ro/1024, ao/1024, rc/1024, ac/1024}'
    # Per run, client plus server.
    local m_cpu=()
    for who in ours lc pp; do
      m_cpu+=("$(paste "$work/cpu-$who-client" "$work/cpu-$who-server" | awk '{print $1 + $2}' | median)")
    done
    awk -v l="$label" -v s="$s" -v o="${m_cpu[0]}" -v c="${m_cpu[1]}" -v f="${m_cpu[2]}" \
      'BEGIN {printf "| %-8s | %10d | %7.1f | %7.1f | %7.1f | %5.2f | %5.2f |\n", l, s, o, c, f, o/c, o/f}' >> "$work/cpu.md"
    kill "$ours_pid" "$lc_pid" 2>/dev/null || true
    wait "$ours_pid" "$lc_pid" 2>/dev/null || true
  done
}

echo "RFC 7959 GET, 1024-byte blocks, median of $RUNS runs (seconds, whole-process wall time;"
echo "server peak RSS in MB, private memory in brackets)"
echo
echo "| mode     |      bytes | coapcam | libcoap |   floor | /libcoap | /floor | floor loop | /loop | coapcam RSS | libcoap RSS |"
echo "|----------|-----------:|--------:|--------:|--------:|------:|------:|--------:|------:|------------:|------------:|"
run_mode unpinned
run_mode "pinned"  taskset -c 0
echo
echo "CPU time per transfer, client and server together (milliseconds, median of $RUNS)"
echo
echo "| mode     |      bytes | coapcam | libcoap |   floor | /libcoap | /floor |"
echo "|----------|-----------:|--------:|--------:|--------:|------:|------:|"
cat "$work/cpu.md"
