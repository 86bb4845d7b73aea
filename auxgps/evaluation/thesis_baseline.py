"""The thesis' method (its Chapter 3) as it describes it, for `auxgps bench` to run beside auxgps on the same frames.

Per image pair (the previous frame and the current one), as in its Listings 3.1 and 3.2:

- detection: ``cv2.ORB_create(nfeatures=1)`` and ``detectAndCompute`` on each image of the pair;
- matching: ``cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match`` between the two single descriptors;
- coordinate assignment (mapping, with GPS; its Algorithm 1): the matched keypoint's pixel offset from the image
  centre, turned to north by the heading and scaled by the altitude over the focal length, added to the drone's
  GPS position, is the feature's position. If its descriptor matches a stored feature (the same matcher, Hamming
  distance at most ``MAX_HAMMING``: the thesis' "above a set percentage" of equal bits, here 75 %), that feature's
  average position and appearance count are updated; else the feature is appended.
- drone positioning (without GPS; its Algorithm 2): the pair's matched feature is looked up among the stored
  features the same way, and the drone is at the stored position minus the keypoint's offset (the reverse
  projection).

It assumes, as the thesis did, a camera looking straight down with image-up towards the nose, and ignores tilt.
Positions are in the local NED frame (the thesis used latitude and longitude; the arithmetic is the same).
Only the standard library, NumPy and OpenCV: it does not use auxgps' pipeline.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import numpy as np

MAX_HAMMING = 64  # bits of 256 that may differ for two descriptors to be the same feature


@dataclass
class StoredFeature:
    """The thesis' FeaturesData, less what it kept only for evaluation (the image, the list of coordinates)."""

    descriptor: np.ndarray  # (32,) uint8
    appearances: int
    avg_ne_m: np.ndarray  # (2,) running average of the assigned positions, m
    heading_rad: float


class ThesisBaseline:
    """One ORB feature per image, brute-force Hamming with cross-check, reverse projection by heading and altitude.

    Parameters
    ----------
    focal_px : focal length, px; ``cx_px``, ``cy_px`` : image centre, px.
    """

    name = "baseline"

    def __init__(self, focal_px: float, cx_px: float, cy_px: float) -> None:
        self.f = float(focal_px)
        self.c = np.array([cx_px, cy_px], float)
        self.orb = cv2.ORB_create(nfeatures=1)
        self.bf = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
        self.store: list[StoredFeature] = []
        self._store_desc = np.zeros((0, 32), np.uint8)
        self._prev: np.ndarray | None = None

    # -- the steps -------------------------------------------------------------------------------------------

    def _pair_feature(self, image_bgr: np.ndarray, times: dict) -> tuple[np.ndarray, np.ndarray] | None:
        """Detect on the previous and current image, match; the current image's matched keypoint and descriptor."""
        prev, self._prev = self._prev, image_bgr
        if prev is None:
            return None
        t0 = time.perf_counter()
        kp1, des1 = self.orb.detectAndCompute(prev, None)
        kp2, des2 = self.orb.detectAndCompute(image_bgr, None)
        t1 = time.perf_counter()
        times["detection"] = (t1 - t0) * 1e3
        if des1 is None or des2 is None:
            return None
        matches = sorted(self.bf.match(des1, des2), key=lambda m: m.distance)
        times["matching"] = (time.perf_counter() - t1) * 1e3
        if not matches:
            return None
        m = matches[0]
        return np.array(kp2[m.trainIdx].pt, float), des2[m.trainIdx]

    def _offset_ne_m(self, uv_px: np.ndarray, yaw_rad: float, alt_m: float) -> np.ndarray:
        """Ground offset (north, east), m, of a pixel from the point below the drone: image-up is the nose."""
        du, dv = (uv_px - self.c) * (alt_m / self.f)
        forward, right = -dv, du
        c, s = np.cos(yaw_rad), np.sin(yaw_rad)
        return np.array([forward * c - right * s, forward * s + right * c])

    def _lookup(self, descriptor: np.ndarray) -> int | None:
        """Index of the stored feature matching ``descriptor`` (cross-checked nearest, within MAX_HAMMING)."""
        if len(self.store) == 0:
            return None
        found = self.bf.match(descriptor[None, :], self._store_desc)
        if not found or found[0].distance > MAX_HAMMING:
            return None
        return found[0].trainIdx

    # -- the benchmark's interface ---------------------------------------------------------------------------

    def map_frame(self, image_bgr: np.ndarray, tel) -> dict:
        """Coordinate assignment for the pair ending at this frame (GPS in ``tel``)."""
        times: dict = {}
        feat = self._pair_feature(image_bgr, times)
        if feat is None or tel.p_gps_ned_m is None:
            return times
        t0 = time.perf_counter()
        uv, desc = feat
        yaw = float(tel.euler_rad[2])
        p_ne = np.asarray(tel.p_gps_ned_m, float)[:2] + self._offset_ne_m(uv, yaw, tel.alt_above_origin_m)
        k = self._lookup(desc)
        if k is not None:
            f = self.store[k]
            f.avg_ne_m = (f.avg_ne_m * f.appearances + p_ne) / (f.appearances + 1)
            f.appearances += 1
        else:
            self.store.append(StoredFeature(desc.copy(), 1, p_ne, yaw))
            self._store_desc = np.vstack([self._store_desc, desc[None, :]])
        times["solving"] = (time.perf_counter() - t0) * 1e3
        return times

    def locate_frame(self, image_bgr: np.ndarray, tel) -> tuple[np.ndarray | None, dict]:
        """Drone position (north, east), m, from the pair ending at this frame, or None."""
        times: dict = {}
        feat = self._pair_feature(image_bgr, times)
        if feat is None:
            return None, times
        t0 = time.perf_counter()
        uv, desc = feat
        k = self._lookup(desc)
        t1 = time.perf_counter()
        times["matching"] = times.get("matching", 0.0) + (t1 - t0) * 1e3
        if k is None:
            return None, times
        p_ne = self.store[k].avg_ne_m - self._offset_ne_m(uv, float(tel.euler_rad[2]), tel.alt_above_origin_m)
        times["solving"] = (time.perf_counter() - t1) * 1e3
        return p_ne, times

    def start_positioning(self) -> None:
        """A new flight: the first frame has no pair."""
        self._prev = None


def make_baseline(camera) -> ThesisBaseline:
    """The baseline for a :class:`auxgps.core.camera.PinholeCamera` (its focal length and centre)."""
    return ThesisBaseline(camera.focal_px, camera.K[0, 2], camera.K[1, 2])
