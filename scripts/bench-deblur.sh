#!/usr/bin/env bash
# Benchmark `lensrig deblur` against scikit-image Richardson-Lucy and Wiener (true PSFs, same
# tiling and hat-weight blending) on the photographs in /work/shared/data/scenes.
#
# usage: scripts/bench-deblur.sh [OUT_DIR] [SCENE.png ...]
# Prints a markdown table: scene, size, method, PSNR (dB, sRGB values), seconds.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT="${1:-target/bench-deblur}"
shift || true
if [ "$#" -gt 0 ]; then SCENES=("$@"); else SCENES=(/work/shared/data/scenes/*.png); fi
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$PWD/target}"
mkdir -p "$OUT"

cargo build --release --quiet --example deblur_peers
BIN="$CARGO_TARGET_DIR/release/examples/deblur_peers"
"$BIN" prepare "$OUT" "${SCENES[@]}"

VENV="$OUT/venv"
PEERS_OK=1
if [ ! -x "$VENV/bin/python" ] || ! "$VENV/bin/python" -c "import skimage" 2>/dev/null; then
  if ! { python3 -m venv "$VENV" && "$VENV/bin/pip" install --quiet scikit-image; } >"$OUT/pip.log" 2>&1; then
    PEERS_OK=0
  fi
fi
if [ "$PEERS_OK" = 1 ]; then
  "$VENV/bin/python" scripts/peers.py "$OUT" "${SCENES[@]}" || PEERS_OK=0
fi
if [ "$PEERS_OK" = 0 ]; then
  for s in "${SCENES[@]}"; do
    n="$(basename "$s" .png)"
    for m in richardson_lucy wiener; do
      [ -f "$OUT/$n/$m.png" ] || echo "scikit-image could not be installed or run, see $OUT/pip.log" >"$OUT/$n/$m.error"
    done
  done
fi
echo "machine: $(nproc) cores, $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs)"
"$BIN" report "$OUT" "${SCENES[@]}"
