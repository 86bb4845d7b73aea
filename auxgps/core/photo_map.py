"""Landmark maps from geotagged photos, and photos located against them alone.

Mapping (:func:`build_photo_map`)
    Overlapping photos are matched pairwise (SIFT, rotation-invariant, Lowe's ratio test both ways, then a
    fundamental matrix by MAGSAC++), and the matches are chained into tracks. A first guess of every photo's
    heading, height and ground position comes from a linear solve that treats each photo as a similarity map to
    the ground, tied to its GPS: it needs no attitude metadata, so a photo whose pixels were turned (a viewer
    re-saved it) is placed right, and its metadata is reported as wrong. A bundle adjustment then solves every
    photo's full pose, the shared focal length and radial distortion of each camera, and the tracks' 3D points,
    with each photo's GPS (and height above take-off, when known) as a soft prior. Every 3D point is thus seen
    from several photos and geotagged by all of their GPS positions at once, so a single receiver's error is
    averaged over the survey instead of copied into the points it saw. Each point keeps its information matrix
    (from its rays) and one descriptor (the medoid of its views).

Locating (:class:`PhotoLocator`)
    A photo's features are matched to the map's points (FLANN, ratio test), the full camera pose is found by
    PnP inside RANSAC and refined by robust least squares. Its metadata (attitude, height) is a prior that is
    checked, never trusted: the fix reports where it disagrees. The reported covariance joins the fit's
    (scaled by its own residuals) and the map's georeferencing uncertainty. A photo with too little support
    (another place, no overlap, a blank or corrupt image) gets a reason and no fix.

Frames: local NED (m) about the map's origin; camera frame OpenCV (x right, y down, z forward); ``R_ned_cam``
maps camera into NED. Pixels are full-resolution pixels of the stored photo.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial.transform import Rotation

from auxgps.core.camera import PinholeCamera
from auxgps.core.geometry import cross_matrix
from auxgps.errors import PhotoMapError

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


def detect_sift(gray: np.ndarray, scale: float, n_features: int) -> PhotoFeatures:
    """SIFT features of a (H, W) uint8 image that is the stored photo reduced by ``scale`` (>= 1).

    Keypoints are returned in the stored photo's pixels. SIFT's orientation makes them rotation-invariant, so
    a photo flown the other way still matches.
    """
    sift = cv2.SIFT_create(nfeatures=int(n_features))
    keypoints, desc = sift.detectAndCompute(gray, None)
    if desc is None or not keypoints:
        return PhotoFeatures(np.zeros((0, 2)), np.zeros((0, SIFT_BYTES), np.uint8), np.zeros(0))
    uv = (np.array([kp.pt for kp in keypoints], float) + 0.5) * scale - 0.5
    size = np.array([kp.size for kp in keypoints], float) * scale
    # OpenCV's SIFT saturates its descriptor to 0..255 and stores it as float: uint8 is lossless.
    return PhotoFeatures(uv, np.clip(np.rint(desc), 0, 255).astype(np.uint8), size)


@dataclass(frozen=True)
class PhotoPrior:
    """What a photo's metadata says, as priors. Any of them may be None.

    gps_ne_m : (2,) north, east of the camera, m (the map's origin frame)
    height_m : camera height above the map origin (the take-off point), m
    R_ned_cam : (3, 3) attitude from the gimbal
    """

    gps_ne_m: np.ndarray | None = None
    height_m: float | None = None
    R_ned_cam: np.ndarray | None = None


@dataclass(frozen=True)
class MapPhoto:
    """One photo's input to mapping: its name, features, initial camera (intrinsics shared by ``camera_id``)."""

    name: str
    features: PhotoFeatures
    camera: PinholeCamera
    camera_id: str
    prior: PhotoPrior


@dataclass(frozen=True)
class SolvedPhoto:
    """A map photo's solved pose. ``gps_residual_ne_m`` (2,) solved minus GPS; ``yaw_vs_metadata_rad`` solved
    camera heading minus the gimbal's (None without one); ``rms_px`` the reprojection RMS of its
    ``n_observations`` kept observations (full-resolution px; None when not known, e.g. read from a map file)."""

    name: str
    p_cam_in_ned_m: np.ndarray
    R_ned_cam: np.ndarray
    n_observations: int
    gps_residual_ne_m: np.ndarray | None
    yaw_vs_metadata_rad: float | None
    rms_px: float | None = None


@dataclass(frozen=True)
class PhotoMap:
    """A map of 3D points geotagged from photos.

    p_ned_m : (M, 3) float64, m
    info_ned : (M, 3, 3) float64, information (inverse covariance) of each point's position relative to the
        others, 1/m^2; the map's common georeferencing error is ``georef_sigma_h_m``, not in here
    descriptors : (M, 128) uint8
    n_views : (M,) int
    cameras : camera id -> refined :class:`PinholeCamera`
    georef_sigma_h_m : one-sigma horizontal error of the whole map's placement on Earth, m (per axis)
    photos : the solved map photos
    messages : what happened to individual photos (left out, metadata found wrong), one line each
    """

    p_ned_m: np.ndarray
    info_ned: np.ndarray
    descriptors: np.ndarray
    n_views: np.ndarray
    cameras: dict
    georef_sigma_h_m: float
    photos: tuple
    messages: tuple = ()

    def __len__(self) -> int:
        return len(self.p_ned_m)


@dataclass(frozen=True)
class PhotoFix:
    """A located photo: camera position ``p_cam_in_ned_m`` (3,), attitude ``R_ned_cam`` (3, 3), position
    covariance ``cov_ned_m2`` (3, 3) (fit and map together), inlier count, reprojection RMS (px) and notes on
    where the photo's own metadata disagrees."""

    p_cam_in_ned_m: np.ndarray
    R_ned_cam: np.ndarray
    cov_ned_m2: np.ndarray
    n_inliers: int
    n_matches: int
    rms_px: float
    notes: tuple = ()

    @property
    def accuracy_m(self) -> float:
        """Horizontal one-sigma along the worst axis, m."""
        return float(np.sqrt(np.linalg.eigvalsh(self.cov_ned_m2[:2, :2])[-1]))


@dataclass(frozen=True)
class PhotoNoFix:
    """No position for this photo, and why."""

    reason: str
    n_inliers: int = 0
    n_matches: int = 0


# --------------------------------------------------------------------------------------------------- geometry


def camera_heading_rad(R_ned_cam: np.ndarray) -> float:
    """Heading of the image's up direction (-y of the camera) projected on the ground, rad from north."""
    up = R_ned_cam @ np.array([0.0, -1.0, 0.0])
    return float(np.arctan2(up[1], up[0]))


def R_ned_cam_nadir(heading_rad: float) -> np.ndarray:
    """A camera looking straight down with the image's top towards ``heading_rad`` (from north)."""
    c, s = np.cos(heading_rad), np.sin(heading_rad)
    # cam y (image down) points opposite the heading; cam x is cam y turned 90 degrees clockwise seen from above.
    x = np.array([-s, c, 0.0])
    y = np.array([-c, -s, 0.0])
    return np.column_stack([x, y, [0.0, 0.0, 1.0]])


def R_ned_cam_from_gimbal(roll_rad: float, pitch_rad: float, yaw_rad: float) -> np.ndarray:
    """Camera attitude from DJI gimbal angles (ZYX, NED): at zero the camera looks forward along the yaw with
    the image's top up; pitch -pi/2 looks straight down with the image's top along the yaw."""
    from auxgps.core.geometry import R_ned_body_from_euler

    R_gimbal_cam = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    return R_ned_body_from_euler(roll_rad, pitch_rad, yaw_rad) @ R_gimbal_cam


def _wrap(a: float) -> float:
    return float((a + np.pi) % (2 * np.pi) - np.pi)


class _Intrinsics:
    """Pinhole with two radial terms, vectorised: normalised camera points -> pixels."""

    @staticmethod
    def project(p_cam: np.ndarray, f: np.ndarray, cx: np.ndarray, cy: np.ndarray, k1: np.ndarray, k2: np.ndarray) -> np.ndarray:
        z = np.maximum(p_cam[:, 2], 0.1)  # a point behind the camera is far off, not infinitely far
        x, y = p_cam[:, 0] / z, p_cam[:, 1] / z
        r2 = x * x + y * y
        d = 1.0 + k1 * r2 + k2 * r2 * r2
        return np.column_stack([f * d * x + cx, f * d * y + cy])


# --------------------------------------------------------------------------------------------------- matching


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


# --------------------------------------------------------------------------------------------------- mapping


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


@dataclass
class _Model:
    """Everything the bundle adjustment moves: per photo R0 (fixed) and the small rotation and centre it
    solves; per camera id f, k1, k2 (cx, cy fixed); points."""

    R0: np.ndarray  # (n, 3, 3)
    cam_of_photo: np.ndarray  # (n,) camera-id index
    f0: np.ndarray  # (c,)
    cx: np.ndarray
    cy: np.ndarray


def _unpack(x, n, c, m):
    cam = x[: 6 * n].reshape(n, 6)
    intr = x[6 * n : 6 * n + 3 * c].reshape(c, 3)
    X = x[6 * n + 3 * c :].reshape(m, 3)
    return cam, intr, X


def _rotations(model: _Model, cam_params: np.ndarray) -> np.ndarray:
    return model.R0 @ Rotation.from_rotvec(cam_params[:, :3]).as_matrix()


def _project_obs(model, cam_params, intr, X, photo, pt_idx) -> np.ndarray:
    R = _rotations(model, cam_params)
    C = cam_params[:, 3:]
    d = X[pt_idx] - C[photo]
    p_cam = np.einsum("nji,nj->ni", R[photo], d)
    ci = model.cam_of_photo[photo]
    f = model.f0[ci] * np.exp(intr[ci, 0])
    return _Intrinsics.project(p_cam, f, model.cx[ci], model.cy[ci], intr[ci, 1], intr[ci, 2])


def _obs_jacobians(model, cam_params, intr, X, photo, pt_idx):
    """Predicted pixels (K, 2) and their Jacobians: (K, 2, 9) by the photo's rotation increment, centre and
    camera's (log f, k1, k2); (K, 2, 3) by the point."""
    R = _rotations(model, cam_params)[photo]
    C = cam_params[photo, 3:]
    ci = model.cam_of_photo[photo]
    f = model.f0[ci] * np.exp(intr[ci, 0])
    k1, k2 = intr[ci, 1], intr[ci, 2]
    Rt = np.transpose(R, (0, 2, 1))
    p = np.einsum("nij,nj->ni", Rt, X[pt_idx] - C)
    z = np.maximum(p[:, 2], 0.1)
    x, y = p[:, 0] / z, p[:, 1] / z
    r2 = x * x + y * y
    d = 1.0 + k1 * r2 + k2 * r2 * r2
    dd = 2.0 * (k1 + 2.0 * k2 * r2)  # d(d)/d(r2) * 2
    uv = np.column_stack([f * d * x + model.cx[ci], f * d * y + model.cy[ci]])
    J_uv_xy = np.empty((len(p), 2, 2))
    J_uv_xy[:, 0, 0] = f * (d + x * dd * x)
    J_uv_xy[:, 0, 1] = f * x * dd * y
    J_uv_xy[:, 1, 0] = f * y * dd * x
    J_uv_xy[:, 1, 1] = f * (d + y * dd * y)
    J_xy_p = np.zeros((len(p), 2, 3))
    J_xy_p[:, 0, 0] = J_xy_p[:, 1, 1] = 1.0 / z
    J_xy_p[:, 0, 2] = -x / z
    J_xy_p[:, 1, 2] = -y / z
    J_p = J_uv_xy @ J_xy_p
    J_cam = np.empty((len(p), 2, 9))
    J_cam[:, :, 0:3] = J_p @ cross_matrix(p)  # R = R_cur exp(w): p = exp(-w) R_cur^T (X - C) ~ p + p x w
    J_cam[:, :, 3:6] = -J_p @ Rt
    J_cam[:, 0, 6], J_cam[:, 1, 6] = f * d * x, f * d * y
    J_cam[:, 0, 7], J_cam[:, 1, 7] = f * x * r2, f * y * r2
    J_cam[:, 0, 8], J_cam[:, 1, 8] = f * x * r2 * r2, f * y * r2 * r2
    return uv, J_cam, J_p @ Rt


def _bundle_adjust(model, cam0, intr0, X0, photo, pt_idx, uv_obs, sigma_px, priors, refine_intrinsics, max_iterations,
                   focal_sigma_rel):
    """Levenberg-Marquardt bundle adjustment with the points eliminated (Schur complement) and Huber weights.

    ``priors`` = (gps_idx, gps_ne (G, 2), gps_sigma, h_idx, h_val, h_sigma): each photo's GPS position and
    height above the origin as soft constraints. With ``refine_intrinsics``, each camera's focal length is held
    to its starting value within ``focal_sigma_rel`` (relative, one sigma) and its distortion weakly to zero.
    Returns photo parameters (n, 6), intrinsics (c, 3) and points (m, 3).
    """
    n, c, m = len(cam0), len(intr0), len(X0)
    gps_idx, gps_ne, gps_sigma, h_idx, h_val, h_sigma = priors
    P = 6 * n + 3 * c
    cols = np.concatenate([6 * photo[:, None] + np.arange(6), 6 * n + 3 * model.cam_of_photo[photo][:, None] + np.arange(3)], axis=1)
    w_obs = 1.0 / sigma_px**2
    huber = 2.0  # sigmas

    def prior_terms(cam, intr):
        """Gradient and Hessian of the prior terms (photo positions, heights, distortion), and their cost."""
        g = np.zeros(P)
        H = np.zeros(P)
        cost = 0.0
        rg = cam[gps_idx, 3:5] - gps_ne
        for a in range(2):
            g[6 * gps_idx + 3 + a] += rg[:, a] / gps_sigma**2
            H[6 * gps_idx + 3 + a] += 1.0 / gps_sigma**2
        rh = -cam[h_idx, 5] - h_val
        g[6 * h_idx + 5] += -rh / h_sigma**2
        H[6 * h_idx + 5] += 1.0 / h_sigma**2
        cost += float(np.sum(rg**2) / gps_sigma**2 + np.sum(rh**2) / h_sigma**2)
        k_sigma = 0.5 if refine_intrinsics else 1e-6  # distortion pulled weakly to zero; fixed when not refined
        for a in range(3):
            sa = k_sigma if a > 0 else (focal_sigma_rel if refine_intrinsics else 1e-6)  # intr[:, 0] is log(f / f0)
            g[6 * n + 3 * np.arange(c) + a] += intr[:, a] / sa**2
            H[6 * n + 3 * np.arange(c) + a] += 1.0 / sa**2
            cost += float(np.sum(intr[:, a] ** 2) / sa**2)
        return g, H, cost

    def total_cost(cam, intr, X):
        uv = _project_obs(model, cam, intr, X, photo, pt_idx)
        e = np.linalg.norm(uv - uv_obs, axis=1) / sigma_px
        rho = np.where(e <= huber, e**2, 2 * huber * e - huber**2)
        return float(np.sum(rho)) + prior_terms(cam, intr)[2]

    cam, intr, X = cam0.copy(), intr0.copy(), X0.copy()
    lam = 1e-3
    cost = total_cost(cam, intr, X)
    for _ in range(max_iterations):
        uv, Jc, Jx = _obs_jacobians(model, cam, intr, X, photo, pt_idx)
        r = uv - uv_obs
        e = np.linalg.norm(r, axis=1) / sigma_px
        w = w_obs * np.where(e <= huber, 1.0, huber / np.maximum(e, 1e-12))
        U = np.zeros((P, P))
        gc = np.zeros(P)
        A = np.einsum("nki,nkj->nij", Jc, Jc) * w[:, None, None]
        np.add.at(U, (cols[:, :, None], cols[:, None, :]), A)
        np.add.at(gc, cols, np.einsum("nki,nk->ni", Jc, r) * w[:, None])
        V = np.zeros((m, 3, 3))
        np.add.at(V, pt_idx, np.einsum("nki,nkj->nij", Jx, Jx) * w[:, None, None])
        gx = np.zeros((m, 3))
        np.add.at(gx, pt_idx, np.einsum("nki,nk->ni", Jx, r) * w[:, None])
        Wk = np.einsum("nki,nkj->nij", Jc, Jx) * w[:, None, None]  # (K, 9, 3)
        gp, Hp, _ = prior_terms(cam, intr)
        U[np.diag_indices(P)] += Hp
        gc += gp
        while True:
            Ud = U + lam * np.diag(np.diag(U) + 1e-9)
            Vd = V + lam * (V * np.eye(3)[None]) + np.eye(3)[None] * 1e-9
            Vinv = np.linalg.inv(Vd)
            # Schur complement over pairs of observations of the same point.
            WV = np.einsum("nij,njk->nik", Wk, Vinv[pt_idx])  # (K, 9, 3)
            order = np.argsort(pt_idx, kind="stable")
            starts = np.searchsorted(pt_idx[order], np.arange(m))
            ends = np.searchsorted(pt_idx[order], np.arange(m), side="right")
            S = Ud.copy()
            counts = ends - starts
            for L in np.unique(counts):
                if L == 0:
                    continue
                pts = np.flatnonzero(counts == L)
                idx = order[starts[pts][:, None] + np.arange(L)]  # (p, L) observations of each such point
                for a in range(L):
                    ka = idx[:, a]
                    for b in range(L):
                        kb = idx[:, b]
                        blk = np.einsum("nij,nkj->nik", WV[ka], Wk[kb])
                        np.add.at(S, (cols[ka][:, :, None], cols[kb][:, None, :]), -blk)
            rhs = -gc.copy()
            np.add.at(rhs, cols, np.einsum("nij,nj->ni", WV, gx[pt_idx]))
            try:
                dc = np.linalg.solve(S, rhs)
            except np.linalg.LinAlgError:
                lam *= 10.0
                if lam > 1e8:
                    converged = True
                    break
                continue
            # Back-substitute the points: V dx = -gx - W^T dc.
            wt_dc = np.zeros((m, 3))
            np.add.at(wt_dc, pt_idx, np.einsum("nij,ni->nj", Wk, dc[cols]))
            dx = np.einsum("nij,nj->ni", Vinv, -gx - wt_dc)
            cam_new = cam.copy()
            cam_new[:, :6] += dc[: 6 * n].reshape(n, 6)
            # The rotation increment is applied on the right of the current rotation.
            R_cur = _rotations(model, cam)
            R_new = R_cur @ Rotation.from_rotvec(dc[: 6 * n].reshape(n, 6)[:, :3]).as_matrix()
            cam_new[:, :3] = Rotation.from_matrix(np.einsum("nji,njk->nik", model.R0, R_new)).as_rotvec()
            intr_new = intr + dc[6 * n :].reshape(c, 3)
            X_new = X + dx
            new_cost = total_cost(cam_new, intr_new, X_new)
            if new_cost < cost:
                converged = (cost - new_cost) < 1e-6 * cost
                cam, intr, X, cost = cam_new, intr_new, X_new, new_cost
                lam = max(lam / 10.0, 1e-7)
                break
            lam *= 10.0
            if lam > 1e8:
                converged = True
                break
        if converged:
            break
    return cam, intr, X


def _refine_points(model, cam_params, intr, X, photo, pt_idx, uv, sigma_px, iterations=6):
    """Gauss-Newton on each point alone (photos and intrinsics fixed). Returns points (m, 3), their
    information (m, 3, 3) 1/m^2 and each observation's reprojection error (px)."""
    m = len(X)
    R = _rotations(model, cam_params)
    C = cam_params[:, 3:]
    ci = model.cam_of_photo[photo]
    f = model.f0[ci] * np.exp(intr[ci, 0])
    Rt = np.transpose(R[photo], (0, 2, 1))
    w = 1.0 / sigma_px**2
    for _ in range(iterations + 1):
        p_cam = np.einsum("nij,nj->ni", Rt, X[pt_idx] - C[photo])
        z = np.maximum(p_cam[:, 2], 0.1)
        err = _project_obs(model, cam_params, intr, X, photo, pt_idx) - uv
        J_p = np.zeros((len(photo), 2, 3))
        J_p[:, 0, 0] = f / z
        J_p[:, 1, 1] = f / z
        J_p[:, 0, 2] = -f * p_cam[:, 0] / z**2
        J_p[:, 1, 2] = -f * p_cam[:, 1] / z**2
        J = J_p @ Rt
        H = np.zeros((m, 3, 3))
        g = np.zeros((m, 3))
        np.add.at(H, pt_idx, np.einsum("nki,nkj->nij", J, J) * w[:, None, None])
        np.add.at(g, pt_idx, np.einsum("nki,nk->ni", J, err) * w[:, None])
        if _ == iterations:
            break
        step = np.linalg.solve(H + np.eye(3)[None] * 1e-6, g[..., None])[..., 0]
        X = X - np.clip(step, -5.0, 5.0)  # metres: a badly conditioned point must not jump away
    return X, H, np.linalg.norm(err, axis=1)


def build_photo_map(photos: list[MapPhoto], cfg, rng: np.random.Generator | None = None,
                    init_gps_sigma_m: float | None = None) -> PhotoMap:
    """Build a :class:`PhotoMap` from photos with features and GPS priors (see the module docstring).

    ``cfg`` is an :class:`auxgps.config.PhotoMapConfig`. ``init_gps_sigma_m``: the GPS's weight in the first
    guess only (default ``cfg.gps_sigma_h_m``). The first guess weighs the overlaps' offsets against the GPS, and
    only the GPS gives the block its size: with a very loose GPS prior there, it comes out shrunk (a 100 m prior
    shrank Brighton Beach 78 times) and the bundle adjustment, which nothing pulls back, keeps it so. Raises
    :class:`PhotoMapError` when too few photos have GPS and overlap.
    """
    rng = rng if rng is not None else np.random.default_rng(0)
    messages: list[str] = []
    n = len(photos)
    with_gps = [i for i, p in enumerate(photos) if p.prior.gps_ne_m is not None]
    if len(with_gps) < 2:
        raise PhotoMapError(f"a map needs at least 2 photos with GPS, got {len(with_gps)}")

    # Which pairs may overlap: photos closer than their footprint (every pair when a photo lacks a height).
    def reach(p: MapPhoto) -> float:
        h = p.prior.height_m if p.prior.height_m is not None else None
        if h is None:
            return np.inf
        cam = p.camera
        return abs(h) * np.hypot(cam.width_px, cam.height_px) / cam.focal_px

    pair_matches: dict = {}
    for i in range(n):
        for j in range(i + 1, n):
            gi, gj = photos[i].prior.gps_ne_m, photos[j].prior.gps_ne_m
            if gi is not None and gj is not None and np.hypot(*(gi - gj)) > 0.5 * (reach(photos[i]) + reach(photos[j])):
                continue
            ia, ib = match_descriptors(photos[i].features.descriptors, photos[j].features.descriptors, cfg.ratio)
            if len(ia) < cfg.min_pair_inliers:
                continue
            inl = _verify_pair(photos[i].features.uv_px[ia], photos[j].features.uv_px[ib], cfg.pair_ransac_px)
            if inl.sum() >= cfg.min_pair_inliers:
                pair_matches[(i, j)] = (ia[inl], ib[inl])

    # Keep the photos connected (through overlaps) to the largest group holding GPS photos.
    if not pair_matches:
        raise PhotoMapError("no two photos overlap (no pair with enough matched features)")
    ii = np.array([k[0] for k in pair_matches]), np.array([k[1] for k in pair_matches])
    _, comp = connected_components(coo_matrix((np.ones(len(ii[0])), ii), shape=(n, n)), directed=False)
    gps_count = np.bincount(comp[with_gps], minlength=comp.max() + 1)
    main = int(np.argmax(gps_count))
    if gps_count[main] < 2:
        raise PhotoMapError("no group of overlapping photos holds 2 or more photos with GPS")
    keep = [i for i in range(n) if comp[i] == main and any(i in k for k in pair_matches)]
    for i in range(n):
        if i not in keep:
            messages.append(f"{photos[i].name}: left out of the map (overlaps no photo of the main group)")
    remap = {old: new for new, old in enumerate(keep)}
    photos = [photos[i] for i in keep]
    pair_matches = {(remap[i], remap[j]): v for (i, j), v in pair_matches.items() if i in remap and j in remap}
    n = len(photos)

    cam_ids = sorted({p.camera_id for p in photos})
    cam_of_photo = np.array([cam_ids.index(p.camera_id) for p in photos])
    first_cam = {cid: next(p.camera for p in photos if p.camera_id == cid) for cid in cam_ids}
    cams = [p.camera for p in photos]

    init = _initial_poses(photos, cams, pair_matches, cfg.gps_sigma_h_m if init_gps_sigma_m is None else init_gps_sigma_m)
    if any(v is None for v in init):
        raise PhotoMapError("could not place every overlapping photo (degenerate overlaps)")
    R0 = np.array([v[0] for v in init])
    C0 = np.array([v[1] for v in init])

    tracks = _build_tracks(photos, pair_matches)
    if tracks.n_tracks < 20:
        raise PhotoMapError(f"only {tracks.n_tracks} features are seen in more than one photo")
    rays = np.einsum("nij,nj->ni", R0[tracks.photo], np.column_stack([
        np.vstack([cams[p].pixels_to_normalized(uv[None]) for p, uv in zip(tracks.photo, tracks.uv)]),
        np.ones(len(tracks.photo))]))
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    X_all = _initial_points(C0, R0, tracks, rays)

    model = _Model(R0, cam_of_photo, np.array([first_cam[c].focal_px for c in cam_ids]),
                   np.array([first_cam[c].K[0, 2] for c in cam_ids]), np.array([first_cam[c].K[1, 2] for c in cam_ids]))
    sigma_obs = np.array([cfg.pixel_sigma_px * max(1.0, s) for s in _obs_scale(photos, tracks)])

    # Place every point with the first-guess photos, and leave out tracks that no point explains (a repeated
    # pattern matched to its twin); bundle-adjust the longest of the rest (enough to fix poses and intrinsics).
    cam_params = np.column_stack([np.zeros((n, 3)), C0])
    intr = np.zeros((len(cam_ids), 3))
    X_all, _, err = _refine_points(model, cam_params, intr, X_all, tracks.photo, tracks.track, tracks.uv, sigma_obs)
    worst0 = np.zeros(tracks.n_tracks)
    np.maximum.at(worst0, tracks.track, err / sigma_obs)
    length = np.bincount(tracks.track, minlength=tracks.n_tracks)
    usable = worst0 <= cfg.init_outlier_sigma
    order = np.lexsort((rng.random(tracks.n_tracks), -length, ~usable))
    ba_tracks = np.sort(order[: min(cfg.max_ba_points, int(usable.sum()))])
    sel = np.isin(tracks.track, ba_tracks)
    new_id = np.full(tracks.n_tracks, -1)
    new_id[ba_tracks] = np.arange(len(ba_tracks))
    gps_idx = np.array([i for i, p in enumerate(photos) if p.prior.gps_ne_m is not None], int)
    gps_ne = np.array([photos[i].prior.gps_ne_m for i in gps_idx]).reshape(-1, 2)
    h_idx = np.array([i for i, p in enumerate(photos) if p.prior.height_m is not None], int)
    h_val = np.array([photos[i].prior.height_m for i in h_idx], float)
    priors = (gps_idx, gps_ne, cfg.gps_sigma_h_m, h_idx, h_val, cfg.height_sigma_m)
    obs_photo, obs_pt, obs_uv, obs_sig = tracks.photo[sel], new_id[tracks.track[sel]], tracks.uv[sel], sigma_obs[sel]
    X_ba = X_all[ba_tracks]
    for gate in (cfg.init_outlier_sigma / 2.0, 3.0):
        cam_params, intr, X_ba = _bundle_adjust(model, cam_params, intr, X_ba, obs_photo, obs_pt, obs_uv, obs_sig,
                                                priors, cfg.refine_intrinsics, cfg.max_ba_evaluations, cfg.focal_sigma_rel)
        # Drop observations the solution cannot explain (a mismatched track, a moving object), then solve again.
        err = np.linalg.norm(_project_obs(model, cam_params, intr, X_ba, obs_photo, obs_pt) - obs_uv, axis=1)
        good = err <= gate * obs_sig
        obs_photo, obs_pt, obs_uv, obs_sig = obs_photo[good], obs_pt[good], obs_uv[good], obs_sig[good]

    # Every track, with the solved photos: points alone, then drop observations over 3 sigma, and again.
    X, H, err = _refine_points(model, cam_params, intr, X_all, tracks.photo, tracks.track, tracks.uv, sigma_obs)
    good = err <= 3.0 * sigma_obs
    t_photo, t_track, t_uv, t_sig = tracks.photo[good], tracks.track[good], tracks.uv[good], sigma_obs[good]
    X, H, err = _refine_points(model, cam_params, intr, X, t_photo, t_track, t_uv, t_sig)
    views = np.bincount(t_track, minlength=tracks.n_tracks)
    worst = np.zeros(tracks.n_tracks)
    np.maximum.at(worst, t_track, err / t_sig)
    R = _rotations(model, cam_params)
    C = cam_params[:, 3:]
    below = np.ones(tracks.n_tracks, bool)
    np.logical_and.at(below, t_track, np.einsum("nj,nj->n", X[t_track] - C[t_photo], R[t_photo][:, :, 2]) > 0)
    with np.errstate(invalid="ignore"):
        cov = np.linalg.inv(H + np.eye(3)[None] * 1e-6)
    sigma_h = np.sqrt(np.maximum(cov[:, 0, 0], cov[:, 1, 1]))
    ok = (views >= 2) & (worst <= 3.0) & below & np.isfinite(sigma_h) & (sigma_h <= cfg.max_point_sigma_m)
    if ok.sum() < 20:
        raise PhotoMapError(f"only {int(ok.sum())} well-placed points; the photos overlap too little")

    # One descriptor per point: the view closest to the mean of its views.
    desc = np.vstack([photos[p].features.descriptors[k] for p, k in zip(tracks.photo, tracks.kp)]).astype(np.float32)
    mean = np.zeros((tracks.n_tracks, SIFT_BYTES))
    np.add.at(mean, tracks.track, desc)
    mean /= np.maximum(np.bincount(tracks.track, minlength=tracks.n_tracks), 1)[:, None]
    dist = np.linalg.norm(desc - mean[tracks.track], axis=1)
    first = np.lexsort((dist, tracks.track))
    medoid = first[np.concatenate([[True], np.diff(tracks.track[first]) != 0])]

    # Where the map sits on Earth: the GPS residuals tell how noisy the receivers were; their mean is known to
    # that noise over the square root of the photos, but a receiver's slowly varying offset is common to all.
    solved = []
    gps_res = []
    for i, p in enumerate(photos):
        res_ne = C[i, :2] - p.prior.gps_ne_m if p.prior.gps_ne_m is not None else None
        if res_ne is not None:
            gps_res.append(res_ne)
        yaw_diff = None
        if p.prior.R_ned_cam is not None:
            yaw_diff = _wrap(camera_heading_rad(R[i]) - camera_heading_rad(p.prior.R_ned_cam))
            if abs(yaw_diff) > np.deg2rad(cfg.max_heading_disagreement_deg):
                messages.append(f"{p.name}: pixels turned {np.degrees(yaw_diff):+.0f} deg from the metadata's camera heading")
        mine = t_photo == i
        rms_px = float(np.sqrt(np.mean(err[mine] ** 2))) if mine.any() else None
        solved.append(SolvedPhoto(p.name, C[i].copy(), R[i].copy(), int(mine.sum()), res_ne, yaw_diff, rms_px))
    gps_res = np.array(gps_res)
    sigma_gps_obs = float(np.sqrt(np.mean(gps_res**2))) if len(gps_res) else cfg.gps_sigma_h_m
    georef = float(np.sqrt(max(sigma_gps_obs, cfg.gps_sigma_floor_m) ** 2 / len(gps_res) + cfg.gps_bias_sigma_m**2))

    cameras = {}
    for ci, cid in enumerate(cam_ids):
        cam = first_cam[cid]
        f = model.f0[ci] * np.exp(intr[ci, 0])
        K = np.array([[f, 0.0, model.cx[ci]], [0.0, f, model.cy[ci]], [0.0, 0.0, 1.0]])
        cameras[cid] = PinholeCamera(cam.width_px, cam.height_px, K, np.array([intr[ci, 1], intr[ci, 2], 0.0, 0.0]))

    idx = np.flatnonzero(ok)
    return PhotoMap(
        p_ned_m=X[idx],
        info_ned=H[idx],
        descriptors=np.vstack([photos[p].features.descriptors[k] for p, k in zip(tracks.photo[medoid[idx]], tracks.kp[medoid[idx]])]),
        n_views=views[idx],
        cameras=cameras,
        georef_sigma_h_m=georef,
        photos=tuple(solved),
        messages=tuple(messages),
    )


def _obs_scale(photos, tracks) -> np.ndarray:
    """Per observation: how much worse than the finest features it is located (SIFT places a blob to about an
    eighth of its diameter, so a large blob's position is less certain)."""
    return np.array([photos[p].features.size_px[k] for p, k in zip(tracks.photo, tracks.kp)]) / 8.0


# --------------------------------------------------------------------------------------------------- locating


class PhotoLocator:
    """Locates photos against a :class:`PhotoMap`. Build once per map; :meth:`locate` per photo."""

    def __init__(self, photo_map: PhotoMap, cfg) -> None:
        self.map = photo_map
        self.cfg = cfg
        self._flann = _flann()
        self._flann.add([photo_map.descriptors.astype(np.float32)])
        self._flann.train()
        p = photo_map.p_ned_m
        self._box = (p[:, :2].min(axis=0), p[:, :2].max(axis=0))
        with np.errstate(invalid="ignore"):
            cov = np.linalg.inv(photo_map.info_ned + np.eye(3)[None] * 1e-6)
        self._point_var_m2 = np.maximum(np.trace(cov, axis1=1, axis2=2) / 3.0, 0.0)

    def locate(self, features: PhotoFeatures, camera: PinholeCamera, prior: PhotoPrior | None = None) -> PhotoFix | PhotoNoFix:
        """Locate one photo from its features alone; ``prior`` (attitude, height: never GPS) is only checked."""
        cfg = self.cfg
        if len(features) < cfg.min_inliers:
            return PhotoNoFix(f"only {len(features)} features in the photo (blank, blurred or tiny)")
        best = np.full(len(self.map), -1)
        best_d = np.full(len(self.map), np.inf)
        for m in self._flann.knnMatch(features.descriptors.astype(np.float32), k=2):
            if len(m) == 2 and m[0].distance < cfg.ratio * m[1].distance and m[0].distance < best_d[m[0].trainIdx]:
                best[m[0].trainIdx] = m[0].queryIdx
                best_d[m[0].trainIdx] = m[0].distance
        lm = np.flatnonzero(best >= 0)
        fi = best[lm]
        n_matches = len(lm)
        if n_matches < cfg.min_inliers:
            return PhotoNoFix(f"only {n_matches} features match the map (not a place it covers)", 0, n_matches)
        X = self.map.p_ned_m[lm]
        uv = features.uv_px[fi]
        scale = np.maximum(features.size_px[fi] / 8.0, 1.0)
        thr = cfg.ransac_px * float(np.median(scale))
        ok, rvec, tvec, inl = cv2.solvePnPRansac(X, uv, camera.K, camera.dist if camera.has_distortion else None,
                                                 iterationsCount=cfg.ransac_iterations, reprojectionError=thr,
                                                 confidence=0.9999, flags=cv2.SOLVEPNP_EPNP)
        if not ok or inl is None or len(inl) < cfg.min_inliers:
            return PhotoNoFix(f"{0 if inl is None else len(inl)} of {n_matches} matches agree on a pose (need {cfg.min_inliers})", 0 if inl is None else len(inl), n_matches)
        R_cam_ned = cv2.Rodrigues(rvec)[0]
        R = R_cam_ned.T
        C = -R @ tvec.ravel()
        sigma_px = cfg.pixel_sigma_px * scale
        inl = inl.ravel()
        # Refine on the inliers, re-select them with the refined pose and the map points' own uncertainty (seen
        # from this camera it adds to the pixel noise), and again.
        for _ in range(3):
            depth = np.maximum((X - C) @ R[:, 2], 1e-3)
            sig = np.sqrt(sigma_px**2 + camera.focal_px**2 * self._point_var_m2[lm] / depth**2)
            R, C, _ = _refine_pose(camera, X[inl], uv[inl], sig[inl], R, C)
            err = _reproject(camera, X, uv, R, C)
            inl = np.flatnonzero(err <= 3.0 * sig)
            if len(inl) < cfg.min_inliers:
                return PhotoNoFix(f"{len(inl)} of {n_matches} matches agree on a pose (need {cfg.min_inliers})", len(inl), n_matches)
        inl = np.flatnonzero(err <= 3.0 * sig)
        n_inl = len(inl)
        share = n_inl / n_matches
        if n_inl < cfg.min_inliers or share < cfg.min_inlier_share:
            return PhotoNoFix(f"{n_inl} of {n_matches} matches agree on a pose (need {cfg.min_inliers} and "
                              f"{cfg.min_inlier_share:.0%})", n_inl, n_matches)
        cov_C, rms_px = _pose_covariance(camera, X[inl], uv[inl], sig[inl], R, C)
        uv_in = uv[inl]
        spread = np.ptp(uv_in[:, 0]) * np.ptp(uv_in[:, 1]) / (camera.width_px * camera.height_px)
        if spread < cfg.min_inlier_spread:
            return PhotoNoFix(f"the {n_inl} agreeing matches cover only {spread:.1%} of the photo", n_inl, n_matches)
        if not np.median(X[inl, 2]) > C[2]:
            return PhotoNoFix("the pose puts the camera below the ground it sees", n_inl, n_matches)
        lo, hi = self._box
        margin = max(cfg.max_outside_map_m, 0.0)
        if np.any(C[:2] < lo - margin) or np.any(C[:2] > hi + margin):
            return PhotoNoFix(f"the pose is {margin:.0f} m or more outside the map", n_inl, n_matches)
        cov = cov_C.copy()
        cov[:2, :2] += np.eye(2) * self.map.georef_sigma_h_m**2
        notes = _check_prior(prior, R, C, cfg)
        fix = PhotoFix(C, R, cov, n_inl, n_matches, rms_px, tuple(notes))
        if fix.accuracy_m > cfg.max_accuracy_m:
            return PhotoNoFix(f"too uncertain: {fix.accuracy_m:.1f} m one sigma", n_inl, n_matches)
        return fix


def _reproject(camera, X, uv, R, C) -> np.ndarray:
    p_cam = (X - C) @ R
    pred, _ = camera.project_cam(p_cam)
    return np.linalg.norm(np.nan_to_num(pred, nan=1e9) - uv, axis=1)


def _refine_pose(camera, X, uv, sig, R, C):
    """Robust least squares of the pose (small rotation about R, and the centre) over these matches."""

    def fun(x):
        Rx = R @ Rotation.from_rotvec(x[:3]).as_matrix()
        p_cam = (X - x[3:]) @ Rx
        pred, _ = camera.project_cam(p_cam)
        return (np.nan_to_num(pred, nan=1e6) - uv).ravel() / np.repeat(sig, 2)

    res = least_squares(fun, np.concatenate([np.zeros(3), C]), loss="huber", f_scale=1.5, method="trf", x_scale="jac")
    Rn = R @ Rotation.from_rotvec(res.x[:3]).as_matrix()
    Cn = res.x[3:]
    return Rn, Cn, _reproject(camera, X, uv, Rn, Cn)


def _pose_covariance(camera, X, uv, sig, R, C) -> tuple[np.ndarray, float]:
    """Covariance of the camera centre (3, 3) m^2 from the Jacobian at the solution, scaled up by the
    residuals when they are larger than ``sig`` says; and the reprojection RMS (px)."""

    def fun(x):
        Rx = R @ Rotation.from_rotvec(x[:3]).as_matrix()
        pred, _ = camera.project_cam((X - x[3:]) @ Rx)
        return (pred - uv).ravel() / np.repeat(sig, 2)

    x0 = np.concatenate([np.zeros(3), C])
    r0 = fun(x0)
    J = np.empty((len(r0), 6))
    for k in range(6):
        h = 1e-6 if k < 3 else 1e-4
        dx = np.zeros(6)
        dx[k] = h
        J[:, k] = (fun(x0 + dx) - fun(x0 - dx)) / (2 * h)
    dof = max(len(r0) - 6, 1)
    s2 = max(1.0, float(r0 @ r0) / dof)
    cov = np.linalg.inv(J.T @ J) * s2
    rms_px = float(np.sqrt(np.mean(np.sum(((r0.reshape(-1, 2)) * sig[:, None]) ** 2, axis=1))))
    return cov[3:, 3:], rms_px


def _check_prior(prior: PhotoPrior | None, R: np.ndarray, C: np.ndarray, cfg) -> list[str]:
    """Where the photo's own metadata disagrees with the pose the map gives."""
    notes = []
    if prior is None:
        return notes
    if prior.R_ned_cam is not None:
        d = _wrap(camera_heading_rad(R) - camera_heading_rad(prior.R_ned_cam))
        if abs(d) > np.deg2rad(cfg.max_heading_disagreement_deg):
            notes.append(f"pixels turned {np.degrees(d):+.0f} deg from the metadata's camera heading")
        tilt = np.degrees(np.arccos(np.clip(R[:, 2] @ prior.R_ned_cam[:, 2], -1, 1)))
        if tilt > cfg.max_heading_disagreement_deg:
            notes.append(f"optical axis {tilt:.0f} deg from the metadata's")
    if prior.height_m is not None:
        dh = -C[2] - prior.height_m
        if abs(dh) > max(2.0, 0.1 * abs(prior.height_m)):
            notes.append(f"height {-C[2]:.1f} m, metadata says {prior.height_m:.1f} m")
    return notes
