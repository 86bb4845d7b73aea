"""The ground of an orthophoto world as a camera sees it: the orthophoto reprojected into the view, flat or over
a height model (DSM), with the depth of the ground behind every pixel.

Flat ground (the plane ``down = 0``): on a lattice of nodes every :data:`NODE_STEP` output pixels, each node's
ray meets the plane at an exact NED point, which pymap3d and rasterio.warp.transform take to the raster's CRS
and the level's affine to a pixel of the orthophoto; the map is interpolated bilinearly to every pixel (exact
for an affine map: the reprojection over one lattice cell is affine to far below a pixel) and the window of the
orthophoto in view, read at the overview level that matches the frame's ground sample distance, is remapped.

Relief: the DSM is resampled, the same way, onto a regular north-east grid over the view's footprint, as the
down of the surface; each pixel's ray is marched down through the grid's height range in steps no longer than
one grid cell horizontally and its first crossing refined (Illinois regula falsi) to the z-depth where it meets
the surface. The colour is the orthophoto at that point's north and east (an affine fit of the reprojection
over the footprint plus its residual, interpolated from the grid's nodes). The surface is the bilinear
interpolant of the grid, which is never coarser than the DSM.
"""

from __future__ import annotations

import cv2
import numpy as np

from auxgps.core.camera import CameraPose, PinholeCamera
from auxgps.core.lattice import node_axis, upsample
from auxgps.io.georaster import GeoRaster, RasterLevel

#: Output pixels (or grid cells) between the nodes where the reprojection is computed exactly.
NODE_STEP = 16
#: Most grid cells along a side of the relief grid (its spacing grows beyond).
MAX_GRID_PX = 2048
#: Steps of the ray march at most, and refinement iterations after it.
MAX_MARCH_STEPS = 256
REFINE_ITERATIONS = 6
#: Colour of the ground off the orthophoto and under its no-data mask (BGR): featureless mid grey. A camera sees
#: ground beyond a survey, not a covered lens: black there made the frame check refuse frames half on the world
#: (over Seneca, the far end of the out-and-back) as "lens covered", which a flight would have located from.
OFF_RASTER_BGR = (96, 96, 96)


def _cell_m(raster: GeoRaster, frame) -> float:
    """Side of a full-resolution pixel at the world origin, m (the mean of its two axes)."""
    p = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    x, y, _ = raster.crs_from_ned(frame, p)
    col, row = raster.colrow(raster.levels[0], x, y)
    J = np.array([[col[1] - col[0], col[2] - col[0]], [row[1] - row[0], row[2] - row[0]]])  # px per m
    return float(1.0 / np.sqrt(abs(np.linalg.det(J))))


class GeoGround:
    """The orthophoto (and DSM) ground of one world through one camera. Build once; per frame call
    :meth:`flat_image` (no DSM) or :meth:`relief`."""

    def __init__(self, world, camera: PinholeCamera, xn: np.ndarray, yn: np.ndarray) -> None:
        self.world = world
        self.frame = world.frame
        self.ortho: GeoRaster = world.ground_orthophoto
        self.dsm: GeoRaster | None = world.ground_dsm
        self.camera = camera
        self._xn, self._yn = xn, yn  # (W,), (H,) float32 normalised image coordinates of the ideal pixels
        W, H = camera.width_px, camera.height_px
        K = camera.K
        uu, vv = node_axis(W, NODE_STEP), node_axis(H, NODE_STEP)
        self._node_xy = np.stack(np.meshgrid((uu - K[0, 2]) / K[0, 0], (vv - K[1, 2]) / K[1, 1]), axis=-1)  # (gh, gw, 2)
        self._ortho_cell_m = _cell_m(self.ortho, self.frame)
        if self.dsm is not None:
            h_lo, h_hi = self.dsm.heights_range_m()
            alt = self.frame.alt_amsl_m
            slack = 1.0 + 0.05 * (h_hi - h_lo)  # the coarsest level's range, widened: a peak it averaged away
            self._down_range_m = (min(alt - h_hi, 0.0) - slack, max(alt - h_lo, 0.0) + slack)
            self._dsm_cell_m = _cell_m(self.dsm, self.frame)

    # -- shared -------------------------------------------------------------------------------------------

    def _read_window(self, raster: GeoRaster, level: RasterLevel, col: np.ndarray, row: np.ndarray):
        """The part of ``level`` under the finite pixel coordinates ``col``, ``row`` (affine convention), with a
        margin for bilinear interpolation: (array, col0, row0), or None when none is on the raster."""
        ok = np.isfinite(col) & np.isfinite(row)
        if not ok.any():
            return None
        c0 = max(int(np.floor(col[ok].min())) - 2, 0)
        r0 = max(int(np.floor(row[ok].min())) - 2, 0)
        c1 = min(int(np.ceil(col[ok].max())) + 2, level.width_px)
        r1 = min(int(np.ceil(row[ok].max())) + 2, level.height_px)
        if c1 <= c0 or r1 <= r0:
            return None
        return raster.read(level, r0, r1, c0, c1), c0, r0

    def _level(self, raster: GeoRaster, full_px_per_out_px: float, col_full: np.ndarray, row_full: np.ndarray) -> RasterLevel:
        ok = np.isfinite(col_full) & np.isfinite(row_full)
        lv0 = raster.levels[0]
        if ok.any():
            span_px = max(np.ptp(np.clip(col_full[ok], 0, lv0.width_px)), np.ptp(np.clip(row_full[ok], 0, lv0.height_px)))
        else:
            span_px = 0.0
        return raster.level_for(full_px_per_out_px, span_px)

    # -- flat ---------------------------------------------------------------------------------------------

    def flat_image(self, pose: CameraPose) -> np.ndarray:
        """(H, W, 3) uint8: the orthophoto on the plane ``down = 0`` seen from ``pose`` (ideal pixels)."""
        W, H = self.camera.width_px, self.camera.height_px
        c = pose.p_cam_in_ned_m
        xy = self._node_xy
        rays = xy[..., 0:1] * pose.R_ned_cam[:, 0] + xy[..., 1:2] * pose.R_ned_cam[:, 1] + pose.R_ned_cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -c[2] / rays[..., 2]
        hit = np.isfinite(t) & (t > 0)
        p_ned = c + np.where(hit, t, 0.0)[..., None] * rays
        p_ned[..., 2] = 0.0
        x, y, _ = self.ortho.crs_from_ned(self.frame, p_ned)
        lv0 = self.ortho.levels[0]
        col, row = self.ortho.colrow(lv0, x, y)
        col[~hit], row[~hit] = np.nan, np.nan
        # Full-resolution raster pixels per output pixel, at the finest part of the view (the nearest ground).
        dc = np.hypot(np.diff(col, axis=1), np.diff(row, axis=1)) / NODE_STEP
        dr = np.hypot(np.diff(col, axis=0), np.diff(row, axis=0)) / NODE_STEP
        scale = np.nanmin(np.concatenate([dc.ravel(), dr.ravel(), [np.inf]]))
        level = self._level(self.ortho, scale if np.isfinite(scale) else 1.0, col, row)
        if level is not lv0:
            col, row = self.ortho.colrow(level, x, y)
            col[~hit], row[~hit] = np.nan, np.nan
        window = self._read_window(self.ortho, level, col, row)
        if window is None:
            return np.full((H, W, 3), OFF_RASTER_BGR, np.uint8)
        img, c0, r0 = window
        nodes = np.stack([col - 0.5 - c0, row - 0.5 - r0], axis=-1)
        nodes[~hit] = -1e6  # off the image: the border colour
        m = upsample(nodes.astype(np.float32), H, W, NODE_STEP)
        out = cv2.remap(img, m[..., 0], m[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=OFF_RASTER_BGR)
        return out

    # -- relief -------------------------------------------------------------------------------------------

    def relief(self, pose: CameraPose) -> tuple[np.ndarray, np.ndarray]:
        """The orthophoto over the DSM seen from ``pose``: (H, W, 3) uint8 ideal image and (H, W) float32
        z-depth of the surface behind every pixel, m (inf where a ray meets no ground)."""
        W, H = self.camera.width_px, self.camera.height_px
        c = pose.p_cam_in_ned_m.astype(float)
        R = pose.R_ned_cam
        fx = float(self.camera.K[0, 0])
        d_top, d_bot = self._down_range_m
        # The footprint: where the node rays cross the highest and the lowest possible surface.
        xy = self._node_xy
        rays = xy[..., 0:1] * R[:, 0] + xy[..., 1:2] * R[:, 1] + R[:, 2]
        height_m = max(d_bot - c[2], 0.1)
        max_range_m = max(200.0, 20.0 * height_m)  # beyond, toward the horizon, no ground is drawn
        with np.errstate(divide="ignore", invalid="ignore"):
            t_hi = np.where(rays[..., 2] > 1e-9, (d_bot - c[2]) / rays[..., 2], np.inf)
        t_hi = np.minimum(t_hi, max_range_m / np.maximum(np.linalg.norm(rays[..., :2], axis=-1), 1e-9))
        t_lo = np.clip(np.where(rays[..., 2] > 1e-9, (d_top - c[2]) / rays[..., 2], 0.0), 0.0, t_hi)
        ne = np.concatenate([(c + t_lo[..., None] * rays)[..., :2].reshape(-1, 2), (c + t_hi[..., None] * rays)[..., :2].reshape(-1, 2), [c[:2]]])
        n_lo, e_lo = ne.min(axis=0)
        n_hi, e_hi = ne.max(axis=0)

        # The DSM level and the grid spacing: as fine as the DSM level, which is as fine as the nearest ground.
        gsd_m = max(d_top - c[2], 0.05) / fx
        span_m = max(n_hi - n_lo, e_hi - e_lo)
        level = self.dsm.level_for(gsd_m / self._dsm_cell_m, span_m / self._dsm_cell_m)
        s = max(self._dsm_cell_m * level.factor, span_m / (MAX_GRID_PX - 1))
        n0, e0 = n_hi + s, e_lo - s
        gw, gh = int(np.ceil((e_hi - e_lo) / s)) + 3, int(np.ceil((n_hi - n_lo) / s)) + 3
        down_grid, ortho_nodes = self._surface_grid(level, n0, e0, s, gh, gw)
        d_top_f, d_bot_f = float(down_grid.min()), float(down_grid.max())

        # Per-pixel rays (NED, with unit z in the camera: the ray parameter is the z-depth).
        xn, yn = self._xn[None, :], self._yn[:, None]
        rn = (R[0, 0] * xn + R[0, 1] * yn + R[0, 2]).astype(np.float32)
        re = (R[1, 0] * xn + R[1, 1] * yn + R[1, 2]).astype(np.float32)
        rd = (R[2, 0] * xn + R[2, 1] * yn + R[2, 2]).astype(np.float32)
        down_ok = rd > 1e-6
        with np.errstate(divide="ignore", invalid="ignore"):
            inv_rd = np.where(down_ok, 1.0 / rd, 0.0).astype(np.float32)
        t_a = np.maximum((np.float32(d_top_f - c[2]) - 0.01) * inv_rd, np.float32(1e-3))
        t_b = np.maximum((np.float32(d_bot_f - c[2]) + 0.01) * inv_rd, t_a)
        r_ne = np.hypot(rn, re)
        t_b = np.minimum(t_b, np.float32(max_range_m) / np.maximum(r_ne, np.float32(1e-9)))
        t_a = np.minimum(t_a, t_b)
        ax, bx = re / np.float32(s), np.float32((c[1] - e0) / s)
        ay, by = -rn / np.float32(s), np.float32((n0 - c[0]) / s)
        cd = np.float32(c[2])

        def below(t):  # how far below the surface the ray's point at depth t is, m (>= 0: at or under it)
            surf = cv2.remap(down_grid, bx + t * ax, by + t * ay, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            return cd + t * rd - surf

        n_steps = int(np.clip(np.ceil(float(((t_b - t_a) * r_ne)[down_ok].max(initial=0.0)) / s), 1, MAX_MARCH_STEPS))
        lo, f_lo = t_a, below(t_a)
        found = f_lo >= 0  # the camera at or under the surface along this ray (not for a flying camera)
        hi, f_hi = t_a.copy(), f_lo.copy()
        t_prev, f_prev = t_a, f_lo
        for k in range(1, n_steps + 1):
            t = t_a + (t_b - t_a) * np.float32(k / n_steps)
            f = below(t)
            new = ~found & (f >= 0)
            if new.any():
                lo, f_lo = np.where(new, t_prev, lo), np.where(new, f_prev, f_lo)
                hi, f_hi = np.where(new, t, hi), np.where(new, f, f_hi)
                found |= new
            t_prev, f_prev = t, f
        found &= down_ok
        # Illinois regula falsi on [lo, hi]: f_lo < 0 <= f_hi.
        side = np.zeros(lo.shape, np.int8)
        for _ in range(REFINE_ITERATIONS):
            with np.errstate(divide="ignore", invalid="ignore"):
                t = np.where(f_hi - f_lo > 0, lo - f_lo * (hi - lo) / (f_hi - f_lo), hi)
            f = below(t)
            under = f >= 0
            hi, f_lo_new = np.where(under, t, hi), np.where(under & (side == 1), f_lo * 0.5, f_lo)
            f_hi_new = np.where(~under & (side == -1), f_hi * 0.5, f_hi)
            f_hi = np.where(under, f, f_hi_new)
            lo, f_lo = np.where(under, lo, t), np.where(under, f_lo_new, f)
            side = np.where(under, 1, -1).astype(np.int8)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(f_hi - f_lo > 0, lo - f_lo * (hi - lo) / (f_hi - f_lo), hi)
        depth = np.where(found, t, np.float32(np.inf)).astype(np.float32)

        # Colour: the orthophoto at each hit's north and east.
        gx, gy = bx + t * ax, by + t * ay  # grid coordinates of the hits
        image = self._ortho_at_grid(ortho_nodes, gx, gy, found, gsd_m, H, W)
        return image, depth

    def _surface_grid(self, level: RasterLevel, n0: float, e0: float, s: float, gh: int, gw: int):
        """The surface's down on the grid of ``gh`` x ``gw`` cells of ``s`` m whose cell (0, 0) is centred at
        (n0, e0), north up: (gh, gw) float32, m. Also the grid's nodes, for the colour: their NED points
        (gh', gw', 3) and grid coordinates along columns and rows."""
        alt = self.frame.alt_amsl_m
        uu, vv = node_axis(gw, NODE_STEP), node_axis(gh, NODE_STEP)
        e_nodes, n_nodes = np.meshgrid(e0 + s * uu, n0 - s * vv)
        p_nodes = np.stack([n_nodes, e_nodes, np.zeros_like(n_nodes)], axis=-1)
        x, y, h0 = self.dsm.crs_from_ned(self.frame, p_nodes)
        col, row = self.dsm.colrow(level, x, y)
        window = self._read_window(self.dsm, level, col, row)
        nodes = np.stack([col - 0.5, row - 0.5, h0 - alt], axis=-1)
        if window is None:
            heights = np.zeros((gh, gw), np.float32)
            up = upsample(nodes[..., 2].astype(np.float32), gh, gw, NODE_STEP)
            return up - heights, (p_nodes, uu, vv)
        data, c0, r0 = window
        data = np.where(np.isfinite(data), data - np.float32(alt), np.float32(0.0)).astype(np.float32)
        nodes[..., 0] -= c0
        nodes[..., 1] -= r0
        up = upsample(nodes.astype(np.float32), gh, gw, NODE_STEP)
        heights = cv2.remap(data, up[..., 0], up[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
        return np.ascontiguousarray(up[..., 2] - heights), (p_nodes, uu, vv)

    def _ortho_at_grid(self, nodes, gx: np.ndarray, gy: np.ndarray, found: np.ndarray, gsd_m: float, H: int, W: int) -> np.ndarray:
        """The orthophoto at the points of grid coordinates ``gx``, ``gy`` (H, W) (the grid of
        :meth:`_surface_grid`, whose ``nodes`` it gave); off-raster colour where not ``found``."""
        p_nodes, uu, vv = nodes
        x, y, _ = self.ortho.crs_from_ned(self.frame, p_nodes)
        lv0 = self.ortho.levels[0]
        col_full, row_full = self.ortho.colrow(lv0, x, y)
        level = self._level(self.ortho, gsd_m / self._ortho_cell_m, col_full, row_full)
        col, row = self.ortho.colrow(level, x, y)
        # An affine fit of grid coordinates -> level pixel coordinates, and its residual at the nodes.
        gh, gw = p_nodes.shape[:2]
        gu, gv = np.meshgrid(uu, vv)
        A = np.column_stack([gu.ravel(), gv.ravel(), np.ones(gu.size)])
        coef, *_ = np.linalg.lstsq(A, np.column_stack([col.ravel(), row.ravel()]), rcond=None)
        resid = (np.column_stack([col.ravel(), row.ravel()]) - A @ coef).reshape(gh, gw, 2).astype(np.float32)
        col_px = (coef[0, 0] * gx + coef[1, 0] * gy + coef[2, 0]).astype(np.float32)
        row_px = (coef[0, 1] * gx + coef[1, 1] * gy + coef[2, 1]).astype(np.float32)
        if np.abs(resid).max() > 1e-3:
            ix = (gx - np.float32((NODE_STEP - 1) / 2.0)) / np.float32(NODE_STEP) + np.float32(1.0)
            iy = (gy - np.float32((NODE_STEP - 1) / 2.0)) / np.float32(NODE_STEP) + np.float32(1.0)
            r = cv2.remap(resid, ix, iy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            col_px += r[..., 0]
            row_px += r[..., 1]
        col_px[~found], row_px[~found] = np.nan, np.nan
        window = self._read_window(self.ortho, level, col_px, row_px)
        if window is None:
            return np.full((H, W, 3), OFF_RASTER_BGR, np.uint8)
        img, c0, r0 = window
        mx = np.where(found, col_px - np.float32(0.5 + c0), np.float32(-1e6))
        my = np.where(found, row_px - np.float32(0.5 + r0), np.float32(-1e6))
        return cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=OFF_RASTER_BGR)
