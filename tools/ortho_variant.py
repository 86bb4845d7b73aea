"""An orthophoto as an older survey would have it: coarser and in other colours, for honest prior-map test worlds.

A prior map comes from imagery taken months before the flight, at 0.1 to 0.5 m a pixel, in another light. This
writes such a variant of a GeoTIFF orthophoto (its CRS kept): area-averaged to ``--gsd-m``, each colour channel
through its own gain and gamma, a brightness that drifts slowly across the image (clouds, another sun) and, with
``--blur-px``, a little softness. The world a test flies stays the original; the prior map is built from the
variant of another mosaic.

    python tools/ortho_variant.py out/ortho/seneca_b.tif --gsd-m 0.3 --out out/ortho/seneca_b_03_shift.tif
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np
import rasterio
from rasterio.enums import Resampling

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from auxgps.io.orthophoto import Orthophoto  # noqa: E402


def shift_colours(rgb: np.ndarray, gains, gammas, drift: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 -> uint8: per channel ``255 * (gain * x / 255) ** gamma``, times ``drift`` (H, W)."""
    x = rgb.astype(np.float32) / 255.0
    out = np.empty_like(x)
    for c in range(3):
        out[..., c] = np.clip(gains[c] * x[..., c], 0, 1) ** gammas[c]
    out *= drift[..., None]
    return np.clip(np.rint(out * 255.0), 0, 255).astype(np.uint8)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("orthophoto")
    ap.add_argument("--out", required=True)
    ap.add_argument("--gsd-m", type=float, required=True, help="metres a pixel of the variant (coarser than the file)")
    ap.add_argument("--gains", type=float, nargs=3, default=(0.85, 1.08, 0.95), help="per channel (R, G, B)")
    ap.add_argument("--gammas", type=float, nargs=3, default=(1.25, 0.85, 1.1), help="per channel (R, G, B)")
    ap.add_argument("--drift", type=float, default=0.25, help="brightness varies by this much across the image (0: none)")
    ap.add_argument("--blur-px", type=float, default=0.0, help="Gaussian blur of the variant, its pixels (0: none)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)

    src = Orthophoto(args.orthophoto)
    factor = args.gsd_m / src.gsd_m
    if factor < 1.0:
        ap.error(f"--gsd-m {args.gsd_m} is finer than the file's {src.gsd_m:.4f} m")
    src.close()
    with rasterio.open(args.orthophoto) as ds:
        w, h = int(ds.width // factor), int(ds.height // factor)
        rgb = np.moveaxis(ds.read([1, 2, 3], out_shape=(3, h, w), resampling=Resampling.average), 0, -1)
        mask = ds.read_masks(1, out_shape=(h, w), resampling=Resampling.average) >= 255
        transform = ds.transform * ds.transform.scale(ds.width / w, ds.height / h)
        profile = dict(driver="GTiff", width=w, height=h, count=3, dtype="uint8", crs=ds.crs, transform=transform,
                       tiled=True, blockxsize=256, blockysize=256, compress="deflate", photometric="RGB")
        tags = ds.tags()
    rng = np.random.default_rng(args.seed)
    coarse = rng.normal(size=(4, 4))
    drift = 1.0 + args.drift * np.tanh(cv2.resize(coarse, (w, h), interpolation=cv2.INTER_CUBIC))
    out = shift_colours(rgb, args.gains, args.gammas, drift.astype(np.float32))
    if args.blur_px > 0:
        out = cv2.GaussianBlur(out, (0, 0), args.blur_px)
    out[~mask] = 0
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    with rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True):
        with rasterio.open(args.out, "w", **profile) as dst:
            dst.write(np.moveaxis(out, -1, 0))
            dst.write_mask(np.where(mask, 255, 0).astype(np.uint8))
            dst.update_tags(**tags)
            factors = [f for f in (2, 4, 8, 16) if min(w, h) // f >= 256]
            if factors:
                dst.build_overviews(factors, Resampling.average)
    print(f"wrote {args.out}: {w} x {h} px at {args.gsd_m:g} m, colours shifted (gains {args.gains}, gammas {args.gammas}, "
          f"drift {args.drift:g}), blur {args.blur_px:g} px")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
