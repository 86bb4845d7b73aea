"""Georeferenced rasters for simulated worlds: an orthophoto or a height model (DSM) GeoTIFF, in any CRS.

I/O at the edge, for the simulator's renderer (prior maps read their orthophotos through auxgps/io/orthophoto.py): rasterio opens the file and its overview levels, reads windows of them in aligned
blocks kept in a small cache (a flight over a large raster does not read the file again for every frame), and
turns map coordinates into pixel coordinates with each level's own affine transform. Points of the world's
local NED frame reach the raster's CRS through pymap3d (NED -> WGS84 geodetic) and rasterio.warp.transform
(WGS84 -> the raster's CRS, by PROJ).

Pixel convention: an affine transform maps a pixel's upper-left corner; ``colrow_px`` here are the affine's
pixel coordinates, so the centre of pixel (row 0, col 0) is at (0.5, 0.5). Subtract 0.5 for OpenCV's remap,
where integers are pixel centres.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rasterio
import rasterio.errors
import rasterio.warp
from rasterio.crs import CRS
from rasterio.windows import Window

from auxgps.core.geometry import LocalFrame
from auxgps.errors import ConfigError

_WGS84 = CRS.from_epsg(4326)


@dataclass(frozen=True)
class RasterLevel:
    """One resolution of a raster: the full one (``factor`` 1) or an overview. ``transform`` maps this level's
    pixel coordinates to the CRS; ``factor`` is full-resolution pixels per level pixel (along columns)."""

    index: int  # -1 the full resolution, else the GDAL overview level
    width_px: int
    height_px: int
    transform: rasterio.Affine
    factor: float


class GeoRaster:
    """A GeoTIFF opened for windowed reading at any of its levels, with a cache of recently read blocks.

    Parameters
    ----------
    path : the GeoTIFF
    what : how errors name it (``"world.yaml: ground.orthophoto"``)
    kind : ``"orthophoto"`` (1, 3 or 4 bands of uint8, RGB(A); read as BGR) or ``"dsm"`` (band 1, heights in
        metres, read as float32 with no-data as NaN)
    block_px : side of the cached blocks, level pixels
    cache_blocks : how many blocks the cache holds (least recently used dropped first)
    fill_bgr : an orthophoto's pixels under its no-data mask (its mask band, alpha or nodata value) read as this
        colour; None: as the file holds them (often black)
    """

    def __init__(self, path: Path | str, what: str, kind: str, block_px: int = 256, cache_blocks: int = 192,
                 fill_bgr: tuple[int, int, int] | None = None) -> None:
        self.path = Path(path)
        self.fill_bgr = fill_bgr
        self.what = what
        self.kind = kind
        self.block_px = int(block_px)
        self.cache_blocks = int(cache_blocks)
        if not self.path.is_file():
            raise ConfigError(f"{what}: no such file {self.path}")
        try:
            ds = rasterio.open(self.path)
        except rasterio.errors.RasterioIOError as err:
            raise ConfigError(f"{what}: cannot read {self.path} as a raster: {err}".replace("\n", " ")) from None
        with ds:
            if ds.crs is None:
                raise ConfigError(f"{what}: {self.path} has no CRS (a georeferenced GeoTIFF is needed)")
            if ds.transform.is_identity:
                raise ConfigError(f"{what}: {self.path} has no geotransform (a georeferenced GeoTIFF is needed)")
            if kind == "orthophoto":
                if ds.count not in (1, 3, 4) or any(dt != "uint8" for dt in ds.dtypes):
                    raise ConfigError(f"{what}: {self.path} must have 1, 3 or 4 bands of uint8 (grey, RGB, RGBA); "
                                      f"it has {ds.count} of {', '.join(sorted(set(ds.dtypes)))}")
                self.bands = [1, 1, 1] if ds.count == 1 else [3, 2, 1]  # BGR
            elif kind == "dsm":
                self.bands = [1]
            else:
                raise ValueError(f"unknown raster kind {kind!r}")
            self.crs = ds.crs
            self.nodata = ds.nodata
            self.bounds = ds.bounds
            levels = [RasterLevel(-1, ds.width, ds.height, ds.transform, 1.0)]
            n_overviews = len(ds.overviews(1))
            full_width = ds.width
        for i in range(n_overviews):
            with rasterio.open(self.path, overview_level=i) as ov:
                levels.append(RasterLevel(i, ov.width, ov.height, ov.transform, full_width / ov.width))
        self.levels: tuple[RasterLevel, ...] = tuple(levels)
        self._datasets: dict[int, rasterio.io.DatasetReader] = {}
        self._cache: OrderedDict = OrderedDict()
        self.reads = 0  # blocks read from the file (a cache miss each)

    # -- pickling: a world may be sent to a worker process; the file is opened again there -----------------

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_datasets"], state["_cache"] = {}, OrderedDict()
        return state

    # -- coordinates --------------------------------------------------------------------------------------

    def crs_from_ned(self, frame: LocalFrame, p_ned_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(..., 3) NED points, m -> their map coordinates x, y in the raster's CRS and their WGS84 height, m
        (each of shape (...)). Horizontal only: a map coordinate names the point's geodetic latitude and
        longitude, whatever its height."""
        p = np.asarray(p_ned_m, float)
        lat_deg, lon_deg, alt_m = frame.to_geodetic(p.reshape(-1, 3))
        x, y = rasterio.warp.transform(_WGS84, self.crs, np.ravel(lon_deg), np.ravel(lat_deg))
        shape = p.shape[:-1]
        return np.reshape(x, shape), np.reshape(y, shape), np.reshape(alt_m, shape)

    @staticmethod
    def colrow(level: RasterLevel, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Map coordinates -> the level's pixel coordinates (col, row), affine convention (pixel centres at .5)."""
        inv = ~level.transform
        x, y = np.asarray(x, float), np.asarray(y, float)
        return inv.a * x + inv.b * y + inv.c, inv.d * x + inv.e * y + inv.f

    def contains(self, x: float, y: float) -> bool:
        """Whether the map point (x, y) lies on the raster."""
        col, row = self.colrow(self.levels[0], x, y)
        return bool(0.0 <= col <= self.levels[0].width_px and 0.0 <= row <= self.levels[0].height_px)

    def level_for(self, full_px_per_out_px: float, window_px: float | None = None, max_window_px: float = 4096.0) -> RasterLevel:
        """The coarsest level still at least as fine as the output: its factor at most ``full_px_per_out_px``
        (full-resolution pixels per output pixel). ``window_px``: the side of the region needed at full
        resolution; a level whose window would exceed ``max_window_px`` is passed over for a coarser one."""
        chosen = self.levels[0]
        for lv in self.levels:
            if lv.factor <= full_px_per_out_px * (1.0 + 1e-6):
                chosen = lv
        if window_px is not None:
            for lv in self.levels:
                if lv.factor >= chosen.factor and window_px / lv.factor <= max_window_px:
                    return lv
            return self.levels[-1]
        return chosen

    # -- reading ------------------------------------------------------------------------------------------

    def _dataset(self, level: RasterLevel):
        ds = self._datasets.get(level.index)
        if ds is None:
            kw = {} if level.index < 0 else {"overview_level": level.index}
            ds = self._datasets[level.index] = rasterio.open(self.path, **kw)
        return ds

    def _block(self, level: RasterLevel, bi: int, bj: int) -> np.ndarray:
        key = (level.index, bi, bj)
        block = self._cache.get(key)
        if block is not None:
            self._cache.move_to_end(key)
            return block
        b = self.block_px
        r0, c0 = bi * b, bj * b
        win = Window(c0, r0, min(b, level.width_px - c0), min(b, level.height_px - r0))
        ds = self._dataset(level)
        if self.kind == "orthophoto":
            block = np.ascontiguousarray(np.moveaxis(ds.read(self.bands, window=win), 0, -1))
            if self.fill_bgr is not None:
                block[ds.read_masks(1, window=win) == 0] = self.fill_bgr
        else:
            data = ds.read(1, window=win, masked=True)
            block = np.ma.filled(data.astype(np.float32), np.nan)
        self.reads += 1
        self._cache[key] = block
        while len(self._cache) > self.cache_blocks:
            self._cache.popitem(last=False)
        return block

    def read(self, level: RasterLevel, row0: int, row1: int, col0: int, col1: int) -> np.ndarray:
        """Rows ``row0:row1`` and columns ``col0:col1`` of ``level`` (inside it), assembled from cached blocks:
        (h, w, 3) uint8 BGR for an orthophoto, (h, w) float32 heights (NaN: no data) for a DSM."""
        h, w = row1 - row0, col1 - col0
        shape = (h, w, 3) if self.kind == "orthophoto" else (h, w)
        out = np.empty(shape, np.uint8 if self.kind == "orthophoto" else np.float32)
        b = self.block_px
        for bi in range(row0 // b, (row1 - 1) // b + 1):
            for bj in range(col0 // b, (col1 - 1) // b + 1):
                block = self._block(level, bi, bj)
                r_a, r_b = max(row0, bi * b), min(row1, bi * b + block.shape[0])
                c_a, c_b = max(col0, bj * b), min(col1, bj * b + block.shape[1])
                out[r_a - row0 : r_b - row0, c_a - col0 : c_b - col0] = block[r_a - bi * b : r_b - bi * b, c_a - bj * b : c_b - bj * b]
        return out

    def heights_range_m(self) -> tuple[float, float]:
        """(lowest, highest) value of a DSM, m, from its coarsest level (no-data ignored)."""
        lv = self.levels[-1]
        data = self._dataset(lv).read(1, masked=True)
        if data.count() == 0:
            raise ConfigError(f"{self.what}: {self.path} holds no heights (all no-data)")
        return float(data.min()), float(data.max())

    def sample(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Bilinear values of band 1 (a DSM) at map points, at full resolution; NaN off the raster or at
        no-data. For a few points (the cubes' bases), not per frame."""
        lv = self.levels[0]
        col, row = self.colrow(lv, x, y)
        fc, fr = np.asarray(col, float) - 0.5, np.asarray(row, float) - 0.5
        out = np.full(np.shape(fc), np.nan)
        for k in np.ndindex(np.shape(fc)):
            c0, r0 = int(np.floor(fc[k])), int(np.floor(fr[k]))
            if c0 < 0 or r0 < 0 or c0 + 1 >= lv.width_px or r0 + 1 >= lv.height_px:
                c0, r0 = min(max(c0, 0), lv.width_px - 1), min(max(r0, 0), lv.height_px - 1)
                if not (0 <= fc[k] + 0.5 <= lv.width_px and 0 <= fr[k] + 0.5 <= lv.height_px):
                    continue
                out[k] = self.read(lv, r0, r0 + 1, c0, c0 + 1)[0, 0]
                continue
            patch = self.read(lv, r0, r0 + 2, c0, c0 + 2).astype(float)
            a, b = fc[k] - c0, fr[k] - r0
            out[k] = (patch[0, 0] * (1 - a) + patch[0, 1] * a) * (1 - b) + (patch[1, 0] * (1 - a) + patch[1, 1] * a) * b
        return out
