"""The landmark map: geotagged point features, stored as columns of compact arrays.

Each landmark keeps its ORB descriptor, its position in the local NED frame, the information matrix of that
position (the inverse covariance, upper triangle), how often it was seen, and how straight down the view was
that gave its descriptor. Positions are refined in information form, so a landmark seen from several places
gets its height as well as its ground position.
"""

from __future__ import annotations

import numpy as np

from auxgps.core.features import DESCRIPTOR_BYTES

_TRIU = (np.array([0, 0, 0, 1, 1, 2]), np.array([0, 1, 2, 1, 2, 2]))


def pack_sym(M: np.ndarray) -> np.ndarray:
    """(..., 3, 3) symmetric -> (..., 6) upper triangle."""
    return M[..., _TRIU[0], _TRIU[1]]


def unpack_sym(v: np.ndarray) -> np.ndarray:
    """(..., 6) upper triangle -> (..., 3, 3) symmetric."""
    v = np.asarray(v, float)
    M = np.empty(v.shape[:-1] + (3, 3))
    M[..., _TRIU[0], _TRIU[1]] = v
    M[..., _TRIU[1], _TRIU[0]] = v
    return M


class LandmarkMap:
    """A growable column store of landmarks. Ids are row indices and never change."""

    def __init__(self, capacity: int = 1024, descriptor_bytes: int = DESCRIPTOR_BYTES) -> None:
        self._n = 0
        self.descriptors = np.zeros((capacity, descriptor_bytes), np.uint8)
        self.p_ned_m = np.zeros((capacity, 3), np.float32)
        self.info_packed = np.zeros((capacity, 6), np.float32)
        self.n_seen = np.zeros(capacity, np.uint16)
        self.view_cos = np.zeros(capacity, np.float16)
        self.chi2_mean = np.zeros(capacity, np.float16)
        self.n_visible = np.zeros(capacity, np.uint16)

    def __len__(self) -> int:
        return self._n

    @property
    def nbytes(self) -> int:
        """Bytes held per stored landmark times the count (capacity slack excluded)."""
        per = sum(a.itemsize * (a.size // len(a)) for a in self._columns())
        return per * self._n

    def _columns(self):
        return (self.descriptors, self.p_ned_m, self.info_packed, self.n_seen, self.view_cos, self.chi2_mean, self.n_visible)

    def _grow(self, need: int) -> None:
        cap = len(self.n_seen)
        if need <= cap:
            return
        new_cap = max(need, 2 * cap)
        for name in ("descriptors", "p_ned_m", "info_packed", "n_seen", "view_cos", "chi2_mean", "n_visible"):
            old = getattr(self, name)
            new = np.zeros((new_cap,) + old.shape[1:], old.dtype)
            new[: self._n] = old[: self._n]
            setattr(self, name, new)

    def add(self, descriptors: np.ndarray, p_ned_m: np.ndarray, info: np.ndarray, view_cos: np.ndarray) -> np.ndarray:
        """Append landmarks seen once. info (M, 3, 3) 1/m^2. Returns their ids (M,)."""
        m = len(descriptors)
        self._grow(self._n + m)
        ids = np.arange(self._n, self._n + m)
        self.descriptors[ids] = descriptors
        self.p_ned_m[ids] = p_ned_m
        self.info_packed[ids] = pack_sym(info)
        self.n_seen[ids] = 1
        self.view_cos[ids] = view_cos
        self.chi2_mean[ids] = 0.0
        self.n_visible[ids] = 1
        self._n += m
        return ids

    def observe(
        self, ids: np.ndarray, A_obs: np.ndarray, b_obs: np.ndarray, descriptors: np.ndarray, view_cos: np.ndarray, chi2: np.ndarray
    ) -> None:
        """Fuse one observation into each landmark in ``ids`` (unique).

        The observation is in information form: ``A_obs`` (M, 3, 3) 1/m^2 and ``b_obs = A_obs @ point`` (M, 3);
        ``chi2`` (M,) is its squared Mahalanobis innovation, averaged into the landmark's consistency. The
        landmark keeps the descriptor of its most nadir view.
        """
        n_before = self.n_seen[ids].astype(np.float32)
        self.chi2_mean[ids] = (self.chi2_mean[ids].astype(np.float32) * (n_before - 1) + chi2) / n_before
        A = unpack_sym(self.info_packed[ids])
        b = np.einsum("nij,nj->ni", A, self.p_ned_m[ids].astype(float)) + b_obs
        A_new = A + A_obs
        self.p_ned_m[ids] = np.linalg.solve(A_new, b[..., None])[..., 0]
        self.info_packed[ids] = pack_sym(A_new)
        self.n_seen[ids] = np.minimum(self.n_seen[ids].astype(np.int32) + 1, np.iinfo(np.uint16).max)
        better = view_cos > self.view_cos[ids]
        self.descriptors[ids[better]] = descriptors[better]
        self.view_cos[ids[better]] = view_cos[better]

    def count_visible(self, ids: np.ndarray) -> None:
        """Count one more frame in which these landmarks were predicted inside the image."""
        self.n_visible[ids] = np.minimum(self.n_visible[ids].astype(np.int32) + 1, np.iinfo(np.uint16).max)

    def usable(self, ids: np.ndarray, min_seen: int, max_chi2: float, min_found_ratio: float) -> np.ndarray:
        """(M,) bool: seen at least ``min_seen`` times, in at least ``min_found_ratio`` of the frames that should
        have seen it, with views that agree (mean squared Mahalanobis innovation at most ``max_chi2``)."""
        n_seen = self.n_seen[ids].astype(np.int32)
        return (
            (n_seen >= min_seen)
            & (self.chi2_mean[ids] <= max_chi2)
            & (n_seen >= min_found_ratio * self.n_visible[ids].astype(np.int32))
        )

    def covariance(self, ids: np.ndarray) -> np.ndarray:
        """(M, 3, 3) position covariance, m^2."""
        return np.linalg.inv(unpack_sym(self.info_packed[ids]))

    def ids_in_box(self, north_range_m: tuple[float, float], east_range_m: tuple[float, float]) -> np.ndarray:
        """Ids of landmarks inside a north/east box (m)."""
        p = self.p_ned_m[: self._n]
        mask = (
            (p[:, 0] >= north_range_m[0])
            & (p[:, 0] <= north_range_m[1])
            & (p[:, 1] >= east_range_m[0])
            & (p[:, 1] <= east_range_m[1])
        )
        return np.flatnonzero(mask)
