#!/usr/bin/env python3
"""quicktex (pip: quicktex, an rgbcx-derived BC1 encoder) as a benchmark peer.

Two ways to run it:

  bc1_quicktex.py --raw PAD.rgba --width PW --height PH --levels 10,18 --out-dir DIR
      Encodes an RGBA8 image whose size is already a multiple of 4 (the
      Rust benchmark pads by edge replication and writes it), writes the
      blocks of each level to DIR/quicktex-LEVEL.bc1 and prints one JSON
      line per level with the encode time. The Rust benchmark decodes the
      blocks with the crate's decoder, so PSNR is computed the same way
      for every encoder.

  bc1_quicktex.py IMAGE.png [--levels 10,18]
      Stand-alone: pads, encodes, decodes with the exact float palette of
      SPEC §5 (re-implemented here with numpy) and prints PSNR and MPix/s.

Encoding is timed around quicktex's encode() call only; quicktex encodes on
one thread. Its colour mode is left at the default, FourColor, which matches
the four-colour-only constraint of our encoder.
"""

import argparse
import json
import os
import sys
import time

import numpy as np

try:
    import quicktex
    import quicktex.s3tc.bc1 as qbc1
except ImportError:  # pragma: no cover - reported, not fatal
    print(json.dumps({"error": "quicktex is not installed (pip install quicktex)"}))
    sys.exit(3)


def encode(rgba, level, repeats=1):
    h, w, _ = rgba.shape
    tex = quicktex.RawTexture.frombytes(np.ascontiguousarray(rgba).tobytes(), w, h)
    enc = qbc1.BC1Encoder(level)
    best = None
    out = None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = enc.encode(tex)
        dt = time.perf_counter() - t0
        best = dt if best is None else min(best, dt)
    return out.tobytes(), best


def expand(c):
    r = (c >> 11) & 31
    g = (c >> 5) & 63
    b = c & 31
    return np.stack([(r << 3) | (r >> 2), (g << 2) | (g >> 4), (b << 3) | (b >> 2)], -1).astype(np.float32)


def decode(data, pw, ph):
    """Exact float palette (SPEC §5), values in [0,1], padded size."""
    blk = np.frombuffer(data, dtype="<u4").reshape(-1, 2)
    c0 = (blk[:, 0] & 0xFFFF).astype(np.int64)
    c1 = (blk[:, 0] >> 16).astype(np.int64)
    idx = blk[:, 1].astype(np.int64)
    a, b = expand(c0), expand(c1)
    four = (c0 > c1)[:, None]
    p2 = np.where(four, (2 * a + b) / np.float32(3), (a + b) / np.float32(2))
    p3 = np.where(four, (a + 2 * b) / np.float32(3), np.float32(0))
    pal = np.stack([a, b, p2, p3], 1) / np.float32(255)  # (n, 4, 3)
    sel = (idx[:, None] >> (2 * np.arange(16))) & 3  # (n, 16)
    tex = np.take_along_axis(pal, sel[:, :, None], 1)  # (n, 16, 3)
    bw, bh = pw // 4, ph // 4
    tex = tex.reshape(bh, bw, 4, 4, 3).transpose(0, 2, 1, 3, 4).reshape(ph, pw, 3)
    return tex


def pad(rgba):
    h, w, _ = rgba.shape
    ph, pw = -(-h // 4) * 4, -(-w // 4) * 4
    return np.pad(rgba, ((0, ph - h), (0, pw - w), (0, 0)), mode="edge")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("image", nargs="?", help="PNG image (stand-alone mode)")
    ap.add_argument("--raw", help="padded RGBA8 file")
    ap.add_argument("--width", type=int)
    ap.add_argument("--height", type=int)
    ap.add_argument("--levels", default="10,18")
    ap.add_argument("--out-dir")
    ap.add_argument("--repeats", type=int, default=1)
    args = ap.parse_args()
    levels = [int(v) for v in args.levels.split(",") if v]

    if args.raw:
        pw, ph = args.width, args.height
        if not pw or not ph or pw % 4 or ph % 4:
            ap.error("--raw needs --width and --height, multiples of 4")
        raw = np.fromfile(args.raw, dtype=np.uint8)
        if raw.size != pw * ph * 4:
            ap.error(f"{args.raw}: {raw.size} bytes, expected {pw * ph * 4}")
        rgba = raw.reshape(ph, pw, 4)
        for level in levels:
            data, secs = encode(rgba, level, args.repeats)
            if args.out_dir:
                with open(os.path.join(args.out_dir, f"quicktex-{level}.bc1"), "wb") as f:
                    f.write(data)
            print(json.dumps({"level": level, "seconds": secs, "bytes": len(data)}), flush=True)
        return

    if not args.image:
        ap.error("give an image or --raw")
    if not os.path.exists(args.image):
        print(f"{args.image}: not found; skipped")
        return
    from PIL import Image

    src = np.asarray(Image.open(args.image).convert("RGBA"))
    h, w, _ = src.shape
    rgba = pad(src)
    ph, pw, _ = rgba.shape
    ref = src[:, :, :3].astype(np.float64) / 255.0
    for level in levels:
        data, secs = encode(rgba, level, args.repeats)
        dec = decode(data, pw, ph)[:h, :w].astype(np.float64)
        mse = np.mean((dec - ref) ** 2)
        psnr = float("inf") if mse == 0 else 10 * np.log10(1 / mse)
        print(f"{os.path.basename(args.image)} {w}x{h} quicktex level {level}: PSNR {psnr:.3f} dB, {w * h / secs / 1e6:.2f} MPix/s (1 thread)")


if __name__ == "__main__":
    main()
