#!/usr/bin/env bash
# The project's test command (README, "Two commands"). CI runs exactly this via .ci/run.
# It installs the peers the tests need, then: format check, the module import checks, the
# commands' sizes and the map's names, clippy with -D warnings, all tests, the multicast
# tests inside a private network namespace, and the fuzz targets (built, seeds replayed).
set -euo pipefail
cd "$(dirname "$0")/.."
# A one-shot full check gains nothing from incremental caches, which would add ~0.9 GB to
# target/ (CI machines have little disk).
export CARGO_INCREMENTAL=0

# Each step's wall time, printed as a table when the script ends (also when a step fails),
# so a slow CI run shows where its minutes went.
step_name="" step_started=$SECONDS step_times=()
end_step() {
  [ -z "$step_name" ] || step_times+=("$(printf '%6d s  %s' $((SECONDS - step_started)) "$step_name")")
  step_name=""
}
print_step_times() {
  end_step
  printf '\n== step times (total %d s)\n' "$SECONDS"
  printf '%s\n' "${step_times[@]}"
}
trap print_step_times EXIT
step() {
  end_step
  step_name="$*" step_started=$SECONDS
  printf '\n== %s\n' "$*"
}
as_root() { if [ "$(id -u)" -eq 0 ]; then "$@"; else sudo "$@"; fi; }

step "toolchain"
cargo --version
rustup component list --installed 2>/dev/null | grep -E 'rustfmt|clippy' || true

step "build dependencies"
# DTLS (coaps://) is OpenSSL's: the openssl crate links the system's libssl.
if pkg-config --exists openssl 2>/dev/null; then
  echo "libssl-dev: present"
else
  as_root apt-get update && as_root env DEBIAN_FRONTEND=noninteractive \
    apt-get install -y --no-install-recommends libssl-dev pkg-config
fi

step "peers"
# The interop tests (crates/coapcam/tests/it/interop.rs, dtls.rs) drive libcoap 4.3.1 (also its
# OpenSSL DTLS tools) and 4.3.5 and aiocoap;
# they fail in CI (CI=true) when a peer is missing, and are skipped loudly elsewhere.
peer_failed() {
  echo "installing $1 failed" >&2
  if [ "${CI:-}" = true ]; then exit 1; fi
}
if command -v coap-client-notls >/dev/null && command -v coap-server-notls >/dev/null; then
  echo "libcoap3-bin: present"
else
  { as_root apt-get update && as_root env DEBIAN_FRONTEND=noninteractive \
      apt-get install -y --no-install-recommends libcoap3-bin; } || peer_failed libcoap3-bin
fi
# libcoap 4.3.5 (Q-Block, RFC 9177; Debian has only 4.3.1) is built from the source
# beside this repository (../shared/peers) for the Q-Block interop tests.
if [ -x ../shared/peers/build-libcoap.sh ] || [ -f ../shared/peers/build-libcoap.sh ]; then
  if COAPCAM_LIBCOAP435=$(bash ../shared/peers/build-libcoap.sh); then
    export COAPCAM_LIBCOAP435
    echo "libcoap 4.3.5: $COAPCAM_LIBCOAP435"
  else
    peer_failed "libcoap 4.3.5 (../shared/peers/build-libcoap.sh)"
  fi
else
  echo "libcoap 4.3.5: ../shared/peers/build-libcoap.sh not found; its tests skip (fail in CI)"
fi
# libcoap 4.3.5 with OpenSSL (coaps+tcp, coaps+ws: Debian's 4.3.1 has no WebSockets) from
# the same tarball, by a script of ours, for the coaps+ws interop tests (tests/it/tls.rs).
if COAPCAM_LIBCOAP435_OPENSSL=$(COAPCAM_LIBCOAP_TARBALL=../shared/peers/libcoap-4.3.5.tar.gz \
    bash scripts/build-libcoap-openssl.sh); then
  export COAPCAM_LIBCOAP435_OPENSSL
  echo "libcoap 4.3.5 with OpenSSL: $COAPCAM_LIBCOAP435_OPENSSL"
else
  peer_failed "libcoap 4.3.5 with OpenSSL (scripts/build-libcoap-openssl.sh)"
fi
AIOCOAP_VERSION=0.4.17
if command -v aiocoap-client >/dev/null \
  && python3 -c "import aiocoap.meta as m, sys; sys.exit(m.version != '$AIOCOAP_VERSION')" 2>/dev/null; then
  echo "aiocoap $AIOCOAP_VERSION: present"
else
  python3 -m pip install "aiocoap==$AIOCOAP_VERSION" || peer_failed "aiocoap==$AIOCOAP_VERSION"
fi
# aiocoap's CoAP over WebSockets (tests/it/ws.rs) needs websockets (aiocoap 0.4.17 takes >=13,<16).
WEBSOCKETS_VERSION=15.0.1
if python3 -c "import websockets, sys; sys.exit(websockets.__version__ != '$WEBSOCKETS_VERSION')" 2>/dev/null; then
  echo "websockets $WEBSOCKETS_VERSION: present"
else
  python3 -m pip install "websockets==$WEBSOCKETS_VERSION" || peer_failed "websockets==$WEBSOCKETS_VERSION"
fi
# The OPC UA output's test (crates/coapcam/tests/it/opcua.rs) runs tests/peers/opcua_client.py on
# asyncua, an OPC UA client library of its own.
ASYNCUA_VERSION=2.1.0
if python3 -c "import asyncua, sys; sys.exit(asyncua.__version__ != '$ASYNCUA_VERSION')" 2>/dev/null; then
  echo "asyncua $ASYNCUA_VERSION: present"
else
  python3 -m pip install "asyncua==$ASYNCUA_VERSION" || peer_failed "asyncua==$ASYNCUA_VERSION"
fi
# The resource directory tests (tests/it/rd.rs) run aiocoap-rd (aiocoap) and coap-rd-notls (libcoap3-bin).
command -v aiocoap-rd >/dev/null && command -v coap-rd-notls >/dev/null || peer_failed "aiocoap-rd and coap-rd-notls"
# The MQTT tests (crates/coapcam/tests/it/mqtt.rs) start Debian's mosquitto broker on a
# free loopback port and read it with mosquitto_sub (mosquitto-clients).
if { command -v mosquitto >/dev/null || [ -x /usr/sbin/mosquitto ]; } \
  && command -v mosquitto_sub >/dev/null; then
  echo "mosquitto: present"
else
  { as_root apt-get update && as_root env DEBIAN_FRONTEND=noninteractive \
      apt-get install -y --no-install-recommends mosquitto mosquitto-clients; } \
    || peer_failed "mosquitto mosquitto-clients"
fi
# The PostgreSQL output's tests (crates/coapcam/tests/it/postgres.rs) make a cluster with
# Debian's initdb and serve it with postgres on a free loopback port (as root, as the user
# nobody); Debian puts them in /usr/lib/postgresql/<version>/bin, not on PATH.
if command -v initdb >/dev/null && command -v postgres >/dev/null \
  || ls /usr/lib/postgresql/*/bin/initdb >/dev/null 2>&1; then
  echo "postgresql: present"
else
  { as_root apt-get update && as_root env DEBIAN_FRONTEND=noninteractive \
      apt-get install -y --no-install-recommends postgresql; } \
    || peer_failed postgresql
fi
# The page's test (crates/coapcam/tests/it/http.rs) drives headless Chromium through
# chromedriver's WebDriver API.
if command -v chromium >/dev/null && command -v chromedriver >/dev/null; then
  echo "chromium, chromedriver: present"
else
  { as_root apt-get update && as_root env DEBIAN_FRONTEND=noninteractive \
      apt-get install -y --no-install-recommends chromium chromium-driver; } \
    || peer_failed "chromium chromium-driver"
fi
# The markers sheet's test (crates/coapcam/tests/it/markers.rs) renders the PDF with
# poppler's pdftoppm and detects the markers on the pages.
if command -v pdftoppm >/dev/null; then
  echo "pdftoppm: present"
else
  { as_root apt-get update && as_root env DEBIAN_FRONTEND=noninteractive \
      apt-get install -y --no-install-recommends poppler-utils; } \
    || peer_failed poppler-utils
fi
# librealsense for the rgbd differential tests (crates/rgbd/tests/it/librealsense.rs
# regenerates its goldens with tools/rs_reference.py); its wheel needs libusb-1.0.
PYREALSENSE2_VERSION=2.59.1.11053
if python3 -c "import pyrealsense2, sys; sys.exit(pyrealsense2.__version__ != '2.59.1')" 2>/dev/null; then
  echo "pyrealsense2 $PYREALSENSE2_VERSION: present"
else
  python3 -m pip install "pyrealsense2==$PYREALSENSE2_VERSION" || peer_failed pyrealsense2
  ldconfig -p | grep 'libusb-1.0.so.0' >/dev/null || { as_root apt-get update && as_root env \
      DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends libusb-1.0-0; } \
    || peer_failed libusb-1.0-0
fi
# The realsense backend tests (crates/rgbd/tests/it/realsense.rs, crates/coapcam/tests/it/
# realsense.rs) load the wheel's module outside Python, after the libpython it needs.
if rs_paths=$(python3 -c "import os, sysconfig, pyrealsense2 as rs
print(rs.pyrealsense2.__file__)
print(os.path.join(sysconfig.get_config_var('LIBDIR'), sysconfig.get_config_var('INSTSONAME')))"); then
  COAPCAM_LIBREALSENSE=$(sed -n 1p <<<"$rs_paths")
  COAPCAM_LIBPYTHON=$(sed -n 2p <<<"$rs_paths")
  export COAPCAM_LIBREALSENSE COAPCAM_LIBPYTHON
  echo "librealsense: $COAPCAM_LIBREALSENSE (after $COAPCAM_LIBPYTHON)"
  [ -f "$COAPCAM_LIBPYTHON" ] || peer_failed "a shared libpython ($COAPCAM_LIBPYTHON)"
else
  peer_failed "pyrealsense2 paths"
fi

step "cargo fmt --check"
cargo fmt --all -- --check

step "no module import cycles, folders in the direction ARCHITECTURE.md states, commands small, the map's names real"
python3 scripts/module-cycles.py --self-test
python3 scripts/module-cycles.py
python3 scripts/cli-size.py --self-test
python3 scripts/cli-size.py
python3 scripts/map-names.py --self-test
python3 scripts/map-names.py

step "cargo clippy -D warnings"
cargo clippy --workspace --all-targets --locked -- -D warnings

step "cargo test"
cargo test --workspace --locked

step "multicast, off-host and full-disk tests in a private network namespace"
# Group traffic must never leave through a real interface: these tests run only inside a
# namespace of their own (scripts/netns-run), which needs root and iproute2. Its
# `ip netns exec` also gives them a mount namespace of their own, where the results-log
# tests mount a small tmpfs (a full disk) and an ext4 image (a disk turned read-only)
# that nothing outside sees.
if ! command -v ip >/dev/null; then
  as_root apt-get update && as_root env DEBIAN_FRONTEND=noninteractive \
    apt-get install -y --no-install-recommends iproute2
fi
# The whole workspace, as in the step above, so the test binaries built there are reused
# (`-p` alone unifies features differently and rebuilds ~300 MB of them).
scripts/netns-run cargo test --workspace --test it --locked -- --ignored multicast:: group:: offhost:: readme:: rd::three_servers \
  results::a_full_disk results::a_disk_turned_read_only

step "the README's main command, typed as the README gives it"
# From a scratch folder under target/ (cargo finds the workspace above it), so the demo's
# ./coapcam-demo lands there; a change that breaks `cargo run --release -- demo` fails here.
demo_dir=target/readme-demo
rm -rf "$demo_dir" && mkdir -p "$demo_dir"
demo_started=$SECONDS
demo_out=$(cd "$demo_dir" && cargo run --release -- demo)
printf '%s\n' "$demo_out"
# README.md quotes this figure's first-build counterpart.
echo "release build and demo: $((SECONDS - demo_started)) s"
for f in color.jpg depth.png depth-view.png depth-color.png cloud.ply top.png annotated.png; do
  [ -s "$demo_dir/coapcam-demo/$f" ] || { echo "demo did not write coapcam-demo/$f" >&2; exit 1; }
done
for row in "length mm" "width mm" "height mm"; do
  grep -Eq "^$row +[0-9]+\.[0-9] +[0-9]+\.[0-9] +[-+][0-9]+\.[0-9]\$" <<<"$demo_out" \
    || { echo "demo printed no \"$row\" row" >&2; exit 1; }
done

step "fuzz targets build and replay their seeds"
bash scripts/fuzz-build.sh

echo
echo "all checks passed"
