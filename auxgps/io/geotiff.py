"""GeoTIFFs written: an RGB orthophoto with its CRS, a nodata mask and overviews (rasterio, GDAL's GTiff driver).

The file is tiled (256 px blocks, DEFLATE), its mask internal (GDAL_TIFF_INTERNAL_MASK: 0 where no photo saw
the ground), and its overviews averaged by powers of two down to one block. It is written beside its final
path and renamed into place, so an interrupted build leaves no half file under that name.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Iterable

import numpy as np
import rasterio
from rasterio.crs import CRS
from rasterio.enums import Resampling
from rasterio.windows import Window

BLOCK_PX = 256


def utm_crs(lat_deg: float, lon_deg: float) -> CRS:
    """The WGS84 UTM zone holding a point (EPSG 326xx north, 327xx south)."""
    zone = int((lon_deg + 180.0) // 6.0) % 60 + 1
    return CRS.from_epsg((32600 if lat_deg >= 0 else 32700) + zone)


def overview_factors(width_px: int, height_px: int, block_px: int = BLOCK_PX) -> list[int]:
    """2, 4, 8, ... while the overview is still larger than one block."""
    out, f = [], 2
    while max(width_px, height_px) / f >= block_px:
        out.append(f)
        f *= 2
    return out


def write_rgb_geotiff(path: Path | str, crs: CRS, transform: rasterio.Affine, width_px: int, height_px: int,
                      tiles: Iterable[tuple[int, int, np.ndarray, np.ndarray]], tags: dict | None = None) -> Path:
    """Write ``tiles`` (row0, col0, (h, w, 3) uint8 RGB, (h, w) bool seen) into a new GeoTIFF at ``path``, with
    these dataset ``tags`` (GDAL metadata)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".part")
    profile = dict(driver="GTiff", width=width_px, height=height_px, count=3, dtype="uint8", crs=crs, transform=transform,
                   tiled=True, blockxsize=BLOCK_PX, blockysize=BLOCK_PX, compress="deflate", predictor=2,
                   photometric="RGB", interleave="pixel", BIGTIFF="IF_SAFER")
    try:
        with rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True):
            with rasterio.open(tmp, "w", **profile) as dst:
                for row0, col0, rgb, seen in tiles:
                    h, w = seen.shape
                    win = Window(col0, row0, w, h)
                    dst.write(np.moveaxis(rgb, -1, 0), window=win)
                    dst.write_mask(np.where(seen, 255, 0).astype(np.uint8), window=win)
            with rasterio.open(tmp, "r+") as dst:
                dst.build_overviews(overview_factors(width_px, height_px), Resampling.average)
                dst.update_tags(ns="rio_overview", resampling="average")
                if tags:
                    dst.update_tags(**{k: str(v) for k, v in tags.items()})
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path
