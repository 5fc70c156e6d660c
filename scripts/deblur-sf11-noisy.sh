#!/usr/bin/env bash
# The real-design-lens case of the deblur benchmark (docs/deconvolution.md "Coloured-noise
# denoising"): astronaut mirror-tiled to 1024x768 (its stored 16-bit values taken as linear),
# blurred by `lensrig simulate` through the sf11 truth profile (../shared/data/lenses), with
# Poisson-Gaussian noise of 15 000 e- full well / 4 e- read noise (seed 1), restored by
# `lensrig deblur` with the true noise law and each denoiser noise model.
#
# usage: scripts/deblur-sf11-noisy.sh [OUT_DIR]
# Prints PSNR (dB, linear values) of the blurred input and of each restoration, and seconds
# (shared machine).
set -euo pipefail
cd "$(dirname "$0")/.."
OUT="${1:-target/sf11-noisy}"
LENS=/work/shared/data/lenses/sf11-singlet-25mm-f5.6
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$PWD/target}"
mkdir -p "$OUT"
cargo build --release --quiet --bin lensrig --example deblur_peers --example noisy_capture
R="$CARGO_TARGET_DIR/release"
"$R/examples/deblur_peers" enlarge /work/shared/data/scenes/astronaut.png 1024 768 "$OUT/sharp.png"
"$R/lensrig" simulate --profile "$LENS" --sharp "$OUT/sharp.png" --out "$OUT/open.png" --force
"$R/examples/noisy_capture" noise "$OUT/open.png" 15000 4 1 "$OUT/blurred.png"
echo "blurred: $("$R/examples/noisy_capture" psnr "$OUT/sharp.png" "$OUT/blurred.png") dB"
LAW="gain=$(echo 'scale=10; 1/15000' | bc),read=$(echo 'scale=10; 4/15000' | bc)"
for m in flat coloured; do
  t0=$(date +%s.%N)
  "$R/lensrig" deblur --profile "$LENS" --in "$OUT/blurred.png" --out "$OUT/lensrig-$m.png" --force --quiet \
    --noise "$LAW" --denoise-noise "$m"
  t1=$(date +%s.%N)
  echo "lensrig ($m denoiser): $("$R/examples/noisy_capture" psnr "$OUT/sharp.png" "$OUT/lensrig-$m.png") dB, $(echo "$t1 - $t0" | bc) s"
done
