#!/bin/sh
# Runs every loader's fuzz target for a fixed budget and prints a table (corpus, time,
# executions). Not part of `cargo test`: a benchmark/CI step.
#
#   scripts/fuzz.sh [SECONDS_PER_TARGET] [TARGET...]     (default 20 s, all targets)
#
# With cargo-fuzz and a nightly toolchain (LENSRIG_FUZZ=libfuzzer), runs libFuzzer on
# fuzz/fuzz_targets/*; otherwise the stable driver examples/fuzz_stable.rs (same bodies,
# fuzz/targets.rs; random mutations of fuzz/corpus/<target>/ without coverage feedback).
# Exit status 1 when any target crashed; crashing inputs land in fuzz/artifacts/<target>/.
set -eu
cd "$(dirname "$0")/.."
secs=${1:-20}
[ $# -gt 0 ] && shift
if [ "${LENSRIG_FUZZ:-stable}" = libfuzzer ] && cargo +nightly fuzz --version >/dev/null 2>&1; then
    targets=${*:-image profile rig_config session grbl_line}
    for t in $targets; do
        mkdir -p "fuzz/corpus/$t"
        cargo +nightly fuzz run "$t" "fuzz/corpus/$t" -- -max_total_time="$secs" -rss_limit_mb=2048 -timeout=10
    done
else
    cargo run --release --quiet --example fuzz_stable -- --seconds "$secs" "$@"
fi
