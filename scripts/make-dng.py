#!/usr/bin/env python3
"""Write a Bayer DNG from a linear RGB render, with an independent DNG writer (pidng).

lensrig's raw tests use this to get DNG files that lensrig's own code did not write: the
mosaicking, the level encoding, the masked border and every DNG tag come from here and pidng.

Input: planar little-endian float32 RGB, 3 x HEIGHT x WIDTH, linear, 0 = black, 1 = white
(the Rust test writes it from a simulator render). Output: a 16-bit uncompressed DNG whose
active area is the render, surrounded by BORDER masked pixels at the black level, with

    code = round(black[cfa position] + value * (white - black[cfa position]))   (clipped)

CFA pattern, per-position black levels (BlackLevelRepeatDim 2x2) and the white level as given.
`--cfa CYGM` writes a non-Bayer pattern (for the "unsupported" test).

Set up:  python3 -m venv target/pyenv && target/pyenv/bin/pip install pidng numpy
Usage:   target/pyenv/bin/python scripts/make-dng.py --in render.f32 --width 512 --height 384 \
             --cfa RGGB --black 1024,1040,1032,1048 --white 15000 --border 8 --out capture.dng
"""
import argparse
import os
import sys

import numpy as np
from pidng.core import RAW2DNG, DNGTags, Tag
from pidng.defs import CalibrationIlluminant, DNGVersion, Orientation, PhotometricInterpretation

# DNG CFAPattern colour codes: 0 red, 1 green, 2 blue, 3 cyan, 4 magenta, 5 yellow
CODES = {"R": 0, "G": 1, "B": 2, "C": 3, "M": 4, "Y": 5}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--in", dest="inp", required=True)
    ap.add_argument("--width", type=int, required=True)
    ap.add_argument("--height", type=int, required=True)
    ap.add_argument("--cfa", default="RGGB")
    ap.add_argument("--black", default="1024", help="one level or four, row-major over the 2x2 cell")
    ap.add_argument("--white", type=int, default=15000)
    ap.add_argument("--border", type=int, default=8, help="masked pixels on each side (even)")
    ap.add_argument("--out", required=True)
    a = ap.parse_args()

    w, h, b = a.width, a.height, a.border
    if len(a.cfa) != 4 or any(c not in CODES for c in a.cfa):
        sys.exit(f"--cfa must be four letters of {''.join(CODES)}, got {a.cfa}")
    if w % 2 or h % 2 or b % 2:
        sys.exit("width, height and border must be even")
    black = [float(x) for x in a.black.split(",")]
    if len(black) == 1:
        black *= 4
    if len(black) != 4:
        sys.exit("--black takes one or four values")

    rgb = np.fromfile(a.inp, dtype="<f4")
    if rgb.size != 3 * w * h:
        sys.exit(f"{a.inp}: {rgb.size} floats, expected 3 x {h} x {w}")
    rgb = rgb.reshape(3, h, w).astype(np.float64)

    mosaic = np.zeros((h, w), dtype=np.float64)
    for i, c in enumerate(a.cfa):
        dy, dx = divmod(i, 2)
        src = rgb["RGB".index(c)] if c in "RGB" else rgb[1]  # CYGM: any plane will do
        mosaic[dy::2, dx::2] = black[i] + src[dy::2, dx::2] * (a.white - black[i])
    full = np.zeros((h + 2 * b, w + 2 * b), dtype=np.float64)
    for i in range(4):
        dy, dx = divmod(i, 2)
        full[dy::2, dx::2] = black[i]  # masked border: black (phase kept, b is even)
    full[b : b + h, b : b + w] = mosaic
    codes = np.clip(np.rint(full), 0, 65535).astype(np.uint16)

    t = DNGTags()
    t.set(Tag.ImageWidth, w + 2 * b)
    t.set(Tag.ImageLength, h + 2 * b)
    t.set(Tag.TileWidth, w + 2 * b)
    t.set(Tag.TileLength, h + 2 * b)
    t.set(Tag.Orientation, Orientation.Horizontal)
    t.set(Tag.PhotometricInterpretation, PhotometricInterpretation.Color_Filter_Array)
    t.set(Tag.SamplesPerPixel, 1)
    t.set(Tag.BitsPerSample, 16)
    t.set(Tag.CFARepeatPatternDim, [2, 2])
    t.set(Tag.CFAPattern, [CODES[c] for c in a.cfa])
    t.set(Tag.BlackLevelRepeatDim, [2, 2])
    t.set(Tag.BlackLevel, [int(round(x)) for x in black])
    t.set(Tag.WhiteLevel, a.white)
    # ActiveArea: top, left, bottom, right
    t.set(Tag.ActiveArea, [b, b, b + h, b + w])
    t.set(Tag.ColorMatrix1, [[1, 1], [0, 1], [0, 1], [0, 1], [1, 1], [0, 1], [0, 1], [0, 1], [1, 1]])
    t.set(Tag.CalibrationIlluminant1, CalibrationIlluminant.D65)
    t.set(Tag.AsShotNeutral, [[1, 1], [1, 1], [1, 1]])
    t.set(Tag.Make, "lensrig")
    t.set(Tag.Model, "pidng test")
    t.set(Tag.DNGVersion, DNGVersion.V1_4)
    t.set(Tag.DNGBackwardVersion, DNGVersion.V1_2)

    out_dir, name = os.path.split(os.path.abspath(a.out))
    if not name.endswith(".dng"):
        sys.exit("--out must end in .dng")
    r = RAW2DNG()
    r.options(t, path=out_dir, compress=False)
    r.convert(codes, filename=name[: -len(".dng")])
    return 0


if __name__ == "__main__":
    sys.exit(main())
