#!/usr/bin/env bash
# build-libcoap-openssl.sh [DIR]: builds libcoap 4.3.5's example client and server with
# OpenSSL (DTLS and TLS, so coaps://, coaps+tcp:// and coaps+ws://; TCP and WebSockets are
# on by default in 4.3.5) from ../shared/peers/libcoap-4.3.5.tar.gz, into DIR (default:
# $HOME/.cache/coapcam-peers/libcoap-4.3.5-openssl), and prints the folder holding
# `coap-client` and `coap-server`. Idempotent: a finished build is reused. A test peer for
# the coaps+ws interop tests (crates/coapcam/tests/it/tls.rs): Debian's libcoap 4.3.1 has
# TLS but no WebSockets, and ../shared/peers/build-libcoap.sh builds 4.3.5 without DTLS
# or TLS. Needs gcc, make, cmake and libssl-dev (cmake installed with apt-get when missing
# and running as root; scripts/test.sh installs libssl-dev). libcoap is BSD-2-Clause; its
# source is a test peer, not part of coapcam.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
tarball=${COAPCAM_LIBCOAP_TARBALL:-$here/../../shared/peers/libcoap-4.3.5.tar.gz}
dir=${1:-$HOME/.cache/coapcam-peers/libcoap-4.3.5-openssl}
if [ -x "$dir/build/coap-client" ] && [ -x "$dir/build/coap-server" ]; then
  echo "$dir/build"; exit 0
fi
if [ ! -f "$tarball" ]; then
  echo "build-libcoap-openssl.sh: $tarball not found" >&2; exit 1
fi
if ! command -v cmake >/dev/null; then
  if [ "$(id -u)" -eq 0 ]; then
    { apt-get install -y -q cmake || { apt-get update -q && apt-get install -y -q cmake; }; } >&2
  else
    echo "build-libcoap-openssl.sh: cmake is missing" >&2; exit 1
  fi
fi
mkdir -p "$dir"
tar -xzf "$tarball" -C "$dir" --strip-components=1
mkdir -p "$dir/build"
cd "$dir/build"
cmake .. -DENABLE_DTLS=ON -DDTLS_BACKEND=openssl -DENABLE_TCP=ON -DENABLE_WS=ON \
  -DENABLE_OSCORE=OFF -DENABLE_EXAMPLES=ON -DENABLE_DOCS=OFF -DENABLE_TESTS=OFF \
  -DCMAKE_BUILD_TYPE=Release >cmake.log 2>&1 || { tail -20 cmake.log >&2; exit 1; }
make -j"$(nproc)" coap-client coap-server >make.log 2>&1 || { tail -20 make.log >&2; exit 1; }
echo "$dir/build"
