#!/usr/bin/env bash
# Proof-suite benchmark of `lensrig diagnose`: every concealed effect and clean data over
# SEEDS seeds (default 3); prints effect, the effect named first, base and final reduced χ²,
# and the final residual RMS over the true noise floor, and the seconds of the diagnosis.
# Realistic size (issue 17), e.g.:
#   scripts/bench-diagnose.sh 3 --bench-first-seed 41 --bench-size 1024x768 --bench-rgb --bench-kernel 45
#   scripts/bench-diagnose.sh 3 --bench-first-seed 41 --bench-lens ../shared/data/lenses/sf11-singlet-25mm-f5.6
# (--bench-effect clean,vignetting picks cases; per-stage seconds and peak memory on stderr/stdout).
set -euo pipefail
cd "$(dirname "$0")/.."
seeds="${1:-3}"
shift || true
cargo run --release --quiet -- diagnose --bench-seeds "$seeds" "$@"
