"""Orthophotos from solved photos: each photo projected onto the ground and blended (:meth:`Mosaic.tile`), and the
offsets at the seams between neighbouring photos measured (:meth:`Mosaic.seam_offsets`).

The poses are the photo block's (:func:`auxgps.photo.build.build_photo_map`); the ground is the plane fitted
to the block's 3D points (:func:`fit_ground_plane`), so relief off that plane shows as parallax at the seams,
and the seam offsets say how much. Every photo's pixel is weighted by its distance from the photo's border, to
the power :data:`EDGE_POWER`: where photos overlap, the one whose centre is nearest dominates and the seam is
feathered rather than cut, and the darker, more distorted corners of a photo count least.

Frames: local NED (m) about the block's origin; the output grid's pixels (col, row; affine convention, pixel
centres at .5) reach it through two functions the caller gives (the grid's CRS lives at the edge). Images are (H, W, 3) uint8
in the photo's own pixels (those of :class:`~auxgps.photo.types.SolvedPhoto`'s camera).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import cv2
import numpy as np

from auxgps.core.camera import CameraPose, PinholeCamera
from auxgps.core.lattice import node_axis, upsample

#: A photo pixel's weight is (its distance to the nearest border / half the shorter side) to this power.
EDGE_POWER = 4.0
#: Output pixels between the nodes where the projection into a photo is computed exactly (bilinear in between).
NODE_STEP = 16
#: A seam is measured on a square patch of at most this many output pixels a side, centred in the overlap.
SEAM_PATCH_PX = 384
#: Phase correlation peaks weaker than this are not a measurement (texture too poor or too different).
SEAM_MIN_RESPONSE = 0.05

#: (a, b) arrays -> (c, d) arrays: output pixel (col, row) -> (north_m, east_m), or the other way.
PlaneMap = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class GroundPlane:
    """The ground as a plane in the block's NED frame: ``down_m = a * north_m + b * east_m + c``; ``rms_m`` the
    points' vertical scatter about it (relief, trees, error), from the ``n_points`` kept."""

    a: float
    b: float
    c: float
    rms_m: float
    n_points: int

    def down_m(self, north_m: np.ndarray, east_m: np.ndarray) -> np.ndarray:
        return self.a * north_m + self.b * east_m + self.c


@dataclass(frozen=True)
class OrthoPhoto:
    """One photo to project: its name, camera and solved pose."""

    name: str
    camera: PinholeCamera
    pose: CameraPose


@dataclass(frozen=True)
class Seam:
    """The offset between two neighbouring photos where both see the ground: ``offset_xy_m`` (2,) of photo
    ``b``'s projection against ``a``'s along the output grid's x (columns) and y (up the rows), m; ``response``
    the phase correlation peak (0 to 1); ``overlap_px`` output pixels both photos see in the patch."""

    a: str
    b: str
    offset_xy_m: np.ndarray
    response: float
    overlap_px: int

    @property
    def offset_m(self) -> float:
        return float(np.hypot(*self.offset_xy_m))


def fit_ground_plane(p_ned_m: np.ndarray, iterations: int = 3) -> GroundPlane:
    """A plane fitted by least squares to 3D points (N, 3), points beyond 3 robust sigmas left out and the fit
    repeated. Raises ValueError with fewer than 3 points."""
    p = np.asarray(p_ned_m, float).reshape(-1, 3)
    if len(p) < 3:
        raise ValueError(f"a ground plane needs at least 3 points, got {len(p)}")
    keep = np.ones(len(p), bool)
    for _ in range(iterations):
        A = np.column_stack([p[keep, 0], p[keep, 1], np.ones(keep.sum())])
        coef, *_ = np.linalg.lstsq(A, p[keep, 2], rcond=None)
        res = p[:, 2] - np.column_stack([p[:, 0], p[:, 1], np.ones(len(p))]) @ coef
        med = np.median(res[keep])
        mad = 1.4826 * np.median(np.abs(res[keep] - med))
        keep = np.abs(res - med) <= max(3.0 * mad, 1e-6)
    rms = float(np.sqrt(np.mean(res[keep] ** 2)))
    return GroundPlane(float(coef[0]), float(coef[1]), float(coef[2]), rms, int(keep.sum()))


def edge_weight(width_px: int, height_px: int, power: float = EDGE_POWER) -> np.ndarray:
    """(H, W) float32 weights of a photo's pixels: distance to the nearest border over half the shorter side,
    to ``power`` (0 at the border, 1 at the centre of the shorter axis)."""
    u = np.minimum(np.arange(width_px) + 0.5, width_px - 0.5 - np.arange(width_px))
    v = np.minimum(np.arange(height_px) + 0.5, height_px - 0.5 - np.arange(height_px))
    d = np.minimum(u[None, :], v[:, None]) / (0.5 * min(width_px, height_px))
    return (np.clip(d, 0.0, 1.0) ** power).astype(np.float32)


def footprint_ne(photo: OrthoPhoto, plane: GroundPlane, samples: int = 8) -> np.ndarray | None:
    """(K, 2) north, east of points along the photo's border projected onto the plane (None when a border ray
    misses it: the photo sees the horizon)."""
    cam = photo.camera
    t = np.linspace(0.0, 1.0, samples, endpoint=False)
    w, h = cam.width_px - 1.0, cam.height_px - 1.0
    uv = np.vstack([np.column_stack([t * w, np.zeros_like(t)]), np.column_stack([np.full_like(t, w), t * h]),
                    np.column_stack([w - t * w, np.full_like(t, h)]), np.column_stack([np.zeros_like(t), h - t * h])])
    rays = photo.pose.rays_ned(cam, uv)
    C = photo.pose.p_cam_in_ned_m
    # Ray point C + s r on the plane: C_d + s r_d = a (C_n + s r_n) + b (C_e + s r_e) + c.
    num = plane.a * C[0] + plane.b * C[1] + plane.c - C[2]
    den = rays[:, 2] - plane.a * rays[:, 0] - plane.b * rays[:, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = num / den
    if not np.all(np.isfinite(s) & (s > 0)):
        return None
    return C[:2] + s[:, None] * rays[:, :2]


class _Projector:
    """Where the ground under output pixels is in one photo, and the photo resampled there."""

    def __init__(self, photo: OrthoPhoto) -> None:
        self.photo = photo
        cam = photo.camera
        # The photo's extent in undistorted normalized coordinates (a little beyond): projecting through the
        # distortion model far outside it can fold back into the image.
        border = np.array([[0, 0], [cam.width_px - 1, 0], [0, cam.height_px - 1], [cam.width_px - 1, cam.height_px - 1],
                           [(cam.width_px - 1) / 2, 0], [(cam.width_px - 1) / 2, cam.height_px - 1],
                           [0, (cam.height_px - 1) / 2], [cam.width_px - 1, (cam.height_px - 1) / 2]], float)
        xy = cam.pixels_to_normalized(border)
        lo, hi = xy.min(axis=0), xy.max(axis=0)
        pad = 0.1 * (hi - lo)
        self.lo, self.hi = lo - pad, hi + pad

    def uv_at(self, p_ned_m: np.ndarray) -> np.ndarray:
        """(..., 3) NED ground points -> (..., 2) float32 photo pixels (NaN where the photo cannot see them)."""
        shape = p_ned_m.shape[:-1]
        p_cam = self.photo.pose.ned_to_cam(p_ned_m.reshape(-1, 3))
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = p_cam[:, :2] / p_cam[:, 2:3]
        ok = (p_cam[:, 2] > 0) & np.all((xy >= self.lo) & (xy <= self.hi), axis=1)
        uv = np.full((len(p_cam), 2), np.nan)
        if ok.any():
            uv[ok] = self.photo.camera.project_cam(p_cam[ok])[0]
        return uv.reshape(*shape, 2).astype(np.float32)


def _resample(proj: _Projector, image: np.ndarray, weight: np.ndarray, nodes: np.ndarray, h: int, w: int):
    """The photo's colour and weight at every output pixel of the window (weight 0 where it does not see)."""
    uv = upsample(proj.uv_at(nodes), h, w, NODE_STEP)
    bad = ~np.isfinite(uv).all(axis=-1)
    uv[bad] = -1e4
    colour = cv2.remap(image, uv[..., 0], uv[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    wt = cv2.remap(weight, uv[..., 0], uv[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    wt[bad] = 0.0
    return colour, wt


class Mosaic:
    """Photos projected onto a ground plane and blended into an output grid.

    Parameters
    ----------
    photos : the solved photos
    images : name -> (H, W, 3) uint8 image (called when a photo is needed; cache it there if it is slow)
    plane : the ground
    ne_of_colrow : output pixel (col, row) -> local north, east, m
    colrow_of_ne : the inverse
    """

    def __init__(self, photos: list[OrthoPhoto], images: Callable[[str], np.ndarray], plane: GroundPlane,
                 ne_of_colrow: PlaneMap, colrow_of_ne: PlaneMap) -> None:
        self.photos = list(photos)
        self.images = images
        self.plane = plane
        self.ne_of_colrow = ne_of_colrow
        self._proj = {p.name: _Projector(p) for p in self.photos}
        self._weights: dict = {}
        self.footprint_colrow: dict[str, np.ndarray] = {}
        self.left_out: list[str] = []
        for p in self.photos:
            fp = footprint_ne(p, plane)
            if fp is None:
                self.left_out.append(p.name)
                continue
            self.footprint_colrow[p.name] = np.column_stack(colrow_of_ne(fp[:, 0], fp[:, 1]))

    def _weight(self, cam: PinholeCamera) -> np.ndarray:
        key = (cam.width_px, cam.height_px)
        if key not in self._weights:
            self._weights[key] = edge_weight(*key)
        return self._weights[key]

    def photos_over(self, row0: int, col0: int, h: int, w: int) -> list[OrthoPhoto]:
        """The photos whose footprint's bounding box meets the window."""
        out = []
        for p in self.photos:
            fp = self.footprint_colrow.get(p.name)
            if fp is None:
                continue
            (c_lo, r_lo), (c_hi, r_hi) = fp.min(axis=0), fp.max(axis=0)
            if c_hi >= col0 and c_lo <= col0 + w and r_hi >= row0 and r_lo <= row0 + h:
                out.append(p)
        return out

    def tile(self, row0: int, col0: int, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
        """The blended window: (h, w, 3) uint8 and (h, w) bool 'some photo sees it'."""
        acc = np.zeros((h, w, 3), np.float32)
        wsum = np.zeros((h, w), np.float32)
        over = self.photos_over(row0, col0, h, w)
        if over:
            nodes = self._nodes(row0, col0, h, w)
            for p in over:
                colour, wt = self._single(p, nodes, h, w)
                acc += colour.astype(np.float32) * wt[..., None]
                wsum += wt
        seen = wsum > 1e-6
        out = np.zeros((h, w, 3), np.uint8)
        out[seen] = np.clip(acc[seen] / wsum[seen, None] + 0.5, 0, 255).astype(np.uint8)
        return out, seen

    def _nodes(self, row0: int, col0: int, h: int, w: int) -> np.ndarray:
        rows = row0 + node_axis(h, NODE_STEP) + 0.5
        cols = col0 + node_axis(w, NODE_STEP) + 0.5
        cc, rr = np.meshgrid(cols, rows)
        n, e = self.ne_of_colrow(cc, rr)
        n, e = np.asarray(n, float), np.asarray(e, float)
        return np.stack([n, e, self.plane.down_m(n, e)], axis=-1)

    def _single(self, photo: OrthoPhoto, nodes: np.ndarray, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
        """One photo alone over the window whose ground ``nodes`` are given: (h, w, 3) uint8 and its (h, w) weight."""
        return _resample(self._proj[photo.name], self.images(photo.name), self._weight(photo.camera), nodes, h, w)

    def seam_offsets(self, gsd_m: float, patch_px: int = SEAM_PATCH_PX) -> list[Seam]:
        """The offset between every two photos whose footprints overlap by at least a quarter of the patch: each
        projected alone over a patch centred in their common area, the shift between them by phase correlation
        (Hann window), in metres of ``gsd_m`` output pixels."""
        seams = []
        names = [p for p in self.photos if p.name in self.footprint_colrow]
        polys = {p.name: cv2.convexHull(self.footprint_colrow[p.name].astype(np.float32)) for p in names}
        for i, pa in enumerate(names):
            for pb in names[i + 1:]:
                area, inter = cv2.intersectConvexConvex(polys[pa.name], polys[pb.name])
                if area < (patch_px / 4) ** 2 or inter is None:
                    continue
                c, r = inter.reshape(-1, 2).mean(axis=0)
                half = patch_px // 2
                row0, col0 = int(r) - half, int(c) - half
                nodes = self._nodes(row0, col0, patch_px, patch_px)  # the same ground for both photos
                ia, wa = self._single(pa, nodes, patch_px, patch_px)
                ib, wb = self._single(pb, nodes, patch_px, patch_px)
                both = (wa > 0) & (wb > 0)
                if both.mean() < 0.25:
                    continue
                ga = cv2.cvtColor(ia, cv2.COLOR_RGB2GRAY).astype(np.float32)
                gb = cv2.cvtColor(ib, cv2.COLOR_RGB2GRAY).astype(np.float32)
                # Only the common area, each at its own mean (brightness differs photo to photo).
                ga = np.where(both, ga - ga[both].mean(), 0.0).astype(np.float32)
                gb = np.where(both, gb - gb[both].mean(), 0.0).astype(np.float32)
                (dc, dr), response = cv2.phaseCorrelate(ga, gb, cv2.createHanningWindow((patch_px, patch_px), cv2.CV_32F))
                if response < SEAM_MIN_RESPONSE:
                    continue
                seams.append(Seam(pa.name, pb.name, np.array([dc * gsd_m, -dr * gsd_m]), float(response), int(both.sum())))
        return seams
