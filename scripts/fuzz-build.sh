#!/usr/bin/env bash
# Builds the cargo-fuzz targets in fuzz/ and replays their seed corpus once (no fuzzing).
#   scripts/fuzz-build.sh        CI (scripts/test.sh): a debug build (cargo fuzz --dev)
#   scripts/fuzz-build.sh -O     scripts/fuzz.sh, before fuzzing: the optimised build
# Both instrument every crate for coverage and AddressSanitizer; the debug build also has
# debug assertions and overflow checks on. It compiles in well under half the CPU time:
# cargo-fuzz compiles -O at opt-level 3 with one codegen unit per crate, for fuzzing speed,
# which a replay of a few seeds does not need (the -O build took 16-18 min in CI; the debug
# build 13.7 CPU-minutes, `cargo fuzz build --dev` under /usr/bin/time).
#
# cargo-fuzz passes nightly-only flags (-Zsanitizer=address, -Cpasses=sancov-module). On a
# stable toolchain RUSTC_BOOTSTRAP=1 unlocks them; on nightly it is harmless.
set -euo pipefail
cd "$(dirname "$0")/../fuzz"
mode="${1:---dev}"

CARGO_FUZZ_VERSION=0.13.2
if ! cargo fuzz --version >/dev/null 2>&1; then
    cargo install cargo-fuzz --version "$CARGO_FUZZ_VERSION" --locked
fi
export RUSTC_BOOTSTRAP=1

cargo fuzz build "$mode"
for target in $(cargo fuzz list); do
    # -runs=0: execute every input of the corpus once, then stop. Only the committed seeds
    # are replayed, so a local corpus cannot change what CI checks.
    seeds="$(mktemp -d)"
    cp corpus/"$target"/seed-* "$seeds"/
    cargo fuzz run "$mode" "$target" "$seeds" -- -runs=0
    rm -rf "$seeds"
done
