"""Landmark maps from geotagged photos (:func:`build_photo_map`).

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

Frames: local NED (m) about the map's origin; camera frame OpenCV (x right, y down, z forward); ``R_ned_cam``
maps camera into NED. Pixels are full-resolution pixels of the stored photo.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from auxgps.core.camera import PinholeCamera
from auxgps.errors import PhotoMapError
from auxgps.photo.bundle import _bundle_adjust, _Model, _project_obs, _refine_points, _rotations
from auxgps.photo.features import SIFT_BYTES, _verify_pair, match_descriptors
from auxgps.photo.tracks import _build_tracks, _initial_points, _initial_poses
from auxgps.photo.types import MapPhoto, PhotoMap, SolvedPhoto, _wrap, camera_heading_rad


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
    # GPS altitudes are over the origin's level, not the ground's: the first guess (heights above the ground
    # under the photos) moves up or down as a whole to meet them.
    alt_idx = np.array([i for i, p in enumerate(photos) if p.prior.height_m is None and p.prior.gps_alt_m is not None], int)
    if len(alt_idx) == n:
        gps_alt = np.array([photos[i].prior.gps_alt_m for i in alt_idx])
        C0[:, 2] -= np.median(C0[:, 2] + gps_alt)  # up = -down

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
    h_sigma = np.full(len(h_idx), cfg.height_sigma_m)
    if len(alt_idx) == n:  # every photo by its GPS altitude (a mix with heights above take-off: those alone)
        h_idx, h_sigma = alt_idx, np.full(n, cfg.gps_alt_sigma_m)
        h_val = np.array([photos[i].prior.gps_alt_m for i in alt_idx], float)
    priors = (gps_idx, gps_ne, cfg.gps_sigma_h_m, h_idx, h_val, h_sigma)
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
