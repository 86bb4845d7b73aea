"""Where one orthophoto lies against another: shifts of windows, and the shift, scale and turn that fit them.

A prior map carries its orthophoto's placement error (`auxgps map build --georef-sigma-m`). This measures it against
an orthophoto you trust, say one built from your own flight with `auxgps ortho build`: both are read in grey at
``--gsd-m`` on the first one's grid (the second reprojected into it, any CRS), each ``--window-m`` square window
they both cover is phase-correlated (half-overlapping windows; those whose correlation peak is under
``--min-response`` are left out), and ``shift = t + M p`` is fitted by least squares over the window centres ``p``
(east, north, m from their mean). A scale shows as M's mean diagonal, a turn as its antisymmetric part.

    python tools/ortho_compare.py out/ortho/seneca.tif out/ortho/seneca_b.tif [--windows]
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass

import cv2
import numpy as np
import rasterio
from rasterio.transform import Affine
from rasterio.warp import Resampling, reproject


@dataclass(frozen=True)
class Comparison:
    """``p_en_m`` (K, 2) window centres, east and north of their mean, m; ``shift_en_m`` (K, 2) how far the second
    orthophoto's content lies from the first's there, m; ``response`` (K,); the fit ``shift = t_en_m + M p``, its
    residual RMS, m."""

    p_en_m: np.ndarray
    shift_en_m: np.ndarray
    response: np.ndarray
    t_en_m: np.ndarray
    M: np.ndarray
    residual_rms_m: float

    @property
    def scale(self) -> float:
        """The second's size against the first's, less one (-0.01: 1 % smaller)."""
        return float(np.trace(self.M) / 2.0)

    @property
    def turn_rad(self) -> float:
        """The second's turn against the first's, rad, anticlockwise seen from above (east to north)."""
        return float((self.M[1, 0] - self.M[0, 1]) / 2.0)


def _grey_on_grid(path: str, transform: Affine, crs, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The orthophoto's grey (mean of its first three bands) and its valid mask, reprojected onto the grid."""
    with rasterio.open(path) as ds:
        bands = min(ds.count, 3)
        grey = np.mean(ds.read(list(range(1, bands + 1))).astype(np.float32), axis=0)
        valid = (ds.read_masks(1) > 0).astype(np.float32)
        out, mask = np.zeros(shape, np.float32), np.zeros(shape, np.float32)
        for src, dst in ((grey, out), (valid, mask)):
            reproject(src, dst, src_transform=ds.transform, src_crs=ds.crs, dst_transform=transform, dst_crs=crs,
                      resampling=Resampling.average)
    return out, mask >= 0.999


def compare(first: str, second: str, gsd_m: float = 0.3, window_m: float = 60.0, min_response: float = 0.3) -> Comparison:
    """Measure ``second`` against ``first`` (paths of georeferenced orthophotos); see the module's docstring."""
    with rasterio.open(first) as ds:
        if ds.crs is None:
            raise ValueError(f"{first}: no CRS")
        step = gsd_m / abs(ds.transform.a)
        transform = ds.transform @ Affine.scale(step)
        shape = (int(ds.height / step), int(ds.width / step))
        crs = ds.crs
    a, valid_a = _grey_on_grid(first, transform, crs, shape)
    b, valid_b = _grey_on_grid(second, transform, crs, shape)
    win = int(round(window_m / gsd_m))
    hann = cv2.createHanningWindow((win, win), cv2.CV_32F)
    rows = []
    for r in range(0, shape[0] - win + 1, win // 2):
        for c in range(0, shape[1] - win + 1, win // 2):
            if not (valid_a[r:r + win, c:c + win].all() and valid_b[r:r + win, c:c + win].all()):
                continue
            pa, pb = a[r:r + win, c:c + win], b[r:r + win, c:c + win]
            pa = (pa - pa.mean()) / (pa.std() + 1e-6)
            pb = (pb - pb.mean()) / (pb.std() + 1e-6)
            (dx, dy), response = cv2.phaseCorrelate(pa, pb, hann)
            if response < min_response:
                continue
            x, y = transform @ (c + win / 2, r + win / 2)
            # Grid columns run east, rows south (a north-up orthophoto): a shift of dy rows is -dy * gsd north.
            rows.append((x, y, dx * gsd_m, -dy * gsd_m, response))
    if len(rows) < 3:
        raise ValueError(f"only {len(rows)} windows of {window_m:g} m correlate (response >= {min_response:g}): "
                         "do the orthophotos cover the same ground?")
    rows = np.array(rows)
    p = rows[:, :2] - rows[:, :2].mean(axis=0)
    X = np.column_stack([np.ones(len(p)), p])
    coef, *_ = np.linalg.lstsq(X, rows[:, 2:4], rcond=None)
    residual = rows[:, 2:4] - X @ coef
    return Comparison(p, rows[:, 2:4], rows[:, 4], coef[0], coef[1:].T, float(np.sqrt(np.mean(np.sum(residual**2, axis=1)))))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("first", help="the orthophoto you trust (GeoTIFF)")
    ap.add_argument("second", help="the one to measure against it (GeoTIFF, any CRS)")
    ap.add_argument("--gsd-m", type=float, default=0.3, help="compare at this many metres a pixel")
    ap.add_argument("--window-m", type=float, default=60.0, help="side of the windows correlated, m")
    ap.add_argument("--min-response", type=float, default=0.3, help="leave out windows whose correlation peak is lower")
    ap.add_argument("--windows", action="store_true", help="print every window's shift")
    a = ap.parse_args(argv)
    cmp = compare(a.first, a.second, a.gsd_m, a.window_m, a.min_response)
    if a.windows:
        for (e, n), (de, dn), resp in zip(cmp.p_en_m, cmp.shift_en_m, cmp.response):
            print(f"  window at {e:+7.1f} E {n:+7.1f} N: shifted {de:+.2f} E {dn:+.2f} N (response {resp:.2f})")
    size = np.hypot(*cmp.shift_en_m.T)
    print(f"{len(size)} windows of {a.window_m:g} m: shift {np.sqrt(np.mean(size**2)):.2f} m RMS, {size.max():.2f} m at most")
    print(f"fit: shift at their centre {cmp.t_en_m[0]:+.2f} E {cmp.t_en_m[1]:+.2f} N m, scale {cmp.scale:+.2%}, "
          f"turn {np.degrees(cmp.turn_rad):+.2f} deg; residual {cmp.residual_rms_m:.2f} m RMS")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
