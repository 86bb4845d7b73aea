"""Does a photo block lie where its photos' GPS says, and is the GPS late? The block as `auxgps ortho build` solves it.

    python tools/block_vs_gps.py --images ../shared/data/seneca/images --only 'IMG_04[6-9]*' \\
        --camera config/cameras/canon_elph300hs.yaml        # about 8 minutes for 39 photos

Prints the 2D similarity that best puts the solved camera positions on their GPS (its scale and turn: the block's
size and direction against the GPS's), each photo's misfit RMS, and the misfit fitted as ``-v dt + c``: a GPS
position taken ``dt`` seconds after the exposure lies ``v dt`` ahead of the camera along its velocity ``v`` (from
the GPS positions and capture times, central differences), ``c`` a constant offset. A negative ``dt``: the GPS
position is older than the exposure.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))  # tools/, for gps_consistency

from gps_consistency import fit_similarity_2d  # noqa: E402


def similarity(src_ne: np.ndarray, dst_ne: np.ndarray) -> tuple[float, float, np.ndarray]:
    """``dst ~ s R src + t`` by least squares (tools/gps_consistency.py's fit): the scale less one, the turn (rad,
    north towards east) and the residuals (N, 2)."""
    sim = fit_similarity_2d(src_ne, dst_ne)
    return sim.scale - 1.0, sim.rotation_rad, np.asarray(dst_ne, float) - sim.apply(src_ne)


def gps_lag(misfit_ne: np.ndarray, gps_ne: np.ndarray, t_s: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Fit ``misfit = -v dt + c`` (misfit: solved minus GPS, (N, 2) m; v from ``gps_ne`` over ``t_s``): dt (s),
    c (2,) m, and what is left (N, 2) m."""
    v = np.gradient(gps_ne, t_s, axis=0)
    n = len(misfit_ne)
    A = np.column_stack([-v.reshape(-1), np.tile([1.0, 0.0], n), np.tile([0.0, 1.0], n)])
    x, *_ = np.linalg.lstsq(A, misfit_ne.reshape(-1), rcond=None)
    return float(x[0]), x[1:], (misfit_ne.reshape(-1) - A @ x).reshape(n, 2)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--images", required=True)
    ap.add_argument("--only", action="append", default=None, help="photos whose file name matches this glob (repeatable)")
    ap.add_argument("--camera", default=None, help="camera file (config/cameras/*.yaml)")
    ap.add_argument("--config", default=None, help="photo workflow settings YAML")
    a = ap.parse_args(argv)

    from auxgps.config import load_photo_camera, load_photo_config
    from auxgps.io.photos import list_photos
    from auxgps.photo.build import build_photo_map
    from auxgps.photo_workflow import read_map_photos

    cfg = load_photo_config(a.config)
    files = list_photos(a.images, a.only)
    metas, _, photos, _ = read_map_photos(files, load_photo_camera(a.camera) if a.camera else None, cfg)
    block = build_photo_map(photos, cfg.map)
    t_of = {m.path.name: m.capture_time.timestamp() for m in metas if m.capture_time is not None}  # camera clock
    solved = [sp for sp in block.photos if sp.gps_residual_ne_m is not None and t_of.get(sp.name) is not None]
    order = np.argsort([t_of[sp.name] for sp in solved])
    solved = [solved[i] for i in order]
    P = np.array([sp.p_cam_in_ned_m[:2] for sp in solved])
    G = P - np.array([sp.gps_residual_ne_m for sp in solved])
    t = np.array([t_of[sp.name] for sp in solved], float)
    scale, turn, res = similarity(G, P)
    print(f"{len(solved)} photos; focal length(s) solved: {', '.join(f'{c.focal_px:.1f} px' for c in block.cameras.values())}")
    print(f"solved against GPS: scale {scale:+.3%}, turn {np.degrees(turn):+.2f} deg; each photo's misfit "
          f"{np.sqrt(np.mean(np.sum((P - G) ** 2, axis=1))):.2f} m RMS ({np.sqrt(np.mean(np.sum(res ** 2, axis=1))):.2f} after the similarity)")
    dt, c, left = gps_lag(P - G, G, t)
    print(f"misfit as a GPS time offset: dt {dt:+.2f} s, constant {c[0]:+.2f} N {c[1]:+.2f} E m; "
          f"left {np.sqrt(np.mean(np.sum(left ** 2, axis=1))):.2f} m RMS")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
