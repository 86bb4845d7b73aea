"""The landmark map: geotagged point features, stored as columns of compact arrays.

Each landmark keeps its ORB descriptor, its position in the local NED frame, the information matrix of that
position (the inverse covariance, upper triangle), how often it was seen, and how straight down the view was
that gave its descriptor and at what range it was taken (its scale). Positions are refined in information form, so a landmark seen from several places
gets its height as well as its ground position.

Recent changes can be kept in a journal (:meth:`LandmarkMap.keep_journal`) and undone back to a time
(:meth:`LandmarkMap.roll_back`): a GPS1 found dragged late has refined landmarks already mapped as well as added
new ones, and both must go back to what they were before the drag.

Landmarks near a place are found through a :class:`GridIndex` (a uniform north/east grid kept as (cell, id)
pairs sorted by cell), so the cost of a box query grows with what is in the box, not with the size of the map.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from auxgps.core.features import DESCRIPTOR_BYTES
from auxgps.core.geometry import pack_sym, unpack_sym
from auxgps.core.prior_map import FLIGHT, MapSource, main_source, shared_sigma_h_m
from auxgps.core.retag import HeadingView, RecentViews, turned_vectors, turned


def _sorted_unique(x: np.ndarray) -> np.ndarray:
    """``np.unique(x)`` for a 1-d integer array, by one sort: for the 2 500 ids of a query, NumPy 2.4's ``np.unique``
    took 0.32 ms and this 0.03."""
    x = np.sort(x)
    return x[np.concatenate([[True], x[1:] != x[:-1]])] if len(x) else x


class GridIndex:
    """Landmark ids by north/east grid cell, for box queries whose cost does not grow with the map.

    Entries are (cell key, id) pairs in two int32 arrays sorted by key; a cell's key is
    ``row * 2**16 + col`` with ``row, col`` the cell's north and east numbers offset into [0, 2**15), so one
    row of cells is one contiguous key range and a box is one binary search per row of cells it spans.
    Places beyond the grid's span (``cell_m * 2**15``, 65 km with 2 m cells) fall into its edge cells: still
    found, only slower.

    The index follows the map lazily: landmarks added since the last query, and landmarks that
    :meth:`LandmarkMap.observe` moved into another cell, are merged in (one linear merge, no full sort) at the
    next query. A moved landmark's old entry stays until the next full rebuild (when stale entries exceed half
    the live ones); queries check every hit against the current position, so stale entries only cost time.
    Memory: 8 bytes per entry.
    """

    _HALF = 1 << 14  # cell numbers are offset by this, so that [-HALF, HALF) cells around 0 fit in 15 bits

    def __init__(self, cell_m: float = 2.0) -> None:
        if not cell_m > 0:
            raise ValueError(f"cell_m must be positive, got {cell_m}")
        self.cell_m = float(cell_m)
        self.keys = np.zeros(0, np.int32)
        self.ids = np.zeros(0, np.int32)
        self.n_indexed = 0  # ids below this have an entry at the cell where they were when it was made
        self._moved: list[np.ndarray] = []
        self._n_stale = 0

    @property
    def nbytes(self) -> int:
        return int(self.keys.nbytes + self.ids.nbytes)

    def cell(self, coord_m: np.ndarray) -> np.ndarray:
        """Cell numbers (offset, clipped into the grid) of north or east coordinates, m -> int32."""
        c = np.floor(np.asarray(coord_m, np.float64) / self.cell_m) + self._HALF
        return np.clip(c, 0, 2 * self._HALF - 1).astype(np.int32)

    def key(self, p_ned_m: np.ndarray) -> np.ndarray:
        """(M, >=2) positions -> (M,) int32 cell keys."""
        return (self.cell(p_ned_m[:, 0]) << 16) | self.cell(p_ned_m[:, 1])

    def note_moved(self, ids: np.ndarray, p_before_ned_m: np.ndarray, p_after_ned_m: np.ndarray) -> None:
        """Record landmarks whose position changed; those now in another cell get a new entry at the next query."""
        ids = np.asarray(ids)
        indexed = ids < self.n_indexed
        if not np.any(indexed):
            return
        changed = indexed & (self.key(p_before_ned_m) != self.key(p_after_ned_m))
        if np.any(changed):
            self._moved.append(ids[changed].astype(np.int32))

    def invalidate(self) -> None:
        """Forget every entry: the next query rebuilds the index from the positions."""
        self.keys, self.ids = np.zeros(0, np.int32), np.zeros(0, np.int32)
        self.n_indexed, self._moved, self._n_stale = 0, [], 0

    def sync(self, p_ned_m: np.ndarray) -> None:
        """Bring the index up to date with the positions ``p_ned_m`` (n, 3) of landmarks 0 .. n-1."""
        n = len(p_ned_m)
        if n < self.n_indexed:
            self.invalidate()
        if self.n_indexed == n and not self._moved:
            return
        new_ids = np.arange(self.n_indexed, n, dtype=np.int32)
        if self._moved:
            moved = _sorted_unique(np.concatenate(self._moved))
            self._n_stale += len(moved)
            new_ids = np.concatenate([moved, new_ids])
        self._moved = []
        self.n_indexed = n
        if self._n_stale > max(n // 2, 1024):
            self._rebuild(p_ned_m)
            return
        new_keys = self.key(p_ned_m[new_ids])
        order = np.argsort(new_keys, kind="stable")
        new_keys, new_ids = new_keys[order], new_ids[order]
        at = np.searchsorted(self.keys, new_keys, side="right")
        self.keys = np.insert(self.keys, at, new_keys)
        self.ids = np.insert(self.ids, at, new_ids)

    def _rebuild(self, p_ned_m: np.ndarray) -> None:
        keys = self.key(p_ned_m)
        order = np.argsort(keys, kind="stable").astype(np.int32)
        self.keys, self.ids = keys[order], order
        self.n_indexed, self._moved, self._n_stale = len(p_ned_m), [], 0

    def query(self, p_ned_m: np.ndarray, north_range_m: tuple[float, float], east_range_m: tuple[float, float]) -> np.ndarray:
        """Sorted unique ids of landmarks whose position in ``p_ned_m`` (n, 3) lies inside the box (m, inclusive)."""
        self.sync(p_ned_m)
        n0, n1 = north_range_m
        e0, e1 = east_range_m
        if not (n0 <= n1 and e0 <= e1) or len(self.keys) == 0:
            return np.zeros(0, np.int64)
        # Cells of the bounds widened by a hair: positions are float32, bounds float64, and a landmark on a cell
        # border must not be missed by rounding. The exact test below removes what the widening lets in.
        slack = 1e-3 + 1e-6 * max(abs(n0), abs(n1), abs(e0), abs(e1))
        r0, r1 = self.cell(np.array([n0 - slack, n1 + slack]))
        c0, c1 = self.cell(np.array([e0 - slack, e1 + slack]))
        rows = np.arange(r0, r1 + 1, dtype=np.int32) << 16
        lo = np.searchsorted(self.keys, rows | c0, side="left")
        hi = np.searchsorted(self.keys, rows | c1, side="right")
        counts = hi - lo
        total = int(counts.sum())
        if total == 0:
            return np.zeros(0, np.int64)
        # Concatenated ranges lo[i]:hi[i] without a Python loop.
        starts = np.repeat(lo - np.concatenate([[0], np.cumsum(counts)[:-1]]), counts)
        hits = self.ids[starts + np.arange(total)]
        p = p_ned_m[hits]
        inside = (p[:, 0] >= n0) & (p[:, 0] <= n1) & (p[:, 1] >= e0) & (p[:, 1] <= e1)
        hits = hits[inside].astype(np.int64)
        return _sorted_unique(hits) if self._n_stale else np.sort(hits)  # a moved landmark may be in its old cell too


class LandmarkMap:
    """A growable column store of landmarks. Ids are row indices and never change.

    Positions are written through :meth:`add` and :meth:`observe`, which keep the spatial index
    (:class:`GridIndex`) in step; code that writes ``p_ned_m`` directly must call :meth:`reindex` after.
    """

    #: Capacity grows by this factor when full: room for amortised appends at a bounded memory slack.
    GROWTH = 1.5
    #: The per-landmark arrays, in the order of the map file (``t_first_s`` is not saved: see :meth:`from_columns`).
    COLUMNS = ("descriptors", "p_ned_m", "info_packed", "n_seen", "view_cos", "descriptor_range_m", "chi2_mean", "n_visible",
               "source", "t_first_s", "ray_bias_sum")
    #: Columns a map file may lack, and what they are then.
    OPTIONAL = {"t_first_s": -np.inf, "source": 0, "ray_bias_sum": 0.0}
    #: chi2_mean of a landmark :meth:`demote` took out of use (no view agreement is that bad).
    DEMOTED_CHI2 = np.float16(60000.0)
    #: What :meth:`observe` changes, and :meth:`count_visible`: what the journal keeps of each before the change.
    OBSERVED = ("descriptors", "p_ned_m", "info_packed", "n_seen", "view_cos", "descriptor_range_m", "chi2_mean", "ray_bias_sum")
    COUNTED = ("n_visible",)

    def __init__(self, capacity: int = 1024, index: GridIndex | None = None, descriptor_bytes: int = DESCRIPTOR_BYTES) -> None:
        self._n = 0
        self.index = index if index is not None else GridIndex()
        self.descriptors = np.zeros((capacity, descriptor_bytes), np.uint8)
        self.p_ned_m = np.zeros((capacity, 3), np.float32)
        self.info_packed = np.zeros((capacity, 6), np.float32)
        self.n_seen = np.zeros(capacity, np.uint16)
        self.view_cos = np.zeros(capacity, np.float16)
        # The range (m) from which the view that gave its descriptor saw it (over the detection scale, if that
        # frame was shrunk): a frame taken much closer must be shrunk to describe it alike. NaN: unknown.
        self.descriptor_range_m = np.full(capacity, np.nan, np.float16)
        self.chi2_mean = np.zeros(capacity, np.float16)
        self.n_visible = np.zeros(capacity, np.uint16)
        # When it was first geotagged, s on the estimator's clock; -inf: before this process (a loaded map).
        self.t_first_s = np.full(capacity, -np.inf, np.float32)
        # Which of ``sources`` it comes from: 0 this flight (or an earlier one's map), others prior maps, which
        # the flight uses to position but never refines (their error is the source's, shared by all of them).
        self.source = np.zeros(capacity, np.uint8)
        self.sources: list[MapSource] = [FLIGHT]
        # Sum over its views of 2 s^2 t d / sigma^2 (s: a view's angular sigma, t its range, d its unit ray, sigma
        # its cross-ray sigma), 1/m: what makes the closest point to noisy rays lie toward the cameras (see
        # :meth:`triangulation_bias_m`). Zero for a prior map's landmarks and those of a map file before version 5.
        self.ray_bias_sum = np.zeros((capacity, 3), np.float32)
        # This flight's recent views, for :meth:`turn` (not saved: a loaded map's landmarks are not turned).
        self.recent_views = RecentViews()
        self._journal: deque[tuple[float, np.ndarray, dict[str, np.ndarray]]] | None = None
        self._journal_span_s = 0.0
        self._journal_forgot_s = -np.inf  # the newest change the journal has let go of (it cannot undo to before it)

    @classmethod
    def from_columns(cls, columns: dict[str, np.ndarray], capacity: int | None = None,
                     sources: list[MapSource] | None = None) -> "LandmarkMap":
        """A map holding the given rows of every column (a map file's, or another map's), its index built now.

        ``columns``: each of :data:`COLUMNS` with the same number of rows (those of :data:`OPTIONAL` may be left
        out: a map file's landmarks were first seen before this process); ``capacity``: rows to allocate (at least
        that number); ``sources``: what the ``source`` column's numbers name (default: this flight alone)."""
        n_rows = len(columns["n_seen"]) if "n_seen" in columns else 0
        columns = {**{k: np.full((n_rows, 3) if k == "ray_bias_sum" else n_rows, v, np.float32) for k, v in cls.OPTIONAL.items()},
                   **columns}
        missing = [name for name in cls.COLUMNS if name not in columns]
        if missing:
            raise ValueError(f"landmark columns missing: {', '.join(missing)}")
        n = len(columns["n_seen"])
        if any(len(columns[name]) != n for name in cls.COLUMNS):
            raise ValueError("landmark columns of different lengths")
        lm = cls(capacity=max(n, capacity or 0, 16))
        for name in cls.COLUMNS:
            getattr(lm, name)[:n] = columns[name]
        lm._n = n
        if sources is not None:
            lm.sources = list(sources)
        if n and int(lm.source[:n].max()) >= len(lm.sources):
            raise ValueError(f"landmark source {int(lm.source[:n].max())} is not among the map's {len(lm.sources)} sources")
        if lm.sources[0] != FLIGHT:
            raise ValueError("source 0 of a flight map must be the flight itself")
        lm.sync_index()  # built here, so that the first frame is not the one that pays for it
        return lm

    def columns(self) -> dict[str, np.ndarray]:
        """The used rows of every column (views, not copies)."""
        return {name: getattr(self, name)[: self._n] for name in self.COLUMNS}

    def __len__(self) -> int:
        return self._n

    def clear(self) -> None:
        """Forget every landmark (a map refused after loading); capacity is kept."""
        self._n = 0
        self.sources = [FLIGHT]
        self.index.invalidate()
        self.recent_views.clear()
        if self._journal is not None:
            self._journal.clear()
            self._journal_forgot_s = -np.inf

    # -- the journal of recent changes ----------------------------------------------------------------------

    def keep_journal(self, span_s: float) -> None:
        """From now on, keep what :meth:`observe` and :meth:`count_visible` change for ``span_s`` seconds (of the
        times they are given), so that :meth:`roll_back` can undo it. 0: keep none."""
        self._journal = deque() if span_s > 0 else None
        self._journal_span_s = float(span_s)
        self._journal_forgot_s = -np.inf

    @property
    def journal_bytes(self) -> int:
        """Bytes the journal holds (0 without one)."""
        if not self._journal:
            return 0
        return sum(ids.nbytes + sum(v.nbytes for v in prior.values()) for _, ids, prior in self._journal)

    def _record(self, t_s: float | None, ids: np.ndarray, names: tuple[str, ...]) -> None:
        if self._journal is None or t_s is None or not len(ids):
            return
        self._journal.append((float(t_s), ids.astype(np.int32), {name: getattr(self, name)[ids].copy() for name in names}))
        while self._journal and self._journal[0][0] < t_s - self._journal_span_s:
            self._journal_forgot_s = max(self._journal_forgot_s, self._journal.popleft()[0])

    def roll_back(self, since_t_s: float) -> tuple[np.ndarray, np.ndarray, bool]:
        """Undo every journalled change made after ``since_t_s``, newest first, and take out of use (:meth:`demote`)
        the landmarks first geotagged after it. Returns the ids of older landmarks put back as they were, the ids
        taken out of use, and whether the journal reached back that far (False: changes older than its span could
        not be undone; the newer ones were)."""
        touched = []
        while self._journal and self._journal[-1][0] > since_t_s:
            _, ids, prior = self._journal.pop()
            p_before = self.p_ned_m[ids].copy()
            for name, value in prior.items():
                getattr(self, name)[ids] = value
            if "p_ned_m" in prior:
                self.index.note_moved(ids, p_before, self.p_ned_m[ids])
            touched.append(ids)
        new = np.flatnonzero(self.t_first_s[: self._n] > since_t_s)
        self.demote(new)
        restored = np.setdiff1d(np.concatenate(touched) if touched else np.zeros(0, int), new).astype(int)
        self.recent_views.forget(np.concatenate([restored, new]))  # put back or out of use: not turned again
        return restored, new, since_t_s >= self._journal_forgot_s

    @property
    def nbytes(self) -> int:
        """Bytes held per stored landmark times the count (capacity slack and index excluded)."""
        per = sum(a.itemsize * (a.size // len(a)) for a in self._columns())
        return per * self._n

    def memory_bytes(self) -> dict:
        """What the running map holds, bytes: ``columns`` (used rows), ``slack`` (allocated, unused rows),
        ``index`` (the spatial index), ``journal`` (recent changes, :meth:`keep_journal`) and their ``total``."""
        used = self.nbytes
        allocated = sum(a.nbytes for a in self._columns())
        index = self.index.nbytes
        journal = self.journal_bytes
        views = self.recent_views.nbytes
        return {"columns": used, "slack": allocated - used, "index": index, "journal": journal, "recent_views": views,
                "total": allocated + index + journal + views}

    def reindex(self) -> None:
        """Rebuild the spatial index at the next query (after positions were written directly)."""
        self.index.invalidate()

    def sync_index(self) -> None:
        """Bring the spatial index up to date now (after loading a map), not at the first query."""
        self.index.sync(self.p_ned_m[: self._n])

    def _columns(self):
        return tuple(getattr(self, name) for name in self.COLUMNS)

    def _grow(self, need: int) -> None:
        cap = len(self.n_seen)
        if need <= cap:
            return
        new_cap = max(need, int(self.GROWTH * cap) + 1)
        for name in self.COLUMNS:
            old = getattr(self, name)
            fill = np.nan if name == "descriptor_range_m" else self.OPTIONAL.get(name, 0)
            new = np.full((new_cap,) + old.shape[1:], fill, old.dtype)
            new[: self._n] = old[: self._n]
            setattr(self, name, new)

    def add(self, descriptors: np.ndarray, p_ned_m: np.ndarray, info: np.ndarray, view_cos: np.ndarray,
            descriptor_range_m: np.ndarray | float = np.nan, t_first_s: float = -np.inf, view: HeadingView | None = None,
            ray_bias: np.ndarray | None = None) -> np.ndarray:
        """Append landmarks seen once (at ``t_first_s``). info (M, 3, 3) 1/m^2. Returns their ids (M,). ``view``:
        the heading correction they were geotagged with, and from where (for :meth:`turn`); ``ray_bias`` (M, 3)
        1/m: the view's term of :attr:`ray_bias_sum` (None: none)."""
        m = len(descriptors)
        self._grow(self._n + m)
        ids = np.arange(self._n, self._n + m)
        self.descriptors[ids] = descriptors
        self.p_ned_m[ids] = p_ned_m
        self.info_packed[ids] = pack_sym(info)
        self.n_seen[ids] = 1
        self.view_cos[ids] = view_cos
        self.descriptor_range_m[ids] = descriptor_range_m
        self.chi2_mean[ids] = 0.0
        self.n_visible[ids] = 1
        self.t_first_s[ids] = t_first_s
        self.source[ids] = 0
        self.ray_bias_sum[ids] = 0.0 if ray_bias is None else ray_bias
        self._n += m
        if view is not None and np.isfinite(t_first_s):
            self.recent_views.note(ids, info, t_first_s, view)
        return ids

    def demote(self, ids: np.ndarray) -> None:
        """Take landmarks out of use for good (geotagged from a GPS1 found dragged): never :meth:`usable` again,
        and kept, so that ids do not change."""
        self.chi2_mean[ids] = self.DEMOTED_CHI2

    def observe(
        self, ids: np.ndarray, A_obs: np.ndarray, b_obs: np.ndarray, descriptors: np.ndarray, view_cos: np.ndarray, chi2: np.ndarray,
        descriptor_range_m: np.ndarray | float = np.nan, t_s: float | None = None, view: HeadingView | None = None,
        ray_bias: np.ndarray | None = None,
    ) -> None:
        """Fuse one observation into each landmark in ``ids`` (unique).

        The observation is in information form: ``A_obs`` (M, 3, 3) 1/m^2 and ``b_obs = A_obs @ point`` (M, 3);
        ``chi2`` (M,) is its squared Mahalanobis innovation, averaged into the landmark's consistency. The
        landmark keeps the descriptor of its most nadir view, and that view's ``descriptor_range_m``. ``t_s``: when
        it was seen, for the journal (None: not journalled); ``view``: the heading correction the observation was
        geotagged with, and from where (for :meth:`turn`; only landmarks of this flight keep it); ``ray_bias`` (M,
        3) 1/m: the observation's term of :attr:`ray_bias_sum`.
        """
        self._record(t_s, ids, self.OBSERVED)
        n_before = self.n_seen[ids].astype(np.float32)
        self.chi2_mean[ids] = (self.chi2_mean[ids].astype(np.float32) * (n_before - 1) + chi2) / n_before
        A = unpack_sym(self.info_packed[ids])
        b = np.einsum("nij,nj->ni", A, self.p_ned_m[ids].astype(float)) + b_obs
        A_new = A + A_obs
        p_before = self.p_ned_m[ids]
        self.p_ned_m[ids] = np.linalg.solve(A_new, b[..., None])[..., 0]
        self.index.note_moved(ids, p_before, self.p_ned_m[ids])
        self.info_packed[ids] = pack_sym(A_new)
        if ray_bias is not None:
            self.ray_bias_sum[ids] += ray_bias
        self.n_seen[ids] = np.minimum(self.n_seen[ids].astype(np.int32) + 1, np.iinfo(np.uint16).max)
        better = view_cos > self.view_cos[ids]
        self.descriptors[ids[better]] = descriptors[better]
        self.view_cos[ids[better]] = view_cos[better]
        self.descriptor_range_m[ids[better]] = np.broadcast_to(descriptor_range_m, ids.shape)[better]
        if view is not None and t_s is not None:
            own = np.isfinite(self.t_first_s[ids]) & (self.recent_views.rows(ids) >= 0)  # every view of it since its first
            self.recent_views.note(ids[own], A_obs[own], t_s, view)

    def turn(self, heading_rad: float, from_rad: float, seen_since_s: float, memory_since: float = -np.inf) -> np.ndarray:
        """Geotag again, with the heading correction ``heading_rad``, the landmarks this flight has seen since
        ``seen_since_s`` (and since the heading tracker's memory clock read ``memory_since``), their views geotagged
        with ``from_rad`` or within a small step of it (:func:`auxgps.core.retag.turned`); forget the views of
        older ones. Returns the ids turned. Not journalled: :meth:`roll_back` puts a landmark's position and information back together, as the last
        observation before the undo point left them, and forgets its views."""
        views = self.recent_views
        views.forget_before(seen_since_s, memory_since)
        ids = views.ids
        if not len(ids):
            return ids
        info, p, sums = turned(views.sums, self.info_packed[ids].astype(float), self.p_ned_m[ids].astype(float), heading_rad,
                               from_rad)
        p_before = self.p_ned_m[ids].copy()
        self.p_ned_m[ids] = p
        self.info_packed[ids] = info
        D = float(from_rad) - float(heading_rad)  # the views' rays turn by this, and with them the bias sum
        self.ray_bias_sum[ids] = turned_vectors(self.ray_bias_sum[ids].astype(float), float(np.cos(D)), float(np.sin(D)))
        self.index.note_moved(ids, p_before, self.p_ned_m[ids])
        views.sums = sums
        return ids.copy()

    def count_visible(self, ids: np.ndarray, t_s: float | None = None) -> None:
        """Count one more frame (taken at ``t_s``, for the journal) in which these landmarks were predicted inside
        the image."""
        self._record(t_s, ids, self.COUNTED)
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

    def merge(self, other: "LandmarkMap", p_ned_m: np.ndarray | None = None) -> np.ndarray:
        """Append every landmark of ``other``, at ``p_ned_m`` (N, 3) if given (its positions in this map's frame;
        default: the same frame), its sources after this map's (a flight source of ``other`` stays this map's
        source 0). Information matrices are kept as they are (frames a few km apart differ in their axes by
        under a milliradian). Returns their new ids."""
        if other.descriptors.shape[1] != self.descriptors.shape[1]:
            raise ValueError("maps of different descriptors cannot be merged")
        cols = other.columns()
        n = len(other)
        renumber = np.zeros(len(other.sources), np.uint8)
        for k, src in enumerate(other.sources):
            if k == 0:
                continue
            if len(self.sources) >= 255:
                raise ValueError("too many map sources (255 at most)")
            self.sources.append(src)
            renumber[k] = len(self.sources) - 1
        self._grow(self._n + n)
        ids = np.arange(self._n, self._n + n)
        for name in self.COLUMNS:
            getattr(self, name)[ids] = cols[name]
        if p_ned_m is not None:
            self.p_ned_m[ids] = np.asarray(p_ned_m, np.float32)
        self.source[ids] = renumber[cols["source"]]
        self._n += n
        return ids

    def shared_sigma_h_m(self, ids: np.ndarray) -> float:
        """The horizontal offset these landmarks share through their sources (m, one sigma): each source's
        placement error, weighed by its share of ``ids`` (variances)."""
        if len(ids) == 0 or len(self.sources) == 1:
            return 0.0
        return shared_sigma_h_m(self.source, self.sources, ids)

    def source_name(self, ids: np.ndarray) -> str:
        """The source most of ``ids`` come from (its ``name``, or its kind), for the logs."""
        if len(ids) == 0:
            return ""
        src = main_source(self.source, self.sources, ids)
        return src.name or src.kind

    def covariance(self, ids: np.ndarray) -> np.ndarray:
        """(M, 3, 3) position covariance, m^2: the information's cofactors over its determinant (a tenth of the
        time of a batched matrix inverse, which the mapper would pay on every candidate of every frame)."""
        c00, c01, c02, c11, c12, c22, det = self._cofactors(ids)
        return unpack_sym(np.column_stack([c00, c01, c02, c11, c12, c22]) / det[:, None])

    def variance_across_rays_m2(self, ids: np.ndarray, d_ned: np.ndarray, with_bias: bool = True) -> np.ndarray:
        """(M,) a landmark's position variance across the unit ray ``d_ned`` (M, 3) it is seen along, per axis,
        m^2: half the trace of ``(I - d d^T) C (I - d d^T)``, so that off nadir its height error counts as well.
        From the cofactors of the information matrix rather than a matrix inverse per landmark (the localiser
        asks for it at every reading)."""
        c00, c01, c02, c11, c12, c22, det = self._cofactors(ids)
        x, y, z = np.asarray(d_ned, float).T
        along = c00 * x * x + c11 * y * y + c22 * z * z + 2.0 * (c01 * x * y + c02 * x * z + c12 * y * z)
        var = 0.5 * (c00 + c11 + c22 - along) / det
        if not with_bias:
            return var
        # The triangulation's expected bias (see :meth:`triangulation_bias_m`) counts as error: its square across
        # the ray, half to each axis (mean squared error = variance + bias^2).
        b0, b1, b2 = self._bias_from_cofactors(ids, c00, c01, c02, c11, c12, c22, det)
        b_along = b0 * x + b1 * y + b2 * z
        return var + 0.5 * (b0 * b0 + b1 * b1 + b2 * b2 - b_along * b_along)

    def height_mse_m2(self, ids: np.ndarray) -> np.ndarray:
        """(M,) each landmark's mean squared height error, m^2: its height variance and the square of its
        triangulation's expected bias down (see :meth:`triangulation_bias_m`)."""
        c = self._cofactors(ids)
        return c[5] / c[6] + self._bias_from_cofactors(ids, *c)[2] ** 2

    def triangulation_bias_m(self, ids: np.ndarray) -> np.ndarray:
        """(M, 3) m: how far the map's placement of each landmark is expected to lie from it, toward the cameras
        that saw it: ``-A^-1 sum 2 s^2 t d / sigma^2`` (A its information). The point closest to rays whose
        directions are noisy (angular sigma ``s`` per axis) lies that way, by about ``2 s^2`` over the squared
        parallax of the range (``tools/triangulation_bias.py``): 0.2 m for eleven views over 9 m from 40 m at
        3.8 mrad, and all but nothing once views span the footprint. Not taken off the position: where the
        parallax is as small as the noise the estimate overshoots (docs/missions.md); it is counted as error."""
        return np.column_stack(self._bias_from_cofactors(ids, *self._cofactors(ids)))

    def _cofactors(self, ids: np.ndarray) -> tuple[np.ndarray, ...]:
        """The cofactors of each landmark's information (c00, c01, c02, c11, c12, c22) and its determinant: its
        covariance is their matrix over the determinant."""
        a00, a01, a02, a11, a12, a22 = self.info_packed[ids].astype(float).T
        c00, c11, c22 = a11 * a22 - a12 * a12, a00 * a22 - a02 * a02, a00 * a11 - a01 * a01
        c01, c02, c12 = a02 * a12 - a01 * a22, a01 * a12 - a02 * a11, a01 * a02 - a00 * a12
        return c00, c01, c02, c11, c12, c22, a00 * c00 + a01 * c01 + a02 * c02

    def _bias_from_cofactors(self, ids, c00, c01, c02, c11, c12, c22, det) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`triangulation_bias_m`'s north, east and down, ``-C g``, from the cofactors of the information."""
        g0, g1, g2 = self.ray_bias_sum[ids].astype(float).T
        return (-(c00 * g0 + c01 * g1 + c02 * g2) / det, -(c01 * g0 + c11 * g1 + c12 * g2) / det,
                -(c02 * g0 + c12 * g1 + c22 * g2) / det)

    def deepest_down_m(self) -> float:
        """The largest NED down of any landmark, m (-inf for an empty map): how deep a camera's view must reach."""
        return float(self.p_ned_m[: self._n, 2].max()) if self._n else -np.inf

    def ids_in_box(self, north_range_m: tuple[float, float], east_range_m: tuple[float, float]) -> np.ndarray:
        """Sorted ids of landmarks inside a north/east box (m, bounds included), through the spatial index."""
        return self.index.query(self.p_ned_m[: self._n], north_range_m, east_range_m)

    def ids_in_box_scan(self, north_range_m: tuple[float, float], east_range_m: tuple[float, float]) -> np.ndarray:
        """The same as :meth:`ids_in_box` by a scan of every landmark: the reference the index is tested against."""
        p = self.p_ned_m[: self._n]
        mask = (
            (p[:, 0] >= north_range_m[0])
            & (p[:, 0] <= north_range_m[1])
            & (p[:, 1] >= east_range_m[0])
            & (p[:, 1] <= east_range_m[1])
        )
        return np.flatnonzero(mask)
