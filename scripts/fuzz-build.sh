#!/usr/bin/env bash
# Builds the cargo-fuzz targets in fuzz/ and replays their seed corpus once (no fuzzing).
# CI calls this; scripts/fuzz.sh calls it before fuzzing.
#
# cargo-fuzz passes nightly-only flags (-Zsanitizer=address, -Cpasses=sancov-module). On a
# stable toolchain RUSTC_BOOTSTRAP=1 unlocks them; on nightly it is harmless.
set -euo pipefail
cd "$(dirname "$0")/../fuzz"

CARGO_FUZZ_VERSION=0.13.2
if ! cargo fuzz --version >/dev/null 2>&1; then
    cargo install cargo-fuzz --version "$CARGO_FUZZ_VERSION" --locked
fi
export RUSTC_BOOTSTRAP=1

cargo fuzz build -O
for target in $(cargo fuzz list); do
    # -runs=0: execute every input of the corpus once, then stop. Only the committed seeds
    # are replayed, so a local corpus cannot change what CI checks.
    seeds="$(mktemp -d)"
    cp corpus/"$target"/seed-* "$seeds"/
    cargo fuzz run -O "$target" "$seeds" -- -runs=0
    rm -rf "$seeds"
done
