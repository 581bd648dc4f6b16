#!/usr/bin/env bash
# Regenerates crates/coapcam/link-order.txt, the order in which the release build's linker
# places functions at the front of the binary's code (crates/coapcam/build.rs).
#
#   scripts/link-order.sh
#
# It runs `coapcam serve --no-cameras --static` and `coapcam get` of a 2,764,810-byte
# file under callgrind and lists every function of the coapcam binary each of them ran:
# the server's first, then those only the client ran, each group sorted by name.
# Placed together, the code a server runs fills a few 64 KiB runs of pages instead of
# being spread over the whole 6 MB of code, and the kernel maps each page it touches
# together with its neighbours (fault-around); the server's peak RSS is measured against
# libcoap's (scripts/bench-transfer.sh). The names carry rustc's hashes: after a toolchain
# update or much renaming, run this again (bench-transfer.sh reports how much of the list
# the binary still has).
set -euo pipefail
cd "$(dirname "$0")/.."
command -v valgrind >/dev/null || { echo "needs valgrind (apt-get install valgrind)" >&2; exit 1; }

cargo build --release -q -p coapcam
BIN=$(realpath "${CARGO_TARGET_DIR:-target}/release/coapcam")
work=$(mktemp -d)
server=
cleanup() { [ -n "$server" ] && kill "$server" 2>/dev/null; rm -rf "$work"; }
trap cleanup EXIT
mkdir "$work/files"
head -c 2764810 /dev/urandom > "$work/files/body.bin"
port=$(python3 -c 'import socket; s=socket.socket(socket.AF_INET, socket.SOCK_DGRAM); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])')

valgrind -q --tool=callgrind --demangle=no --callgrind-out-file="$work/serve.out" \
  "$BIN" serve --no-cameras --static "$work/files" --bind "127.0.0.1:$port" 2>"$work/serve.log" &
server=$!
for _ in $(seq 300); do grep -q "serving on" "$work/serve.log" && break; sleep 0.1; done
grep -q "serving on" "$work/serve.log" || { cat "$work/serve.log" >&2; exit 1; }
valgrind -q --tool=callgrind --demangle=no --callgrind-out-file="$work/get.out" \
  "$BIN" get "coap://127.0.0.1:$port/files/body.bin" --block-size 1024 -o "$work/out"
cmp "$work/out" "$work/files/body.bin"
kill -TERM "$server"
wait "$server" || true
server=

python3 - "$BIN" "$work/serve.out" "$work/get.out" > crates/coapcam/link-order.txt <<'EOF'
import re, subprocess, sys

binary, profiles = sys.argv[1], sys.argv[2:]
defined = set()
for line in subprocess.run(["nm", "--defined-only", binary], capture_output=True,
                           text=True, check=True).stdout.splitlines():
    parts = line.split()
    if len(parts) == 3 and parts[1] in "tTwW":
        defined.add(parts[2])

def ran(profile):
    """Functions of the coapcam object that have costs in a callgrind profile."""
    names, objects, found, current = {}, {}, set(), None
    for line in open(profile, errors="replace"):
        m = re.match(r"^(c?)(ob|fn)=\((\d+)\)(?: (.*))?$", line.rstrip("\n"))
        if not m:
            continue
        called, kind, idx, name = m.groups()
        table = objects if kind == "ob" else names
        if name is not None:
            table[idx] = name
        if called:
            continue
        if kind == "ob":
            current = objects.get(idx, "")
        elif current == binary:
            # Recursion levels show as name'2, name'3 ...
            found.add(re.sub(r"'\d+$", "", names.get(idx, "")))
    return found & defined

server = ran(profiles[0])
client = ran(profiles[1]) - server
for name in sorted(server) + sorted(client):
    print(name)
EOF
echo "crates/coapcam/link-order.txt: $(wc -l < crates/coapcam/link-order.txt) functions" >&2
