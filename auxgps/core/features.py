"""Feature detection (ORB) and binary descriptor distances."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from auxgps.errors import FrameError

DESCRIPTOR_BYTES = 32
_POPCOUNT = np.array([bin(i).count("1") for i in range(256)], np.uint8)
#: Indices below this fit 16 bits, which NumPy's stable sort orders by radix.
_RADIX_SORTABLE = 1 << 16


@dataclass(frozen=True)
class Features:
    """Point features of one frame.

    uv_px : (N, 2) float64, full-resolution px; descriptors : (N, 32) uint8 (ORB, 256 bits); octave : (N,) int
    pyramid level; scale : the image scale they were detected at (detection px per full-resolution px, 1 = full
    resolution), so that a keypoint of octave ``k`` spans ``scale_factor**k / scale`` full-resolution px.
    """

    uv_px: np.ndarray
    descriptors: np.ndarray
    octave: np.ndarray
    scale: float = 1.0

    def __len__(self) -> int:
        return len(self.uv_px)

    @classmethod
    def empty(cls) -> "Features":
        return cls(np.zeros((0, 2)), np.zeros((0, DESCRIPTOR_BYTES), np.uint8), np.zeros(0, int))


class FeatureDetector:
    """ORB keypoints and descriptors, as configured by a :class:`auxgps.config.DetectorConfig`.

    FAST thresholds are tried from ``fast_threshold_first`` down to ``fast_threshold`` in ``fast_threshold_rungs``
    even steps; the first whose keypoints fill the budget of ``n_features`` gives them (see :func:`detect`). A
    frame starts at the rung that filled the frame before (ground changes slowly), and after ``_CLIMB_AFTER``
    frames in a row filled there, one rung higher: over ground where the first threshold never fills (Seneca's
    fields), every frame would otherwise pay a failed pass before the one that counts.
    """

    _CLIMB_AFTER = 15

    def __init__(self, cfg) -> None:
        self.cfg = cfg
        make = lambda threshold: cv2.ORB_create(  # noqa: E731
            nfeatures=cfg.n_features,
            scaleFactor=cfg.scale_factor,
            nlevels=cfg.n_levels,
            edgeThreshold=cfg.edge_threshold_px,
            patchSize=max(cfg.edge_threshold_px, 2),
            fastThreshold=threshold,
        )
        thresholds = np.linspace(cfg.fast_threshold_first, cfg.fast_threshold, cfg.fast_threshold_rungs)
        self.thresholds = sorted({int(round(t)) for t in thresholds}, reverse=True)
        self.ladder = [make(t) for t in self.thresholds]
        self.orb = self.ladder[-1]
        self._rung = 0  # where the next frame starts
        self._filled_in_a_row = 0

    def detect(self, image: np.ndarray, R_ned_cam: np.ndarray | None = None, scale: float = 1.0) -> "Features":
        """Features of ``image``. With the camera's attitude ``R_ned_cam`` (and ``north_aligned`` set), every
        descriptor is taken in the direction of north instead of the keypoint's own orientation.

        ``scale`` < 1 detects on the image shrunk by that factor (area interpolation), as a camera ``1 / scale``
        times farther away would see it: a frame taken closer to the ground than the map's descriptors then
        describes its corners alike. Positions are returned in full-resolution pixels all the same.
        """
        if not 0.0 < scale <= 1.0:
            raise ValueError(f"detection scale must be in (0, 1], got {scale}")
        angle = north_angle_deg(R_ned_cam) if (self.cfg.north_aligned and R_ned_cam is not None) else None
        gray = to_gray(image)
        if scale < 1.0 and gray.size:
            size = (max(int(round(gray.shape[1] * scale)), 1), max(int(round(gray.shape[0] * scale)), 1))
            gray = cv2.resize(gray, size, interpolation=cv2.INTER_AREA)
        start = self._rung
        if start > 0 and self._filled_in_a_row >= self._CLIMB_AFTER:
            start, self._filled_in_a_row = start - 1, 0
        feats, filled = detect(self.ladder[start:], gray, self.cfg.min_harris, angle)
        rung = start + filled
        self._filled_in_a_row = self._filled_in_a_row + 1 if rung == self._rung else 0
        self._rung = rung
        if self.cfg.subpixel_window_px > 0 and len(feats):
            feats = refine_subpixel(gray, feats, self.cfg.subpixel_window_px)
        if scale < 1.0:
            # Pixel centres: detection pixel u covers full-resolution [u / s, (u + 1) / s).
            feats = Features((feats.uv_px + 0.5) / scale - 0.5, feats.descriptors, feats.octave, scale)
        return feats


def near_nadir(feats: Features, camera, R_ned_cam: np.ndarray, max_off_nadir_deg: float | None) -> Features:
    """``feats`` without those whose ray, through ``camera`` at attitude ``R_ned_cam``, is more than
    ``max_off_nadir_deg`` from straight down (all of them when it is None)."""
    if max_off_nadir_deg is None or not len(feats):
        return feats
    down = camera.pixels_to_rays_cam(feats.uv_px) @ np.asarray(R_ned_cam, float)[2]
    keep = down >= np.cos(np.deg2rad(max_off_nadir_deg))
    return Features(feats.uv_px[keep], feats.descriptors[keep], feats.octave[keep], feats.scale)


def to_gray(image: np.ndarray) -> np.ndarray:
    """Validate a frame and return it as (H, W) uint8 grey. Raises :class:`FrameError` naming what is wrong."""
    if not isinstance(image, np.ndarray):
        raise FrameError(f"frame is {type(image).__name__}, not an image array")
    if image.dtype != np.uint8:
        raise FrameError(f"frame has dtype {image.dtype}, expected uint8")
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.ndim == 2:
        return image
    raise FrameError(f"frame has shape {image.shape}, expected (H, W) or (H, W, 3)")


def north_angle_deg(R_ned_cam: np.ndarray) -> float:
    """Direction of north in the image (OpenCV keypoint angle, degrees) for a camera with attitude ``R_ned_cam``."""
    north_cam = np.asarray(R_ned_cam, float).T @ np.array([1.0, 0.0, 0.0])
    return float(np.degrees(np.arctan2(north_cam[1], north_cam[0])) % 360.0)


def detect(ladder: list[cv2.ORB], image: np.ndarray, min_harris: float = 0.0, angle_deg: float | None = None) -> tuple[Features, int]:
    """Detect and describe point features; also the index in ``ladder`` of the detector whose keypoints were
    kept. An empty or featureless frame gives empty :class:`Features`.

    ``ladder``: the same ORB at falling FAST thresholds. Keypoints are taken from the first that finds the full
    budget of ``nfeatures``, else from the last. Per pyramid level, ORB takes the corners of highest FAST score
    (twice the level's share), then the best of those by Harris score; a higher threshold only drops corners of
    lower FAST score. So when twice each level's share passes it (as on textured ground and real photos), the
    features are the same as the last one's, found in less time (FAST is the largest part of ORB's); when only the
    share passes, they are strong corners still; a frame poor in corners is detected as at the last.

    Keypoints whose Harris score is not above ``min_harris`` are dropped: a negative score marks a point on a
    straight edge, which slides along the edge from view to view and is no point landmark. With ``angle_deg``,
    descriptors are computed at that orientation rather than each keypoint's own: the autopilot knows the
    heading, and a descriptor aligned to north tells apart the four alike corners of a cube, which
    rotation-invariant ones cannot.
    """
    gray = to_gray(image)
    if gray.size == 0:
        raise FrameError("frame is empty")
    for used, orb in enumerate(ladder):
        keypoints = orb.detect(gray, None)
        if len(keypoints) >= orb.getMaxFeatures():
            break
    detector = ladder[-1]
    keypoints = [kp for kp in keypoints if kp.response > min_harris]
    if not keypoints:
        return Features.empty(), used
    if angle_deg is not None:
        for kp in keypoints:
            kp.angle = angle_deg
    keypoints, descriptors = detector.compute(gray, keypoints)
    if descriptors is None or not keypoints:
        return Features.empty(), used
    uv = cv2.KeyPoint_convert(keypoints).astype(float)  # the keypoints' float32 positions, as kp.pt gives them
    octave = np.array([kp.octave for kp in keypoints], int)
    return Features(uv, descriptors, octave), used


def refine_subpixel(gray: np.ndarray, feats: Features, window_px: int) -> Features:
    """Move each keypoint to the sub-pixel corner (OpenCV's cornerSubPix): FAST puts a corner on a whole pixel,
    about one pixel inside it, and that pixel is 2 to 3 cm on the ground from 15 m."""
    pts = feats.uv_px.astype(np.float32).reshape(-1, 1, 2).copy()
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.01)
    refined = cv2.cornerSubPix(gray, pts, (window_px, window_px), (-1, -1), criteria).reshape(-1, 2).astype(float)
    # A point that wandered off (a weak corner) keeps its detector position.
    moved = np.linalg.norm(refined - feats.uv_px, axis=1)
    uv = np.where((moved <= window_px)[:, None], refined, feats.uv_px)
    return Features(uv, feats.descriptors, feats.octave, feats.scale)


def hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise Hamming distances between (N, 32) and (N, 32) uint8 descriptors -> (N,) int32.

    Counted on 64-bit words with the CPU's popcount (``np.bitwise_count``) where the descriptors are contiguous
    32-byte rows, else by a byte table; both give the same numbers.
    """
    a, b = np.ascontiguousarray(a), np.ascontiguousarray(b)
    if a.dtype == np.uint8 and b.dtype == np.uint8 and a.ndim == b.ndim == 2 and a.shape[1] == b.shape[1] == DESCRIPTOR_BYTES:
        x = np.bitwise_xor(a.view(np.uint64), b.view(np.uint64))
        return np.bitwise_count(x).sum(axis=1, dtype=np.int32)
    return _POPCOUNT[np.bitwise_xor(a, b)].sum(axis=1, dtype=np.int32)


def hamming_pairs(a: np.ndarray, ia: np.ndarray, b: np.ndarray, ib: np.ndarray) -> np.ndarray:
    """Hamming distances of the pairs ``(a[ia[k]], b[ib[k]])`` of (N, 32) and (M, 32) uint8 descriptors -> (K,)
    int32: ``hamming(a[ia], b[ib])`` without gathering the rows. Each 64-bit word is gathered and counted on its
    own (four 8-byte gathers cost a quarter of one 32-byte-row gather over tens of thousands of pairs)."""
    a, b = np.ascontiguousarray(a), np.ascontiguousarray(b)
    if not (a.dtype == np.uint8 and b.dtype == np.uint8 and a.ndim == b.ndim == 2 and a.shape[1] == b.shape[1] == DESCRIPTOR_BYTES):
        return hamming(a[ia], b[ib])
    a64, b64 = a.view(np.uint64), b.view(np.uint64)
    out = np.zeros(len(ia), np.uint16)
    for k in range(a64.shape[1]):
        out += np.bitwise_count(a64[:, k][ia] ^ b64[:, k][ib])
    return out.astype(np.int32)


def pairs_within(a_px: np.ndarray, b_px: np.ndarray, radius_px: float, ordered: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Every (i, j) with ``|a_i - b_j| <= radius_px``, for (N, 2) and (M, 2) pixels, ordered by i then j (in the
    k-d trees' order with ``ordered=False``: a caller that keeps few of them puts those in order, with
    :func:`pair_order`, for less).

    Found through k-d trees, so the cost follows the pairs found rather than N * M. The trees are built
    unbalanced (sliding midpoint splits, no median search: half the build time for a frame's pixels, and the
    same pairs).
    """
    if len(a_px) == 0 or len(b_px) == 0:
        return np.zeros(0, int), np.zeros(0, int)
    a_tree = cKDTree(a_px, balanced_tree=False, compact_nodes=False)
    found = a_tree.sparse_distance_matrix(cKDTree(b_px, balanced_tree=False, compact_nodes=False), radius_px, output_type="ndarray")
    i, j = found["i"].astype(np.int64), found["j"].astype(np.int64)
    if not ordered:
        return i, j
    order = pair_order(i, j, len(a_px), len(b_px))
    return i[order], j[order]


def pairs_within_radii(a_px: np.ndarray, b_px: np.ndarray, radius_b_px: np.ndarray, edges_px=(12.0, 24.0)) -> tuple[np.ndarray, np.ndarray]:
    """Every (i, j) with ``|a_i - b_j| <= radius_b_px[j]``, each ``b`` with its own radius, unordered.

    The ``b`` are searched in groups of like radius (up to each of ``edges_px``, then the rest), each group with its
    largest, and the pairs beyond their own radius dropped: when a few radii are wide, the rest are not searched as
    widely too (the pairs found cost most of a search).
    """
    radius_b_px = np.asarray(radius_b_px, float)
    if len(a_px) == 0 or len(b_px) == 0:
        return np.zeros(0, int), np.zeros(0, int)
    a_tree = cKDTree(a_px, balanced_tree=False, compact_nodes=False)
    group = np.searchsorted(np.asarray(edges_px, float), radius_b_px)
    found_i, found_j = [], []
    for g in range(len(edges_px) + 1):
        sel = np.flatnonzero(group == g)
        if len(sel) == 0:
            continue
        found = a_tree.sparse_distance_matrix(cKDTree(b_px[sel], balanced_tree=False, compact_nodes=False),
                                              float(radius_b_px[sel].max()), output_type="ndarray")
        i, j = found["i"].astype(np.int64), sel[found["j"]]
        keep = found["v"] <= radius_b_px[j]
        found_i.append(i[keep])
        found_j.append(j[keep])
    return np.concatenate(found_i), np.concatenate(found_j)


def pair_order(i: np.ndarray, j: np.ndarray, n_a: int, n_b: int) -> np.ndarray:
    """The permutation that puts pairs ``(i[k], j[k])`` (``i < n_a``, ``j < n_b``, no pair twice) in order of i,
    then j: two stable sorts of 16-bit indices where they fit (NumPy sorts those by radix, in linear time), else
    one sort of a unique key per pair."""
    if max(n_a, n_b) <= _RADIX_SORTABLE:
        by_j = np.argsort(j.astype(np.uint16), kind="stable")
        return by_j[np.argsort(i[by_j].astype(np.uint16), kind="stable")]
    return np.argsort(i * n_b + j)


#: Up to this many pairs, :func:`greedy_one_to_one` takes them one by one; beyond, in rounds of array work. Each
#: round costs about 0.5 ms however short the list, the loop about 0.3 us a pair (1000 pairs: 0.9 ms in rounds,
#: 0.3 ms by the loop; 20 000: 7.4 and 8.9 ms). A reading's members are tens to hundreds of pairs.
GREEDY_LOOP_MAX_PAIRS = 5000


def greedy_one_to_one(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The positions of the pairs ``(a[k], b[k])``, taken in order, that a greedy one-to-one assignment keeps (a
    pair is kept unless an earlier kept pair has its ``a`` or its ``b``), ascending.

    A short list pair by pair; a long one (over ``GREEDY_LOOP_MAX_PAIRS``) in rounds: a pair that is the first
    remaining one of both its ``a`` and its ``b`` is kept by the sequential greedy too (everything before it that
    shares either was dropped for a kept pair still earlier), so each round keeps all such pairs and drops the
    pairs they block; the first remaining pair always qualifies. The same pairs either way.
    """
    if len(a) <= GREEDY_LOOP_MAX_PAIRS:
        used_a, used_b, kept_k = set(), set(), []
        for k, (x, y) in enumerate(zip(np.asarray(a).tolist(), np.asarray(b).tolist())):
            if x not in used_a and y not in used_b:
                used_a.add(x)
                used_b.add(y)
                kept_k.append(k)
        return np.array(kept_k, np.int64)
    return _greedy_one_to_one_in_rounds(np.asarray(a), np.asarray(b))


def _greedy_one_to_one_in_rounds(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """:func:`greedy_one_to_one` in rounds of array work, for long lists."""
    def first_of_each(x: np.ndarray) -> np.ndarray:
        first = np.zeros(len(x), bool)
        first[np.unique(x, return_index=True)[1]] = True
        return first

    k = np.arange(len(a))
    kept = []
    while len(k):
        ak, bk = a[k], b[k]
        keep = first_of_each(ak) & first_of_each(bk)
        kept.append(k[keep])
        k = k[~(np.isin(ak, ak[keep]) | np.isin(bk, bk[keep]))]
    return np.sort(np.concatenate(kept)) if kept else np.zeros(0, np.int64)


def spots(feature_tree: cKDTree, radius_px: float) -> np.ndarray:
    """(N,) an id per feature, shared by features within ``radius_px`` of each other (chained): one spot of the
    image, which is one point of the ground however many pyramid levels found it. Ids count the spots in order of
    their first feature (as ``scipy.sparse.csgraph.connected_components`` numbers components).

    Each feature takes the smallest index it is chained to, by passes of "the smaller of a pair's two" and
    pointer jumping: a frame's pairs are few and their chains two or three long, so two or three passes of
    array work, where the sparse-graph route cost 0.4 ms a frame in building and checking the graph.
    """
    pairs = feature_tree.query_pairs(radius_px, output_type="ndarray")
    n = feature_tree.n
    if not len(pairs):
        return np.arange(n)
    i, j = pairs[:, 0], pairs[:, 1]
    root = np.arange(n)
    while True:
        before = root.copy()
        lo = np.minimum(root[i], root[j])
        np.minimum.at(root, i, lo)
        np.minimum.at(root, j, lo)
        root = root[root]
        if np.array_equal(root, before):
            break
    return np.unique(root, return_inverse=True)[1]
