"""Prior landmark maps from an orthophoto: what a flying camera would map, made from one north-up image of the ground.

An orthophoto is a nadir view with one ground sample distance (``gsd_m``, metres per pixel) everywhere. Its
features are detected tile by tile with the flight pipeline's own detector (descriptors north-aligned, as a
north-up image has them), each tile about the size of a frame at the scale positioning detects it at, so that the
map is as dense as what a frame finds. A landmark's descriptor range is the range from which the flight's camera
sees the ground at ``gsd_m``: positioning then shrinks a frame taken closer to the map's scale, as it does for a
descent (:meth:`auxgps.core.localise.Localiser.detection_scale`).

Uncertainty, per landmark: the keypoint's own (``keypoint_sigma_px`` of its pyramid level, on the ground) and the
orthophoto's internal error (seams, relief displacement: ``internal_sigma_h_m``) across; the height model's (or,
without one, the ground plane's) along. The orthophoto's placement error is not per landmark: it is one offset
shared by every landmark of the map, stated once as :attr:`MapSource.georef_sigma_h_m` and carried into each
fix whole (averaging many landmarks cannot shrink it).

Frames: local NED about the map's origin; an orthophoto tile's pixels are (col, row), x right (east) and y down
(south) in the north-up image.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: n_seen and n_visible of a prior landmark: in use from the start (at least any ``mapping.min_seen``), and a
#: frame that does not find it never makes it look unreliable (the flight does not count its views).
PRIOR_SEEN = 1000


@dataclass(frozen=True)
class MapSource:
    """Where a map's landmarks come from: ``kind`` "flight" (mapped in flight with GPS), "orthophoto" or "photos";
    ``name`` (a file name) and ``georef_sigma_h_m``, the one-sigma horizontal offset all its landmarks share (m;
    0 for a flight's own map, whose error per landmark is in its covariance)."""

    kind: str
    name: str = ""
    georef_sigma_h_m: float = 0.0

    def to_json(self) -> dict:
        return {"kind": self.kind, "name": self.name, "georef_sigma_h_m": self.georef_sigma_h_m}

    @classmethod
    def from_json(cls, d: dict) -> "MapSource":
        return cls(str(d["kind"]), str(d.get("name", "")), float(d.get("georef_sigma_h_m", 0.0)))


FLIGHT = MapSource("flight")


def shared_sigma_h_m(source: np.ndarray, sources, ids: np.ndarray) -> float:
    """The horizontal placement error points ``ids`` share through their sources (m, one sigma): each source's
    ``georef_sigma_h_m``, weighed by its share of ``ids`` (variances). ``source`` indexes ``sources``."""
    counts = np.bincount(source[ids], minlength=len(sources))
    var = np.array([s.georef_sigma_h_m**2 for s in sources])
    return float(np.sqrt(counts @ var / counts.sum()))


def main_source(source: np.ndarray, sources, ids: np.ndarray) -> MapSource:
    """The source most of points ``ids`` come from (``ids`` not empty)."""
    return sources[int(np.bincount(source[ids]).argmax())]


@dataclass(frozen=True)
class PriorMapModel:
    """How an orthophoto becomes landmarks: the build's ground sample distance ``gsd_m``, and the error model."""

    gsd_m: float
    keypoint_sigma_px: float = 0.5  # a corner's position in its pyramid level's pixels, one sigma
    internal_sigma_h_m: float = 0.15  # the orthophoto's own local distortion (seams, relief), one sigma
    height_sigma_m: float = 1.0  # the height model's (or the ground plane's) error, one sigma

    def altitude_range_m(self, focal_px: float, min_detection_scale: float, max_scale: float) -> tuple[float, float]:
        """Heights above ground (m) from which a camera of ``focal_px`` can position on this map: from where a
        frame is shrunk the most (``min_detection_scale``) to where it is as coarse as the map's finest pyramid
        level allows (``max_scale``, the detector's own scale range)."""
        h = self.gsd_m * focal_px
        return min_detection_scale * h, max_scale * h


def tile_grid(width_px: int, height_px: int, tile_w_px: int, tile_h_px: int) -> list[tuple[int, int, int, int]]:
    """(col0, row0, w, h) tiles covering a ``width_px`` x ``height_px`` image without overlap."""
    return [(c, r, min(tile_w_px, width_px - c), min(tile_h_px, height_px - r))
            for r in range(0, height_px, tile_h_px) for c in range(0, width_px, tile_w_px)]


def keep_inside(uv_px: np.ndarray, valid: np.ndarray, core: tuple[int, int, int, int], margin_px: int) -> np.ndarray:
    """(N,) bool: keypoints of a padded tile inside its core box (col0, row0, w, h; tile pixels) and at least
    ``margin_px`` from any pixel the orthophoto does not cover (``valid`` False): a corner at the edge of the
    mosaic is the edge, not the ground."""
    c0, r0, w, h = core
    u, v = uv_px[:, 0], uv_px[:, 1]
    inside = (u >= c0 - 0.5) & (u < c0 + w - 0.5) & (v >= r0 - 0.5) & (v < r0 + h - 0.5)
    if not np.any(inside):
        return inside
    H, W = valid.shape
    ui = np.clip(np.rint(u).astype(int), 0, W - 1)
    vi = np.clip(np.rint(v).astype(int), 0, H - 1)
    if margin_px > 0:
        import cv2

        k = 2 * margin_px + 1
        valid = cv2.erode(valid.astype(np.uint8), np.ones((k, k), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0) > 0
    return inside & valid[vi, ui]


def landmark_columns(descriptors: np.ndarray, p_ned_m: np.ndarray, level_scale: np.ndarray, model: PriorMapModel,
                     focal_px: float) -> dict[str, np.ndarray]:
    """The map columns (:data:`auxgps.core.landmarks.LandmarkMap.COLUMNS`) of prior landmarks.

    ``level_scale`` (N,): how many build pixels one pixel of the keypoint's pyramid level spans (1 at full
    resolution). Horizontal variance: the keypoint's and the orthophoto's internal error; vertical: the height
    model's. ``focal_px``: the flight camera's focal length, for the descriptor range."""
    n = len(p_ned_m)
    sigma_h = np.hypot(model.keypoint_sigma_px * model.gsd_m * np.asarray(level_scale, float), model.internal_sigma_h_m)
    info = np.zeros((n, 6), np.float32)
    info[:, 0] = info[:, 3] = 1.0 / sigma_h**2
    info[:, 5] = 1.0 / model.height_sigma_m**2
    return {
        "descriptors": np.ascontiguousarray(descriptors, np.uint8),
        "p_ned_m": np.asarray(p_ned_m, np.float32),
        "info_packed": info,
        "n_seen": np.full(n, PRIOR_SEEN, np.uint16),
        "n_visible": np.full(n, PRIOR_SEEN, np.uint16),
        "view_cos": np.ones(n, np.float16),
        "descriptor_range_m": np.full(n, model.gsd_m * focal_px, np.float16),
        "chi2_mean": np.zeros(n, np.float16),
    }
