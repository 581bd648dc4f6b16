#!/usr/bin/env bash
# Windowed against stop-and-wait Block2 GETs through an emulated link, in the same run.
#
#   scripts/bench-window.sh [RUNS] [SLOW_RUNS]     (defaults 5 and 1)
#   LOSSES="0.02" scripts/bench-window.sh ...     (only these loss rates; default "0 0.02")
#
# Every transfer goes through `coapcam netem` with a 20 ms round trip (10 ms each way), at
# 0 % and 2 % loss each way. Sizes 921,610 and 2,764,810 bytes (a 640x480 and a 1280x720
# RGB frame), 1024-byte blocks, served by `coapcam serve --no-cameras --static`. Modes:
#   window         coapcam get (the default, --transfer window), RUNS runs
#   stop-and-wait  coapcam get --transfer stop-and-wait, SLOW_RUNS runs
#   libcoap 4.3.1  coap-client-notls (RFC 7959, CON, NSTART 1, at most 300 s), SLOW_RUNS runs
#   QUIC           crates/quic-bench (quinn 0.11 with BBR, one stream), RUNS runs: the
#                  modern-transport reference, through the same relay
# Each time is the whole process's wall time (QUIC's includes its handshake, CoAP needs
# none); every body is compared with the original (a mismatch aborts). The table gives
# medians (seconds) and ratios.
set -euo pipefail
cd "$(dirname "$0")/.."
RUNS=${1:-5}
SLOW_RUNS=${2:-1}
command -v coap-client-notls >/dev/null || { echo "needs libcoap3-bin (apt-get install libcoap3-bin)" >&2; exit 1; }

cargo build --release -q -p coapcam -p quic-bench
BIN=${CARGO_TARGET_DIR:-target}/release/coapcam
QUIC=${CARGO_TARGET_DIR:-target}/release/quic-bench

work=$(mktemp -d)
pids=()
cleanup() { for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done; rm -rf "$work"; }
trap cleanup EXIT
mkdir -p "$work/files"
SIZES=(921610 2764810)
for s in "${SIZES[@]}"; do head -c "$s" /dev/urandom > "$work/files/body-$s.bin"; done

free_port() { python3 -c 'import socket; s=socket.socket(socket.AF_INET, socket.SOCK_DGRAM); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])'; }
median() { sort -g | awk '{a[NR]=$1} END {if (NR%2) print a[(NR+1)/2]; else printf "%.6f\n", (a[NR/2]+a[NR/2+1])/2}'; }

server_port=$(free_port)
"$BIN" serve --no-cameras --static "$work/files" --bind "127.0.0.1:$server_port" 2>/dev/null &
pids+=("$!")
declare -A quic_port
for s in "${SIZES[@]}"; do
  quic_port[$s]=$(free_port)
  "$QUIC" serve "127.0.0.1:${quic_port[$s]}" "$work/files/body-$s.bin" "$work/cert-$s.der" >/dev/null &
  pids+=("$!")
done
sleep 0.5

# timed_runs N SIZE CMD...: runs CMD N times (it writes $work/out), prints the median
# seconds, or "failed" if a run failed (what it printed goes to standard error). A body
# that differs from the original aborts the benchmark.
timed_runs() {
  local n=$1 size=$2; shift 2
  local times=()
  for _ in $(seq "$n"); do
    rm -f "$work/out"
    local t0=${EPOCHREALTIME/./}
    if ! "$@" >/dev/null 2>"$work/err"; then
      echo "$* failed after $(( (${EPOCHREALTIME/./} - t0) / 1000000 )) s:" >&2
      cat "$work/err" >&2
      echo failed
      return
    fi
    times+=("$(( ${EPOCHREALTIME/./} - t0 ))")
    cmp -s "$work/out" "$work/files/body-$size.bin" || { echo "$*: body differs" >&2; exit 1; }
  done
  printf '%s\n' "${times[@]}" | awk '{print $1/1e6}' | median | awk '{printf "%.3f\n", $1}'
}

# ratio A B: A / B with one decimal and an x, or "-" if either failed.
ratio() { awk -v a="$1" -v b="$2" 'BEGIN {if (a == "failed" || b == "failed") print "-"; else printf "%.2fx\n", a / b}'; }

echo "Block2 GET through coapcam netem, 20 ms round trip, 1024-byte blocks (seconds, median;"
echo "window: $RUNS runs, the others: $SLOW_RUNS)"
echo
echo "| loss each way |      bytes | window |  QUIC | stop-and-wait | libcoap 4.3.1 | window / QUIC | s&w / window | libcoap / window |"
echo "|--------------:|-----------:|-------:|------:|--------------:|--------------:|--------------:|-------------:|-----------------:|"
for loss in ${LOSSES:-0 0.02}; do
  for s in "${SIZES[@]}"; do
    port=$(free_port); qport=$(free_port)
    "$BIN" netem --listen "127.0.0.1:$port" --forward "127.0.0.1:$server_port" \
      --delay-ms 10 --loss "$loss" --seed 7 >/dev/null 2>&1 &
    netem=$!; pids+=("$netem")
    "$BIN" netem --listen "127.0.0.1:$qport" --forward "127.0.0.1:${quic_port[$s]}" \
      --delay-ms 10 --loss "$loss" --seed 7 >/dev/null 2>&1 &
    qnetem=$!; pids+=("$qnetem")
    sleep 0.5
    uri="coap://127.0.0.1:$port/files/body-$s.bin"
    w=$(timed_runs "$RUNS" "$s" "$BIN" get "$uri" -o "$work/out")
    q=$(timed_runs "$RUNS" "$s" "$QUIC" get "127.0.0.1:$qport" "$work/cert-$s.der" "$work/out")
    sw=$(timed_runs "$SLOW_RUNS" "$s" "$BIN" get "$uri" --transfer stop-and-wait -o "$work/out")
    lc=$(timed_runs "$SLOW_RUNS" "$s" timeout 300 coap-client-notls -b 1024 -B 300 "$uri" -o "$work/out")
    printf '| %12s %% | %10d | %6s | %5s | %13s | %13s | %13s | %12s | %16s |\n' \
      "$(awk -v l="$loss" 'BEGIN {print l * 100}')" "$s" "$w" "$q" "$sw" "$lc" \
      "$(ratio "$w" "$q")" "$(ratio "$sw" "$w")" "$(ratio "$lc" "$w")"
    kill "$netem" "$qnetem"; wait "$netem" "$qnetem" 2>/dev/null || true
  done
done
