#!/usr/bin/env bash
# The project's test command (README "Test"). CI runs exactly this through .ci/run.
# It installs what the tests need, then: format check, clippy with -D warnings, all tests.
set -euo pipefail
cd "$(dirname "$0")/.."

step() { printf '\n== %s\n' "$*"; }

step "toolchain"
cargo --version
rustup component list --installed 2>/dev/null | grep -E 'rustfmt|clippy' || true

step "cargo fmt --check"
cargo fmt --all -- --check

step "cargo clippy -D warnings"
cargo clippy --workspace --all-targets --locked -- -D warnings

step "cargo test"
cargo test --workspace --locked

step "multicast tests in a private network namespace"
# Group traffic must never leave through a real interface: these tests run only inside a
# namespace of their own (scripts/netns-run), which needs root and iproute2.
if ! command -v ip >/dev/null; then
  apt-get install -y iproute2
fi
scripts/netns-run cargo test -p coap-net --test it --locked multicast

step "fuzz targets build and replay their seeds"
bash scripts/fuzz-build.sh

echo
echo "all checks passed"
