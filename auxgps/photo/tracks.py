"""Pairwise matches chained into tracks, and the first guess of every photo's pose and every track's point.

The first guess needs no attitude metadata (see :func:`_initial_poses`), so a photo whose pixels were turned
is placed right.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from auxgps.core.camera import PinholeCamera
from auxgps.photo.types import MapPhoto, R_ned_cam_nadir, _wrap


@dataclass
class _Tracks:
    """Observations sorted by track: photo index, keypoint index, pixel (full res) per observation."""

    track: np.ndarray
    photo: np.ndarray
    kp: np.ndarray
    uv: np.ndarray
    n_tracks: int


def _build_tracks(photos: list[MapPhoto], pair_matches: dict) -> _Tracks:
    offsets = np.concatenate([[0], np.cumsum([len(p.features) for p in photos])])
    rows, cols = [], []
    for (i, j), (ia, ib) in pair_matches.items():
        rows.append(offsets[i] + ia)
        cols.append(offsets[j] + ib)
    n = int(offsets[-1])
    r, c = np.concatenate(rows), np.concatenate(cols)
    graph = coo_matrix((np.ones(len(r)), (r, c)), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    used = np.zeros(n, bool)
    used[r] = used[c] = True
    nodes = np.flatnonzero(used)
    photo_of = np.searchsorted(offsets, nodes, side="right") - 1
    lab = label[nodes]
    # A track that holds two keypoints of one photo joined two different places: drop it.
    key = lab.astype(np.int64) * len(photos) + photo_of
    uniq, counts = np.unique(key, return_counts=True)
    bad_labels = np.unique(uniq[counts > 1] // len(photos))
    ok = ~np.isin(lab, bad_labels)
    nodes, photo_of, lab = nodes[ok], photo_of[ok], lab[ok]
    _, track = np.unique(lab, return_inverse=True)
    order = np.argsort(track, kind="stable")
    nodes, photo_of, track = nodes[order], photo_of[order], track[order]
    kp = nodes - offsets[photo_of]
    uv = np.vstack([photos[p].features.uv_px[k] for p, k in zip(photo_of, kp)]) if len(nodes) else np.zeros((0, 2))
    return _Tracks(track, photo_of, kp, uv, int(track.max() + 1) if len(track) else 0)


def _initial_poses(photos: list[MapPhoto], cams: list[PinholeCamera], pair_matches: dict, gps_sigma_m: float) -> list[tuple[np.ndarray, np.ndarray] | None]:
    """First guess of each photo's pose, with no attitude metadata.

    Each photo is taken as a similarity from its normalised image point z = x + iy to the ground (north + i
    east): ``a z + b`` (heading and height in the complex ``a``, ground point under the principal point ``b``).
    Each overlapping pair gives, robustly (RANSAC, so trees and roofs do not bend it), ``a_j / a_i`` and
    ``(b_j - b_i) / a_i``. Their logarithms are averaged over the overlap graph, which fixes every ``a`` up to
    one common factor ``G``; then ``G`` and every ``b`` are one linear least-squares solve, with the pairs'
    offsets and each photo's GPS. Returns (R_ned_cam, C_ned) per photo, or None for one that is not connected.
    """
    n = len(photos)
    rel = {}
    for (i, j), (ia, ib) in pair_matches.items():
        p = cams[i].pixels_to_normalized(photos[i].features.uv_px[ia])
        q = cams[j].pixels_to_normalized(photos[j].features.uv_px[ib])
        M, inl = cv2.estimateAffinePartial2D(q, p, method=cv2.RANSAC, ransacReprojThreshold=0.02, maxIters=5000)
        if M is None or inl is None or inl.sum() < 8:
            continue
        r = complex(M[0, 0], M[1, 0])
        if abs(r) < 1e-3:
            continue
        rel[(i, j)] = (r, complex(M[0, 2], M[1, 2]), int(inl.sum()))
    # log a: magnitudes by linear least squares; angles along a maximum spanning tree, then averaged.
    adj: dict[int, list] = {k: [] for k in range(n)}
    for (i, j), (r, t, w) in rel.items():
        adj[i].append((j, np.log(r), w))
        adj[j].append((i, -np.log(r), w))
    root = max(range(n), key=lambda k: sum(w for _, _, w in adj[k]))
    logs: dict[int, complex] = {root: 0j}
    frontier = [root]
    while frontier:  # breadth first, strongest overlaps first
        nxt = []
        for i in frontier:
            for j, lr, w in sorted(adj[i], key=lambda e: -e[2]):
                if j not in logs:
                    logs[j] = logs[i] + lr
                    nxt.append(j)
        frontier = nxt
    for _ in range(10):  # each photo moves to the weighted mean its neighbours imply (angles wrapped)
        for i in logs:
            num, den = 0j, 0.0
            for j, lr, w in adj[i]:
                if j in logs:
                    imp = logs[j] - lr
                    d = imp - logs[i]
                    imp = logs[i] + complex(d.real, _wrap(d.imag))
                    num += w * imp
                    den += w
            if den > 0 and i != root:
                logs[i] = num / den
    # G and b: b_j - b_i = a_i t_ij = G exp(l_i) t_ij, and b_i = gps_i.
    known = sorted(logs)
    col = {k: c for c, k in enumerate(known)}
    m = len(known)
    rows, rhs, wts = [], [], []
    sigma_pair_m = 0.3  # how well one overlap fixes two photos' relative placement
    for (i, j), (r, t, w) in rel.items():
        if i in col and j in col:
            row = np.zeros(m + 1, complex)
            row[col[j]], row[col[i]], row[m] = 1.0, -1.0, -np.exp(logs[i]) * t
            rows.append(row)
            rhs.append(0j)
            wts.append(1.0 / sigma_pair_m)
    for k in known:
        if photos[k].prior.gps_ne_m is not None:
            row = np.zeros(m + 1, complex)
            row[col[k]] = 1.0
            rows.append(row)
            rhs.append(complex(*photos[k].prior.gps_ne_m))
            wts.append(1.0 / gps_sigma_m)
    w = np.array(wts)
    sol = np.linalg.lstsq(np.array(rows) * w[:, None], np.array(rhs) * w, rcond=None)[0]
    G = sol[m]
    out: list = []
    for k, p in enumerate(photos):
        if k not in col or abs(G) < 1e-6:
            out.append(None)
            continue
        a = G * np.exp(logs[k])
        b = sol[col[k]]
        R = R_ned_cam_nadir(float(np.angle(a)) - np.pi / 2)  # the camera's x axis points along arg(a)
        height = p.prior.height_m if p.prior.height_m is not None else float(abs(a))
        out.append((R, np.array([b.real, b.imag, -height])))
    return out


def _triangulate_midpoint(C: np.ndarray, rays: np.ndarray, track: np.ndarray, n_tracks: int) -> np.ndarray:
    """Least-squares intersection of rays ``C[k] + t rays[k]`` grouped by ``track``. Returns (n_tracks, 3)."""
    P = np.eye(3)[None] - rays[:, :, None] * rays[:, None, :]
    A = np.zeros((n_tracks, 3, 3))
    b = np.zeros((n_tracks, 3))
    np.add.at(A, track, P)
    np.add.at(b, track, np.einsum("nij,nj->ni", P, C))
    A += np.eye(3)[None] * 1e-9
    return np.linalg.solve(A, b[..., None])[..., 0]


def _initial_points(C: np.ndarray, R: np.ndarray, tracks: _Tracks, rays: np.ndarray) -> np.ndarray:
    """Each track's point: the rays' least-squares intersection where it lies well in front of every camera
    that sees it, else (near-parallel rays) the mean of the rays' crossings of the scene's median level."""
    X = _triangulate_midpoint(C[tracks.photo], rays, tracks.track, tracks.n_tracks)
    depth = np.einsum("nj,nj->n", X[tracks.track] - C[tracks.photo], R[tracks.photo][:, :, 2])
    height = np.median(np.abs(C[:, 2] - np.median(X[:, 2])))
    good = np.ones(tracks.n_tracks, bool)
    np.logical_and.at(good, tracks.track, (depth > 0.2 * height) & (depth < 5.0 * height))
    level = np.median(X[good, 2]) if good.any() else 0.0
    t = (level - C[tracks.photo, 2]) / np.where(np.abs(rays[:, 2]) > 1e-3, rays[:, 2], 1e-3)
    on_level = C[tracks.photo] + t[:, None] * rays
    mean = np.zeros((tracks.n_tracks, 3))
    np.add.at(mean, tracks.track, on_level)
    mean /= np.bincount(tracks.track, minlength=tracks.n_tracks)[:, None]
    X[~good] = mean[~good]
    return X
