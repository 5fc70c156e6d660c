#!/usr/bin/env bash
# Benchmark `lensrig deblur` against scikit-image Richardson-Lucy and Wiener (true PSFs, same
# tiling and hat-weight blending) on the photographs in /work/shared/data/scenes.
#
# usage: scripts/bench-deblur.sh [OUT_DIR] [SCENE.png ...]
# Prints a markdown table: scene, size, method, PSNR (dB, sRGB values), seconds.
# LARGE=1 also times lensrig alone on 1-MP (1024x1024) and 12-MP (4000x3000) mirror-tilings of
# hubble_deep_field (no peers): the `run` line (deblur wall and CPU seconds, PSNR) and the
# process's wall, user, system seconds and peak RSS from /usr/bin/time -v.
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

if [ "${LARGE:-0}" = 1 ]; then
  L="$OUT/large"
  mkdir -p "$L"
  SRC=/work/shared/data/scenes/hubble_deep_field.png
  "$BIN" enlarge "$SRC" 1024 1024 "$L/mp1.png"
  "$BIN" enlarge "$SRC" 4000 3000 "$L/mp12.png"
  LR_NO_RUN=1 "$BIN" prepare "$L" "$L/mp1.png" "$L/mp12.png"
  for m in mp1 mp12; do
    /usr/bin/time -v "$BIN" run "$L" "$L/$m.png" 2>"$L/$m.time-v"
    grep -E "Elapsed|User time|System time|Maximum resident" "$L/$m.time-v"
  done
fi
