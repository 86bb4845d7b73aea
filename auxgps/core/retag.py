"""Landmarks geotagged again when the heading is better known.

A mapping frame puts each landmark's ray into the map turned by the heading correction the solver
(:mod:`auxgps.core.heading`) had then. The first frames of a flight are mapped while it still knows little: its
estimate moves by a degree in the first seconds. A landmark seen from a leg with its rays turned by different
amounts is placed wrong across the leg, and at a wrong height too (a ray turned sideways looks like parallax), and
the return leg, beside the way out, positions on it.

So the map keeps, for the landmarks of this flight seen in the last ``heading.follow_s``, what is needed to turn
each of their views again about the vertical through its camera: sums over the views ``i`` (ray information
``A_i``, camera ``C_i = c_i + z_i e_down``, correction ``b_i``) from which the landmark's information and
information vector with every ray turned are formed. The turn all views share (the estimate's move since the map
was last turned) is applied exactly; what differs from view to view (under the turn step, ``heading.turn_step_deg``)
to first order. Older landmarks keep where they are. Off by default (``heading.follow_s: 0``): on a real SITL flight it
cost the fixes more than it gave (docs/missions.md, "The map turned as the solver learns").

Pure: arrays in, arrays out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from auxgps.core.geometry import pack_sym, solve_sym3, unpack_sym

#: A small clockwise turn about down (north toward east), per radian: ``d(R v) = K v dtheta``.
K = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
_E_DOWN = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class HeadingView:
    """The heading correction (rad, subtracted from the autopilot's heading) a mapping frame was geotagged with,
    and where its camera was (NED, m)."""

    heading_rad: float
    camera_ned_m: np.ndarray
    memory: float = 0.0  # the heading tracker's memory clock then (HeadingEstimate.memory)


class RecentViews:
    """Per landmark seen within the last few seconds, the sums :func:`turned` needs, in rows reused as landmarks
    age out (a map of a hundred thousand landmarks keeps rows for the ten thousand in view lately). Rows are
    appended into spare capacity and dropped in bulk, so a frame pays for its own views, not for the table.

    Row layout (float64): ``sum b_i A_i`` (packed, 6), ``sum b_i A_i c_i``, ``sum A_i K c_i``,
    ``sum b_i A_i K c_i``, ``sum z_i A_i e_down``, ``sum b_i z_i A_i e_down`` (3 each); ``c_i`` the camera's
    north/east (down 0), ``z_i`` its down."""

    WIDTH = 21
    GROWTH = 1.5

    def __init__(self) -> None:
        self._row_of = np.full(0, -1, np.int64)  # per landmark id: its row, -1 none
        self._n = 0
        self._ids = np.zeros(0, np.int64)  # per row: its landmark
        self._sums = np.zeros((0, self.WIDTH))
        self._t_last_s = np.zeros(0)
        self._memory_last = np.zeros(0)

    def __len__(self) -> int:
        return self._n

    @property
    def ids(self) -> np.ndarray:
        return self._ids[: self._n]

    @property
    def sums(self) -> np.ndarray:
        return self._sums[: self._n]

    @sums.setter
    def sums(self, value: np.ndarray) -> None:
        self._sums[: self._n] = value

    @property
    def nbytes(self) -> int:
        return int(self._row_of.nbytes + self._ids.nbytes + self._sums.nbytes + self._t_last_s.nbytes + self._memory_last.nbytes)

    def clear(self) -> None:
        self.__init__()

    def rows(self, ids: np.ndarray) -> np.ndarray:
        """The rows of ``ids``, -1 for those without one."""
        ids = np.asarray(ids, np.int64)
        out = np.full(len(ids), -1, np.int64)
        known = ids < len(self._row_of)
        out[known] = self._row_of[ids[known]]
        return out

    def _add_rows(self, ids: np.ndarray) -> np.ndarray:
        """New zero rows for ``ids`` (none of which has one); their row numbers."""
        m, n = len(ids), self._n
        if int(ids.max()) >= len(self._row_of):
            grown = np.full(max(int(ids.max()) + 1, int(self.GROWTH * len(self._row_of))), -1, np.int64)
            grown[: len(self._row_of)] = self._row_of
            self._row_of = grown
        if n + m > len(self._ids):
            cap = max(n + m, int(self.GROWTH * len(self._ids)) + 64)
            self._ids = np.concatenate([self._ids[:n], np.zeros(cap - n, np.int64)])
            self._sums = np.concatenate([self._sums[:n], np.zeros((cap - n, self.WIDTH))])
            self._t_last_s = np.concatenate([self._t_last_s[:n], np.zeros(cap - n)])
            self._memory_last = np.concatenate([self._memory_last[:n], np.zeros(cap - n)])
        rows = np.arange(n, n + m)
        self._ids[rows] = ids
        self._sums[rows] = 0.0
        self._row_of[ids] = rows
        self._n = n + m
        return rows

    def note(self, ids: np.ndarray, A: np.ndarray, t_s: float, view: HeadingView) -> None:
        """One view (at ``t_s``) of each landmark in ``ids`` (unique), with its ray information ``A`` (M, 3, 3)."""
        ids = np.asarray(ids, np.int64)
        if not len(ids):
            return
        rows = self.rows(ids)
        new = rows < 0
        if np.any(new):
            rows[new] = self._add_rows(ids[new])
        b = float(view.heading_rad)
        C = np.asarray(view.camera_ned_m, float)
        c = np.array([C[0], C[1], 0.0])
        z = float(C[2])
        Ac, AKc, Ae = A @ c, A @ (K @ c), A @ _E_DOWN
        S = self._sums[rows]
        S[:, 0:6] += b * pack_sym(A)
        S[:, 6:9] += b * Ac
        S[:, 9:12] += AKc
        S[:, 12:15] += b * AKc
        S[:, 15:18] += z * Ae
        S[:, 18:21] += b * z * Ae
        self._sums[rows] = S
        self._t_last_s[rows] = t_s
        self._memory_last[rows] = view.memory

    def forget(self, ids: np.ndarray) -> None:
        """Drop the rows of ``ids`` (their positions were put back by an undo: the sums no longer describe them)."""
        rows = self.rows(ids)
        dead = np.zeros(self._n, bool)
        dead[rows[rows >= 0]] = True
        self._keep(np.flatnonzero(~dead))

    def forget_before(self, t_s: float, memory: float = -np.inf, lazily: bool = False) -> None:
        """Drop the rows of landmarks last seen before ``t_s``, or before the memory clock read ``memory``;
        ``lazily``: only once they are a quarter of the rows (a frame need not copy the table for the few that aged
        since the last)."""
        old = (self._t_last_s[: self._n] < t_s) | (self._memory_last[: self._n] < memory)
        n_old = int(old.sum())
        if n_old and (not lazily or n_old >= max(256, self._n // 4)):
            self._keep(np.flatnonzero(~old))

    def _keep(self, rows: np.ndarray) -> None:
        if len(rows) == self._n:
            return
        self._row_of[self.ids] = -1
        k = len(rows)
        self._ids[:k], self._sums[:k] = self._ids[rows], self._sums[rows]
        self._t_last_s[:k], self._memory_last[:k] = self._t_last_s[rows], self._memory_last[rows]
        self._n = k
        self._row_of[self.ids] = np.arange(k)


def _k_commutator(m: np.ndarray) -> np.ndarray:
    """``K M - M K`` of symmetric ``M``, both packed (..., 6) (what a small turn adds to an information matrix)."""
    m00, m01, m02, m11, m12 = m[:, 0], m[:, 1], m[:, 2], m[:, 3], m[:, 4]
    return np.column_stack([-2.0 * m01, m00 - m11, -m12, 2.0 * m01, m02, np.zeros_like(m00)])


def _k(v: np.ndarray) -> np.ndarray:
    """``K v`` of vectors (..., 3)."""
    return np.column_stack([-v[:, 1], v[:, 0], np.zeros(len(v))])


def _turned_packed(a: np.ndarray, c: float, s: float) -> np.ndarray:
    """``R A R^T`` of symmetric ``A``, packed (..., 6), ``R`` the turn about down with cosine ``c`` and sine ``s``."""
    a00, a01, a02, a11, a12, a22 = a.T
    cs = c * s
    return np.column_stack([c * c * a00 - 2.0 * cs * a01 + s * s * a11, cs * (a00 - a11) + (c * c - s * s) * a01,
                            c * a02 - s * a12, s * s * a00 + 2.0 * cs * a01 + c * c * a11, s * a02 + c * a12, a22])


def turned_vectors(v: np.ndarray, c: float, s: float) -> np.ndarray:
    """``R v`` of vectors (..., 3)."""
    return np.column_stack([c * v[:, 0] - s * v[:, 1], s * v[:, 0] + c * v[:, 1], v[:, 2]])


def turned(sums: np.ndarray, info_packed: np.ndarray, p_ned_m: np.ndarray, heading_rad: float, from_rad: float
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Landmarks with information ``info_packed`` (M, 6) at ``p_ned_m`` (M, 3), every view of which is in ``sums``
    (M, :attr:`RecentViews.WIDTH`), with each view's ray turned about the vertical through its camera by
    ``b_i - heading_rad``: their new information (packed), positions and sums (every view now at ``heading_rad``).

    The views share ``from_rad`` (the correction the map was last turned to) but for a small part each,
    ``e_i = b_i - from_rad`` (the estimate moves by less than the turn step between turns): the common turn
    ``D = from_rad - heading_rad`` is applied exactly (a rotation of the landmark's rays, so that a landmark seen
    from one place, known well across its ray and hardly along it, keeps that shape), the ``e_i`` to first order.
    The information may hold a height prior beside the rays: a turn about the vertical leaves it."""
    b, beta = float(heading_rad), float(from_rad)
    D = beta - b
    cD, sD = float(np.cos(D)), float(np.sin(D))
    S = sums
    S1, S3, S4, S5, S6, S7 = S[:, 0:6], S[:, 6:9], S[:, 9:12], S[:, 12:15], S[:, 15:18], S[:, 18:21]
    A = unpack_sym(info_packed)
    G = np.einsum("nij,nj->ni", A, p_ned_m)  # sum A_i C_i
    S2 = G - S6  # sum A_i c_i
    # The small parts e_i, to first order: A_i -> A_i + e_i (K A_i - A_i K), and A_i C_i -> that times C_i.
    eA = S1 - beta * info_packed  # sum e_i A_i, packed
    eAC = (S3 - beta * S2) + (S7 - beta * S6)  # sum e_i A_i C_i
    eAKc = S5 - beta * S4  # sum e_i A_i K c_i
    A_e = info_packed + _k_commutator(eA)
    G_e = G + _k(eAC) - eAKc
    S4_e = S4 + _k(eAKc) + (S3 - beta * S2)  # - sum e_i A_i K K c_i = + sum e_i A_i c_i
    S6_e = S6 + _k(S7 - beta * S6)
    S2_e = G_e - S6_e
    # The common turn D, exactly: A_i -> R A_i R^T, so sum A_i' C_i = R sum A_i R^T C_i, and R^T c = cos c - sin K c.
    X = S2_e * cD - S4_e * sD + S6_e
    P_new = turned_vectors(solve_sym3(A_e, X), cD, sD)
    A_new = _turned_packed(A_e, cD, sD)
    S2_new = turned_vectors(S2_e * cD - S4_e * sD, cD, sD)
    S4_new = turned_vectors(S4_e * cD + S2_e * sD, cD, sD)
    S6_new = turned_vectors(S6_e, cD, sD)
    out = np.empty_like(S)
    out[:, 0:6] = b * A_new
    out[:, 6:9] = b * S2_new
    out[:, 9:12] = S4_new
    out[:, 12:15] = b * S4_new
    out[:, 15:18] = S6_new
    out[:, 18:21] = b * S6_new
    return A_new, P_new, out
