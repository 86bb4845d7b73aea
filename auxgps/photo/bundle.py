"""Bundle adjustment of photo poses, shared intrinsics and 3D points; refinement of points alone.

Parameters per photo: a rotation increment (rotation vector, rad) applied on the right of its fixed first-guess
rotation ``R0``, and its centre in NED (m); per camera id: log(f / f0), k1, k2 (cx, cy fixed); per point: its
NED position (m). Camera frame OpenCV (x right, y down, z forward).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from auxgps.core.geometry import cross_matrix


class _Intrinsics:
    """Pinhole with two radial terms, vectorised: normalised camera points -> pixels."""

    @staticmethod
    def project(p_cam: np.ndarray, f: np.ndarray, cx: np.ndarray, cy: np.ndarray, k1: np.ndarray, k2: np.ndarray) -> np.ndarray:
        z = np.maximum(p_cam[:, 2], 0.1)  # a point behind the camera is far off, not infinitely far
        x, y = p_cam[:, 0] / z, p_cam[:, 1] / z
        r2 = x * x + y * y
        d = 1.0 + k1 * r2 + k2 * r2 * r2
        return np.column_stack([f * d * x + cx, f * d * y + cy])


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

    ``priors`` = (gps_idx, gps_ne (G, 2), gps_sigma, h_idx, h_val, h_sigma (a number or one per height)): each
    photo's GPS position and height above the origin as soft constraints. With ``refine_intrinsics``, each camera's focal length is held
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
        cost += float(np.sum(rg**2) / gps_sigma**2 + np.sum(rh**2 / h_sigma**2))
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
