"""Point features of photos (SIFT) and descriptor matching between two photos.

Pixels are full-resolution pixels of the stored photo, whatever scale the features were detected at.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

SIFT_BYTES = 128


@dataclass(frozen=True)
class PhotoFeatures:
    """Point features of one photo: ``uv_px`` (N, 2) float64 full-resolution px; ``descriptors`` (N, 128)
    uint8 (SIFT); ``size_px`` (N,) the keypoint diameter, full-resolution px."""

    uv_px: np.ndarray
    descriptors: np.ndarray
    size_px: np.ndarray

    def __len__(self) -> int:
        return len(self.uv_px)


#: SIFT's contrast thresholds, tried in turn while a photo has fewer features than asked for: OpenCV's default,
#: then one for bare ground (a Seneca photo of bare soil: 92 features at the default, 16 675 at 0.01).
CONTRAST_THRESHOLDS = (0.04, 0.01)


def detect_sift(gray: np.ndarray, scale: float, n_features: int, min_features: int = 0) -> PhotoFeatures:
    """SIFT features of a (H, W) uint8 image that is the stored photo reduced by ``scale`` (>= 1).

    Keypoints are returned in the stored photo's pixels. SIFT's orientation makes them rotation-invariant, so
    a photo flown the other way still matches. With fewer than ``min_features`` the contrast threshold is
    lowered (:data:`CONTRAST_THRESHOLDS`).
    """
    for threshold in CONTRAST_THRESHOLDS:
        sift = cv2.SIFT_create(nfeatures=int(n_features), contrastThreshold=threshold)
        keypoints, desc = sift.detectAndCompute(gray, None)
        if len(keypoints) >= min_features:
            break
    if desc is None or not keypoints:
        return PhotoFeatures(np.zeros((0, 2)), np.zeros((0, SIFT_BYTES), np.uint8), np.zeros(0))
    uv = (np.array([kp.pt for kp in keypoints], float) + 0.5) * scale - 0.5
    size = np.array([kp.size for kp in keypoints], float) * scale
    # OpenCV's SIFT saturates its descriptor to 0..255 and stores it as float: uint8 is lossless.
    return PhotoFeatures(uv, np.clip(np.rint(desc), 0, 255).astype(np.uint8), size)


def _flann() -> cv2.FlannBasedMatcher:
    return cv2.FlannBasedMatcher({"algorithm": 1, "trees": 4}, {"checks": 64})


def match_descriptors(desc_a: np.ndarray, desc_b: np.ndarray, ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """Mutual nearest neighbours that pass Lowe's ratio test both ways. Returns index arrays (K,), (K,)."""
    if len(desc_a) < 2 or len(desc_b) < 2:
        return np.zeros(0, int), np.zeros(0, int)
    a, b = desc_a.astype(np.float32), desc_b.astype(np.float32)
    fl = _flann()

    def one_way(q, t):
        best = np.full(len(q), -1)
        for m in fl.knnMatch(q, t, k=2):
            if len(m) == 2 and m[0].distance < ratio * m[1].distance:
                best[m[0].queryIdx] = m[0].trainIdx
        return best

    ab, ba = one_way(a, b), one_way(b, a)
    ia = np.flatnonzero(ab >= 0)
    keep = ba[ab[ia]] == ia
    return ia[keep], ab[ia[keep]]


def _verify_pair(uv_a: np.ndarray, uv_b: np.ndarray, threshold_px: float) -> np.ndarray:
    """Inlier mask of a fundamental matrix found by MAGSAC++ (general 3D scenes, not only flat ground)."""
    if len(uv_a) < 15:
        return np.zeros(len(uv_a), bool)
    F, mask = cv2.findFundamentalMat(uv_a, uv_b, cv2.USAC_MAGSAC, threshold_px, 0.9999, 10000)
    if F is None or mask is None:
        return np.zeros(len(uv_a), bool)
    return mask.ravel().astype(bool)
