"""A georeferenced orthophoto (or height model) read for map building, in any CRS (rasterio).

:class:`Orthophoto` reads windows resampled to a chosen ground sample distance (pixel averaging, never finer than
the file), with the file's coverage mask, and turns build pixels into geodetic positions: affine to the file's
CRS, then PROJ (``rasterio.warp.transform``) to WGS84. :class:`HeightModel` samples a DSM (metres, in the vertical
datum the user states for it) bilinearly at geodetic points.

Pixel convention (rasterio's affine): integer pixel coordinates are pixel corners, so the centre of the build
pixel (row 0, col 0) is at (0.5, 0.5). Build pixel (col, row) of a window starting at build pixel (col0, row0)
is at file pixel ``(col0 + col + 0.5) * k`` along columns, with ``k`` file pixels per build pixel.

Tags auxgps writes into the orthophotos it builds (``auxgps ortho build``) and reads back here:
``AUXGPS_GEOREF_SIGMA_H_M`` (the block's placement error, one sigma, m), ``AUXGPS_GROUND_ALT_AMSL_M`` (the
fitted ground plane's height under the orthophoto's centre, m above mean sea level) and ``AUXGPS_GROUND_SLOPE``
(that plane's rise northward and eastward, m per m, two numbers).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import rasterio
import rasterio.errors
import rasterio.warp
from rasterio.crs import CRS
from rasterio.enums import Resampling
from rasterio.windows import Window

from auxgps.core.geometry import LocalFrame
from auxgps.errors import MapError

_WGS84 = CRS.from_epsg(4326)
TAG_GEOREF_SIGMA = "AUXGPS_GEOREF_SIGMA_H_M"
TAG_GROUND_ALT = "AUXGPS_GROUND_ALT_AMSL_M"
TAG_GROUND_SLOPE = "AUXGPS_GROUND_SLOPE"


def _open(path: Path, what: str):
    if not path.is_file():
        raise MapError(f"{what}: no such file {path}")
    try:
        ds = rasterio.open(path)
    except rasterio.errors.RasterioIOError as err:
        raise MapError(f"{what}: cannot read {path} as a raster: {err}".replace("\n", " ")) from None
    if ds.crs is None or ds.transform.is_identity:
        ds.close()
        missing = "no CRS" if ds.crs is None else "no geotransform"
        raise MapError(f"{what}: {path} has {missing}: a georeferenced GeoTIFF is needed (gdal_edit.py -a_srs / -a_ullr, "
                       "or export it georeferenced)")
    if abs(ds.transform.b) > 1e-12 or abs(ds.transform.d) > 1e-12:
        ds.close()
        raise MapError(f"{what}: {path} is rotated in its CRS (a north-up grid is needed; gdalwarp it first)")
    return ds


class Orthophoto:
    """An orthophoto GeoTIFF (1, 3 or 4 bands of uint8) open for windowed reading. Errors are one :class:`MapError`."""

    def __init__(self, path: Path | str, what: str = "--orthophoto") -> None:
        self.path = Path(path)
        self.what = what
        ds = _open(self.path, what)
        if ds.count not in (1, 3, 4) or any(dt != "uint8" for dt in ds.dtypes):
            ds.close()
            raise MapError(f"{what}: {self.path} must have 1, 3 or 4 bands of uint8 (grey, RGB, RGBA); it has "
                           f"{ds.count} of {', '.join(sorted(set(ds.dtypes)))}")
        self._ds = ds
        self.crs: CRS = ds.crs
        self.transform = ds.transform
        self.width_px, self.height_px = ds.width, ds.height
        self.bands = [1, 1, 1] if ds.count == 1 else [3, 2, 1]  # read as BGR
        self.tags = ds.tags()
        lat, lon = self.geodetic_of_xy(*self.xy_of_colrow(np.array([ds.width / 2]), np.array([ds.height / 2])))
        self.centre_lat_deg, self.centre_lon_deg = float(lat[0]), float(lon[0])
        step_col, step_row = self.pixel_steps_ne_m(ds.width / 2, ds.height / 2)
        gx, gy = float(np.linalg.norm(step_col)), float(np.linalg.norm(step_row))
        if not (gx > 0 and gy > 0 and abs(gx - gy) <= 0.02 * max(gx, gy)):
            raise MapError(f"{what}: {self.path} has pixels of {gx:.4f} x {gy:.4f} m on the ground: square pixels are "
                           "needed (gdalwarp it to a conformal projection such as UTM first)")
        self.gsd_m = float(0.5 * (gx + gy))

    def pixel_steps_ne_m(self, col: float, row: float) -> tuple[np.ndarray, np.ndarray]:
        """North/east (m) of one file pixel step along columns and along rows at file pixel (col, row): the
        ground size and direction of the grid there, whatever the CRS (true north and grid north differ by the
        projection's convergence)."""
        x, y = self.xy_of_colrow(np.array([col, col + 1.0, col]), np.array([row, row, row + 1.0]))
        lat, lon = self.geodetic_of_xy(x, y)
        frame = LocalFrame(float(lat[0]), float(lon[0]), 0.0)
        ne = frame.to_ned(lat_deg=lat, lon_deg=lon, alt_amsl_m=np.zeros(3))[:, :2]
        return ne[1] - ne[0], ne[2] - ne[0]

    def close(self) -> None:
        self._ds.close()

    def tag_float(self, name: str, count: int = 1):
        """A numeric tag (``count`` numbers: a tuple), None when the file lacks it."""
        v = self.tags.get(name)
        if v is None:
            return None
        try:
            nums = tuple(float(x) for x in v.split())
        except ValueError:
            nums = ()
        if len(nums) != count or not all(np.isfinite(nums)):
            raise MapError(f"{self.what}: {self.path}: tag {name}={v!r} is not {count} number{'s' if count > 1 else ''}")
        return nums[0] if count == 1 else nums

    # -- coordinates --------------------------------------------------------------------------------------

    def xy_of_colrow(self, col: np.ndarray, row: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """File pixel coordinates (affine convention) -> CRS coordinates."""
        t = self.transform
        col, row = np.asarray(col, float), np.asarray(row, float)
        return t.a * col + t.b * row + t.c, t.d * col + t.e * row + t.f

    def geodetic_of_xy(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """CRS coordinates -> (lat_deg, lon_deg)."""
        if len(np.ravel(x)) == 0:
            return np.zeros(0), np.zeros(0)
        lon, lat = rasterio.warp.transform(self.crs, _WGS84, np.ravel(x), np.ravel(y))
        return np.reshape(lat, np.shape(x)), np.reshape(lon, np.shape(x))

    # -- reading ------------------------------------------------------------------------------------------

    def build_size_px(self, factor: float) -> tuple[int, int]:
        """Width and height of the whole orthophoto at ``factor`` file pixels per build pixel (whole pixels)."""
        return int(np.floor(self.width_px / factor)), int(np.floor(self.height_px / factor))

    def read(self, col0: int, row0: int, w: int, h: int, factor: float) -> tuple[np.ndarray, np.ndarray]:
        """Build pixels [row0, row0 + h) x [col0, col0 + w) at ``factor`` (>= 1) file pixels each: (h, w, 3) BGR
        uint8 (area-averaged) and (h, w) bool, True where the file covers the ground. Outside the file (and a
        last build pixel only partly on it): not covered."""
        img = np.zeros((h, w, 3), np.uint8)
        valid = np.zeros((h, w), bool)
        W, H = int(np.floor(self.width_px / factor)), int(np.floor(self.height_px / factor))
        c_lo, c_hi, r_lo, r_hi = max(col0, 0), min(col0 + w, W), max(row0, 0), min(row0 + h, H)
        if c_hi <= c_lo or r_hi <= r_lo:
            return img, valid
        win = Window(c_lo * factor, r_lo * factor, (c_hi - c_lo) * factor, (r_hi - r_lo) * factor)
        shape = (r_hi - r_lo, c_hi - c_lo)
        # (Not boundless: rasterio's boundless reads give no mask.)
        data = self._ds.read(self.bands, window=win, out_shape=(3, *shape), resampling=Resampling.average)
        mask = self._ds.read_masks(1, window=win, out_shape=shape, resampling=Resampling.average)
        img[r_lo - row0 : r_hi - row0, c_lo - col0 : c_hi - col0] = np.moveaxis(data, 0, -1)
        valid[r_lo - row0 : r_hi - row0, c_lo - col0 : c_hi - col0] = mask >= 255
        return img, valid

    def geodetic_of_build_px(self, col0: int, row0: int, uv_px: np.ndarray, factor: float) -> tuple[np.ndarray, np.ndarray]:
        """(N, 2) build-pixel positions (OpenCV convention: integers are pixel centres) of the window at (col0,
        row0) -> (lat_deg, lon_deg)."""
        col = (col0 + uv_px[:, 0] + 0.5) * factor
        row = (row0 + uv_px[:, 1] + 0.5) * factor
        return self.geodetic_of_xy(*self.xy_of_colrow(col, row))


class HeightModel:
    """A DSM GeoTIFF (band 1, metres above mean sea level), sampled bilinearly; NaN off the raster or at no-data."""

    def __init__(self, path: Path | str, what: str = "--dsm") -> None:
        self.path = Path(path)
        self.what = what
        ds = _open(self.path, what)
        self._ds = ds
        self.nodata = ds.nodata

    def close(self) -> None:
        self._ds.close()

    def alt_amsl_m(self, lat_deg: np.ndarray, lon_deg: np.ndarray) -> np.ndarray:
        ds = self._ds
        lat_deg, lon_deg = np.ravel(lat_deg), np.ravel(lon_deg)
        out = np.full(len(lat_deg), np.nan)
        if not len(lat_deg):
            return out
        x, y = rasterio.warp.transform(_WGS84, ds.crs, lon_deg, lat_deg)
        inv = ~ds.transform
        col = inv.a * np.asarray(x) + inv.b * np.asarray(y) + inv.c - 0.5
        row = inv.d * np.asarray(x) + inv.e * np.asarray(y) + inv.f - 0.5
        c0, r0 = int(np.floor(np.nanmin(col))), int(np.floor(np.nanmin(row)))
        c1, r1 = int(np.floor(np.nanmax(col))) + 2, int(np.floor(np.nanmax(row))) + 2
        data = ds.read(1, window=Window(c0, r0, c1 - c0, r1 - r0), boundless=True, fill_value=np.nan, masked=True)
        z = np.asarray(data.filled(np.nan), float)
        if self.nodata is not None:
            z[z == self.nodata] = np.nan
        fc, fr = col - c0, row - r0
        i0, j0 = np.floor(fr).astype(int), np.floor(fc).astype(int)
        ok = (i0 >= 0) & (j0 >= 0) & (i0 + 1 < z.shape[0]) & (j0 + 1 < z.shape[1])
        i0, j0, a, b = i0[ok], j0[ok], (fc - np.floor(fc))[ok], (fr - np.floor(fr))[ok]
        out[ok] = ((z[i0, j0] * (1 - a) + z[i0, j0 + 1] * a) * (1 - b) + (z[i0 + 1, j0] * (1 - a) + z[i0 + 1, j0 + 1] * a) * b)
        return out
