"""Which detector matches a flying camera to an older orthophoto: ORB (auxgps's) beside SIFT (OpenCV's, no weights).

Frames are rendered from the true pose over a world (mosaic A); prior maps of both kinds are built from another
orthophoto of the same ground (mosaic B, coarser and colour-shifted: tools/ortho_variant.py). Each frame's
features are matched to the map's landmarks under its footprint (nearest neighbour with Lowe's ratio test,
Hamming for ORB, L2 for SIFT) and the camera is solved by PnP in RANSAC (attitude free). Reported per detector:
frames located (at least 15 inliers and within 3 m of the truth), median inliers, median and 95th percentile
error. The truth only picks the landmarks near the footprint (both detectors alike) and scores; it is a study of
what the descriptors can match, not of auxgps's positioning, which searches around its own prediction.

    python tools/prior_detector_study.py --world config/worlds/seneca.yaml --prior-ortho out/ortho/seneca_b_03_shift.tif \
        --alt-m 60 --frames 40 --json out/prior_detector_study.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from auxgps.config import PhotoConfig, PipelineConfig  # noqa: E402
from auxgps.core.camera import CameraPose, camera_from_config  # noqa: E402
from auxgps.core.estimator import prior_map_detector  # noqa: E402
from auxgps.core.geometry import R_body_cam_from_mount, R_ned_body_from_euler  # noqa: E402
from auxgps.ortho_map import build_prior_map  # noqa: E402
from auxgps.photo.features import detect_sift  # noqa: E402
from auxgps.sim.render import Renderer  # noqa: E402
from auxgps.sim.world import load_world  # noqa: E402


def _in_world_frame(report, frame):
    lat, lon, alt = report.frame.to_geodetic(report.columns["p_ned_m"].astype(float))
    return frame.to_ned(lat_deg=lat, lon_deg=lon, alt_amsl_m=alt)


def _solve(uv, X, camera):
    if len(uv) < 15:
        return None, 0
    ok, rvec, tvec, inl = cv2.solvePnPRansac(X.astype(np.float64), uv.astype(np.float64), camera.K, None, iterationsCount=3000,
                                             reprojectionError=4.0, confidence=0.999, flags=cv2.SOLVEPNP_EPNP)
    if not ok or inl is None:
        return None, 0
    R = cv2.Rodrigues(rvec)[0]
    return (-R.T @ tvec.ravel()), len(inl)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--world", required=True)
    ap.add_argument("--prior-ortho", required=True)
    ap.add_argument("--alt-m", type=float, default=60.0)
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--box-m", type=float, default=150.0, help="frames over north/east within this of the world's origin")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json")
    args = ap.parse_args(argv)

    cfg = PipelineConfig()
    camera = camera_from_config(cfg.camera)
    world = load_world(args.world)
    renderer = Renderer(world, camera)
    orb_map = build_prior_map(args.prior_ortho, descriptor="orb", pipeline=cfg)
    sift_map = build_prior_map(args.prior_ortho, descriptor="sift", photo_cfg=PhotoConfig())
    maps = {"orb": (orb_map, _in_world_frame(orb_map, world.frame)), "sift": (sift_map, _in_world_frame(sift_map, world.frame))}
    detector = prior_map_detector(cfg)
    R_body_cam = R_body_cam_from_mount()
    rng = np.random.default_rng(args.seed)
    rows = {k: [] for k in maps}
    for _ in range(args.frames):
        p = np.array([*rng.uniform(-args.box_m, args.box_m, 2) + [90.0, -40.0], -args.alt_m])
        R_ned_cam = R_ned_body_from_euler(*np.deg2rad([rng.normal(0, 3), rng.normal(0, 3), rng.uniform(0, 360)])) @ R_body_cam
        image = renderer.render(CameraPose(p, R_ned_cam)).image_bgr
        scale = min(1.0, args.alt_m / camera.focal_px / orb_map.gsd_m)
        near_r = args.alt_m * 0.8 + 20.0
        for kind, (report, P) in maps.items():
            near = np.flatnonzero(np.hypot(P[:, 0] - p[0], P[:, 1] - p[1]) < near_r)
            if kind == "orb":
                f = detector.detect(image, R_ned_cam, scale)
                uv, desc = f.uv_px, f.descriptors
                norm = cv2.NORM_HAMMING
            else:
                s = min(1.0, args.alt_m / camera.focal_px / sift_map.gsd_m)
                gray = cv2.resize(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY), None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
                f = detect_sift(gray, 1.0 / s, 4000, 500)
                uv, desc = f.uv_px, f.descriptors.astype(np.float32)
                norm = cv2.NORM_L2
            if len(near) < 15 or len(uv) < 15:
                rows[kind].append({"inliers": 0, "error_m": None})
                continue
            map_desc = report.columns["descriptors"][near]
            map_desc = map_desc if kind == "orb" else map_desc.astype(np.float32)
            knn = cv2.BFMatcher(norm).knnMatch(desc, map_desc, k=2)
            pairs = [(m[0].queryIdx, m[0].trainIdx) for m in knn if len(m) == 2 and m[0].distance < 0.8 * m[1].distance]
            if len(pairs) < 15:
                rows[kind].append({"inliers": 0, "error_m": None})
                continue
            qi, ti = np.array(pairs).T
            c, n_inl = _solve(uv[qi], P[near[ti]], camera)
            err = None if c is None else float(np.hypot(*(c[:2] - p[:2])))
            rows[kind].append({"inliers": n_inl, "error_m": err})
    out = {"scenario": vars(args), "map_landmarks": {k: v[0].count for k, v in maps.items()}, "results": {}}
    for kind, rs in rows.items():
        located = [r for r in rs if r["error_m"] is not None and r["inliers"] >= 15 and r["error_m"] < 3.0]
        errs = np.array([r["error_m"] for r in located]) if located else np.array([np.nan])
        out["results"][kind] = {"frames": len(rs), "located": len(located), "median_inliers": float(np.median([r["inliers"] for r in rs])),
                                "median_error_m": float(np.median(errs)), "p95_error_m": float(np.percentile(errs, 95))}
        print(f"{kind}: {len(located)} of {len(rs)} frames located (15 inliers, under 3 m), median inliers "
              f"{out['results'][kind]['median_inliers']:.0f}, error median {np.median(errs):.2f} m, p95 {np.percentile(errs, 95):.2f} m "
              f"({maps[kind][0].count} landmarks)")
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
