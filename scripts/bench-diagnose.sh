#!/usr/bin/env bash
# Proof-suite benchmark of `lensrig diagnose`: every concealed effect and clean data over
# SEEDS seeds (default 3); prints effect, the effect named first, base and final reduced χ²,
# and the final residual RMS over the true noise floor.
set -euo pipefail
cd "$(dirname "$0")/.."
seeds="${1:-3}"
shift || true
cargo run --release --quiet -- diagnose --bench-seeds "$seeds" "$@"
