#!/usr/bin/env bash
# Fuzzes each cargo-fuzz target for N seconds, one after the other (default 600), e.g.
#   scripts/fuzz.sh 600                    # every target
#   scripts/fuzz.sh 60 endpoint_handle     # one target
# The corpus grows in fuzz/corpus/<target>/ (only the seed-* files are committed); crashes
# land in fuzz/artifacts/<target>/. Reproduce one with
#   cd fuzz && RUSTC_BOOTSTRAP=1 cargo fuzz run -O <target> artifacts/<target>/crash-...
set -euo pipefail
secs="${1:-600}"
shift || true
here="$(dirname "$0")"
bash "$here/fuzz-build.sh" -O
cd "$here/../fuzz"
export RUSTC_BOOTSTRAP=1

targets=("$@")
if [ ${#targets[@]} -eq 0 ]; then
    mapfile -t targets < <(cargo fuzz list)
fi
for target in "${targets[@]}"; do
    printf '\n== fuzz %s for %ss\n' "$target" "$secs"
    cargo fuzz run -O "$target" -- -max_total_time="$secs" -print_final_stats=1
done
