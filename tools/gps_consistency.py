"""Are the photos' GPS positions consistent with each other? Ask the photos.

    python tools/gps_consistency.py --images DIR [--only GLOB] [--camera CFG] [--config PHOTO_YAML]
        [--gps-sigma-m 100] [--hold-out PASS [--hold-out-bare]] [--json OUT]

1. One photogrammetric block of ALL the given photos, built by the map builder
   (:func:`auxgps.photo.build.build_photo_map`) with the GPS prior made so loose (``--gps-sigma-m``, default
   100 m) that the GPS cannot bend the block: its shape comes from the images (and the heights above take-off).
2. Its camera positions are then placed on the GPS by a least-squares 2D similarity (north/east translation,
   rotation, scale; equal weights): the photos' GPS fixes where the block lies, nothing more. Per photo the tool
   prints the solved position minus its GPS (north, east, m), and per pass (photos grouped by consecutive capture
   along one flight direction) the mean offset and the spread about it (the residual of a pass-by-pass
   translation fit). A pass whose mean offset differs from the others' by more than its spread has GPS that is
   inconsistent with theirs by that much.
3. Leave one pass out: the same block placed by the OTHER passes' GPS alone, and the left-out pass's photos
   compared with their own GPS. This is the question a locator answers (a map georeferenced by some passes, a
   photo of another pass located in it), solved here by the block's own geometry. With three parallel passes
   these rows hold one number between them: the similarity absorbs the outer passes' difference, and what is
   left is the middle pass against the line between the outer two (seen from either side, doubled).
4. ``--hold-out PASS`` (1-based): also a full joint adjustment with the configured GPS prior
   (``map.gps_sigma_h_m``, default 1 m) on every photo except that pass's, which gets no GPS prior at all; the
   held-out photos' solved positions are compared with their own GPS (what ``auxgps locate`` scores). With
   ``--hold-out-bare`` those photos get no height or attitude prior either (as ``auxgps locate`` on stripped
   photos).

The block's shape leans on the intrinsics: a flat scene barely fixes the focal length, and a wrong one bends the
passes against each other. Compare with ``--config`` holding ``map: {refine_intrinsics: false}`` (the camera
file's focal length, no distortion), and look at the within-pass spread and the ground's level below take-off.

Checks on the photogrammetry itself: each photo's reprojection RMS (px) and observations kept, the refined focal
length, and the similarity's scale and rotation (near 1 and 0 when the bundle adjustment converged to the
least-squares placement; any value is harmless here, as the similarity fit replaces that placement).

Frames: local north/east (m) about the photos' mean GPS position (as ``auxgps map build``).
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass, replace
from datetime import datetime
from pathlib import Path

import numpy as np

from auxgps.config import load_photo_camera, load_photo_config
from auxgps.io.photos import list_photos
from auxgps.photo.build import build_photo_map
from auxgps.photo.types import PhotoPrior
from auxgps.photo_workflow import read_map_photos


# --------------------------------------------------------------------------------------------------- analysis


@dataclass(frozen=True)
class Similarity2D:
    """``p_dst = scale * R(rotation_rad) @ p_src + t_ne_m`` on north/east points (m)."""

    scale: float
    rotation_rad: float
    t_ne_m: np.ndarray

    def apply(self, p_ne_m: np.ndarray) -> np.ndarray:
        c, s = np.cos(self.rotation_rad), np.sin(self.rotation_rad)
        R = np.array([[c, -s], [s, c]])
        return self.scale * np.asarray(p_ne_m, float) @ R.T + self.t_ne_m


def fit_similarity_2d(src_ne_m: np.ndarray, dst_ne_m: np.ndarray) -> Similarity2D:
    """Least-squares similarity taking ``src`` (K, 2) onto ``dst`` (K, 2), K >= 2 (Umeyama, equal weights)."""
    src, dst = np.asarray(src_ne_m, float), np.asarray(dst_ne_m, float)
    if len(src) < 2:
        raise ValueError("a 2D similarity needs at least 2 points")
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - mu_s, dst - mu_d
    # As complex numbers (north + i east): dst = z * src + t, z = scale * exp(i rotation).
    zs, zd = a[:, 0] + 1j * a[:, 1], b[:, 0] + 1j * b[:, 1]
    z = np.vdot(zs, zd) / np.vdot(zs, zs).real
    sim = Similarity2D(float(abs(z)), float(np.angle(z)), np.zeros(2))
    return Similarity2D(sim.scale, sim.rotation_rad, mu_d - sim.apply(mu_s))


def group_passes(gps_ne_m: np.ndarray, max_turn_deg: float = 45.0) -> list[list[int]]:
    """Photos (in capture order) grouped into passes: a pass goes on while each step between consecutive photos
    keeps within ``max_turn_deg`` of the pass's first step; the step that turns (the cross-over to the next
    line) belongs to no pass, and the next pass starts at the photo it reaches."""
    p = np.asarray(gps_ne_m, float)
    passes: list[list[int]] = [[0]]
    heading = None
    for k in range(1, len(p)):
        step = p[k] - p[k - 1]
        h = np.arctan2(step[1], step[0])
        if heading is None:
            heading = h
        turn = abs((h - heading + np.pi) % (2 * np.pi) - np.pi)
        if turn <= np.deg2rad(max_turn_deg):
            passes[-1].append(k)
        else:
            passes.append([k])
            heading = None
    return passes


@dataclass(frozen=True)
class PassOffset:
    """One pass's photos' solved-minus-GPS offsets: their mean (north, east, m), the RMS of the photos about
    that mean (m, horizontal: what a translation of the pass alone leaves), and the pass's flight heading."""

    photos: tuple[int, ...]
    mean_offset_ne_m: np.ndarray
    spread_rms_m: float
    heading_deg: float


def pass_offsets(offset_ne_m: np.ndarray, gps_ne_m: np.ndarray, passes: list[list[int]]) -> list[PassOffset]:
    out = []
    for idx in passes:
        o = offset_ne_m[idx]
        mean = o.mean(axis=0)
        spread = float(np.sqrt(np.mean(np.sum((o - mean) ** 2, axis=1))))
        d = gps_ne_m[idx[-1]] - gps_ne_m[idx[0]]
        out.append(PassOffset(tuple(idx), mean, spread, float(np.degrees(np.arctan2(d[1], d[0]))) if len(idx) > 1 else float("nan")))
    return out


@dataclass(frozen=True)
class Placement:
    """The block placed on the GPS of the photos ``fitted_on``: ``offset_ne_m`` (N, 2) of EVERY photo, solved
    (placed) minus its GPS, m; and the similarity used."""

    fitted_on: tuple[int, ...]
    similarity: Similarity2D
    offset_ne_m: np.ndarray


def place_block(block_ne_m: np.ndarray, gps_ne_m: np.ndarray, fitted_on: list[int]) -> Placement:
    sim = fit_similarity_2d(block_ne_m[fitted_on], gps_ne_m[fitted_on])
    return Placement(tuple(fitted_on), sim, sim.apply(block_ne_m) - gps_ne_m)


def along_cross(offset_ne_m: np.ndarray, heading_deg: float) -> tuple[float, float]:
    """An offset split along a flight heading (forward +) and across it (right of the heading +), m."""
    h = np.deg2rad(heading_deg)
    fwd, right = np.array([np.cos(h), np.sin(h)]), np.array([-np.sin(h), np.cos(h)])
    return float(offset_ne_m @ fwd), float(offset_ne_m @ right)


# --------------------------------------------------------------------------------------------------- photos


def load_photos(files: list[Path], cam_cfg, cfg, say=print):
    """The map builder's reading of ``files`` (:func:`read_map_photos`, its messages said): the MapPhotos
    (features computed once) in capture order."""
    metas, _, photos, messages = read_map_photos(files, cam_cfg, cfg)
    for message in messages:
        say(f"  {message}")
    order = sorted(range(len(photos)), key=lambda i: (metas[i].capture_time or datetime.min, metas[i].path.name))  # else by name
    return [photos[i] for i in order]


def _vec(v) -> list:
    return [round(float(x), 4) for x in v]


def run(files: list[Path], cam_cfg, cfg, *, gps_sigma_m: float, hold_out: int | None, max_turn_deg: float,
        hold_out_bare: bool = False, say=print) -> dict:
    photos = load_photos(files, cam_cfg, cfg, say)
    names = [p.name for p in photos]
    gps_ne_m = np.array([p.prior.gps_ne_m for p in photos])
    passes = group_passes(gps_ne_m, max_turn_deg)
    say(f"{len(photos)} photos with GPS; passes (capture order, a turn over {max_turn_deg:.0f} deg starts a new one):")
    for k, idx in enumerate(passes, 1):
        say(f"  pass {k}: {names[idx[0]]} .. {names[idx[-1]]} ({len(idx)} photos)")

    loose = replace(cfg.map, gps_sigma_h_m=gps_sigma_m, gps_sigma_floor_m=min(cfg.map.gps_sigma_floor_m, gps_sigma_m))
    say(f"\nblock of all {len(photos)} photos, GPS prior {gps_sigma_m:g} m per axis (shape from the images):")
    pm = build_photo_map(photos, loose, init_gps_sigma_m=cfg.map.gps_sigma_h_m)  # a first guess of the right size
    solved = {p.name: p for p in pm.photos}
    missing = [n for n in names if n not in solved]
    if missing:
        say(f"  left out of the block: {', '.join(missing)} (the analysis needs every photo)")
        raise SystemExit(1)
    block_ne_m = np.array([solved[n].p_cam_in_ned_m[:2] for n in names])
    for cid, cam in pm.cameras.items():
        say(f"  camera {cid}: focal {cam.focal_px:.1f} px, k1 {cam.dist[0]:+.4f}, k2 {cam.dist[1]:+.4f}")
    rms = np.array([solved[n].rms_px for n in names], float)
    nobs = np.array([solved[n].n_observations for n in names])
    say(f"  {len(pm)} points; reprojection RMS per photo {rms.min():.2f}-{rms.max():.2f} px "
        f"(overall {np.sqrt(np.sum(rms**2 * nobs) / nobs.sum()):.2f} px, {nobs.sum()} observations kept)")
    say(f"  median point {np.median(pm.p_ned_m[:, 2]):+.2f} m below the take-off level (the photos' heights above "
        "take-off are priors; the ground's level is free: a focal length that is off moves it)")

    everyone = place_block(block_ne_m, gps_ne_m, list(range(len(photos))))
    sim = everyone.similarity
    say(f"  similarity block -> GPS: scale {sim.scale:.5f}, rotation {np.degrees(sim.rotation_rad):+.3f} deg, "
        f"shift {np.hypot(*sim.t_ne_m):.3f} m")

    say("\nplaced on ALL photos' GPS: solved minus GPS, m (north, east)")
    say(f"  {'photo':<14}{'pass':>5}{'north':>8}{'east':>8}{'dist':>7}{'rms px':>8}{'obs':>7}")
    pass_of = {i: k for k, idx in enumerate(passes, 1) for i in idx}
    for i, n in enumerate(names):
        o = everyone.offset_ne_m[i]
        say(f"  {n:<14}{pass_of[i]:>5}{o[0]:>+8.2f}{o[1]:>+8.2f}{np.hypot(*o):>7.2f}{rms[i]:>8.2f}{nobs[i]:>7}")
    per_pass = pass_offsets(everyone.offset_ne_m, gps_ne_m, passes)
    say(f"  {'pass':<6}{'heading':>8}{'mean N':>8}{'mean E':>8}{'spread':>8}")
    for k, po in enumerate(per_pass, 1):
        say(f"  {k:<6}{po.heading_deg:>8.0f}{po.mean_offset_ne_m[0]:>+8.2f}{po.mean_offset_ne_m[1]:>+8.2f}{po.spread_rms_m:>8.2f}")
    total_rms = float(np.sqrt(np.mean(np.sum(everyone.offset_ne_m**2, axis=1))))
    within_rms = float(np.sqrt(np.mean([po.spread_rms_m**2 for po in per_pass])))
    say(f"  RMS of all offsets {total_rms:.2f} m; within passes {within_rms:.2f} m (after one translation per pass)")

    say("\nleave one pass out: block placed on the OTHER passes' GPS; the left-out pass vs its own GPS, m")
    say(f"  {'pass':<6}{'mean N':>8}{'mean E':>8}{'|mean|':>8}{'bearing':>8}{'along':>7}{'across':>7}{'median dist':>12}{'max':>6}")
    held = []
    for k, idx in enumerate(passes, 1):
        others = [i for i in range(len(photos)) if i not in idx]
        if len(others) < 2:
            continue
        pl = place_block(block_ne_m, gps_ne_m, others)
        o = pl.offset_ne_m[idx]
        mean = o.mean(axis=0)
        dist = np.hypot(o[:, 0], o[:, 1])
        a, c = along_cross(mean, per_pass[k - 1].heading_deg)
        # The GPS sits opposite the solved offset: bearing from the photo's GPS to where the block puts it.
        bearing = float(np.degrees(np.arctan2(mean[1], mean[0])) % 360)
        say(f"  {k:<6}{mean[0]:>+8.2f}{mean[1]:>+8.2f}{np.hypot(*mean):>8.2f}{bearing:>8.0f}{a:>+7.2f}{c:>+7.2f}"
            f"{np.median(dist):>12.2f}{dist.max():>6.2f}")
        held.append({"pass": k, "photos": [names[i] for i in idx], "offset_ne_m": [_vec(v) for v in o],
                     "mean_offset_ne_m": _vec(mean), "along_across_m": _vec((a, c)), "bearing_deg": round(bearing, 1),
                     "median_dist_m": round(float(np.median(dist)), 4), "max_dist_m": round(float(dist.max()), 4),
                     "scale": round(pl.similarity.scale, 6), "rotation_deg": round(float(np.degrees(pl.similarity.rotation_rad)), 4)})
    say("  (along: along the pass's flight heading; across: to its right; bearing: from the photo's GPS to the"
        " block's position, deg from north)")

    result = {
        "photos": names, "passes": [[names[i] for i in idx] for idx in passes], "gps_sigma_m": gps_sigma_m,
        "block": {"points": len(pm), "median_point_down_m": round(float(np.median(pm.p_ned_m[:, 2])), 4), "rms_px": [round(float(r), 4) for r in rms], "observations": nobs.tolist(),
                  "focal_px": {cid: round(cam.focal_px, 3) for cid, cam in pm.cameras.items()},
                  "similarity": {"scale": round(sim.scale, 6), "rotation_deg": round(float(np.degrees(sim.rotation_rad)), 4)}},
        "all_gps": {"offset_ne_m": [_vec(v) for v in everyone.offset_ne_m],
                    "passes": [{"mean_offset_ne_m": _vec(po.mean_offset_ne_m), "spread_rms_m": round(po.spread_rms_m, 4),
                                "heading_deg": round(po.heading_deg, 2)} for po in per_pass],
                    "rms_m": round(total_rms, 4), "within_pass_rms_m": round(within_rms, 4)},
        "leave_one_pass_out": held,
    }

    if hold_out is not None:
        if not 1 <= hold_out <= len(passes):
            raise SystemExit(f"--hold-out {hold_out}: there are {len(passes)} passes")
        idx = passes[hold_out - 1]
        bare = PhotoPrior()
        mixed = [replace(p, prior=bare if hold_out_bare else PhotoPrior(None, p.prior.height_m, p.prior.R_ned_cam))
                 if i in idx else p for i, p in enumerate(photos)]
        say(f"\njoint adjustment: GPS prior {cfg.map.gps_sigma_h_m:g} m on every photo but pass {hold_out}'s (none on those"
            + (", nor height or attitude)" if hold_out_bare else ")"))
        pj = build_photo_map(mixed, cfg.map)
        sj = {p.name: p for p in pj.photos}
        for cid, cam in pj.cameras.items():
            say(f"  camera {cid}: focal {cam.focal_px:.1f} px, k1 {cam.dist[0]:+.4f}, k2 {cam.dist[1]:+.4f}; "
                f"median point {np.median(pj.p_ned_m[:, 2]):+.2f} m below take-off")
        rows = []
        for i in idx:
            if names[i] not in sj:
                say(f"  {names[i]}: left out of the adjustment")
                continue
            o = sj[names[i]].p_cam_in_ned_m[:2] - gps_ne_m[i]
            rows.append(o)
            say(f"  {names[i]:<14}{o[0]:>+8.2f}{o[1]:>+8.2f}  dist {np.hypot(*o):.2f}")
        ref = [sj[names[i]].gps_residual_ne_m for i in range(len(names)) if i not in idx and names[i] in sj]
        rows = np.array(rows)
        d = np.hypot(rows[:, 0], rows[:, 1])
        mean = rows.mean(axis=0)
        say(f"  held-out pass: mean {mean[0]:+.2f} N {mean[1]:+.2f} E, median distance {np.median(d):.2f} m, "
            f"max {d.max():.2f} m; the other photos vs their GPS: RMS {np.sqrt(np.mean(np.sum(np.square(ref), axis=1))):.2f} m")
        result["joint_hold_out"] = {"pass": hold_out, "bare": hold_out_bare, "gps_sigma_m": cfg.map.gps_sigma_h_m,
                                    "offset_ne_m": [_vec(v) for v in rows], "mean_offset_ne_m": _vec(mean),
                                    "median_dist_m": round(float(np.median(d)), 4), "max_dist_m": round(float(d.max()), 4)}
    return result


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--images", required=True, help="folder of geotagged photos")
    ap.add_argument("--only", action="append", help="only photos whose file name matches this glob (repeatable, or comma-separated)")
    ap.add_argument("--camera", help="camera file (config/cameras/*.yaml); default: from EXIF")
    ap.add_argument("--config", help="photo settings YAML (as auxgps map build); default: the defaults")
    ap.add_argument("--gps-sigma-m", type=float, default=100.0, help="the block's GPS prior, m per axis (default 100: placement only)")
    ap.add_argument("--hold-out", type=int, help="also a joint adjustment without this pass's GPS (1-based)")
    ap.add_argument("--hold-out-bare", action="store_true", help="and without its height and attitude metadata too")
    ap.add_argument("--max-turn-deg", type=float, default=45.0, help="a turn larger than this starts a new pass")
    ap.add_argument("--json", help="write the numbers here")
    args = ap.parse_args(argv)
    if not args.gps_sigma_m > 0:
        ap.error("--gps-sigma-m must be positive")
    if args.hold_out_bare and args.hold_out is None:
        ap.error("--hold-out-bare needs --hold-out")
    cfg = load_photo_config(args.config)
    cam_cfg = load_photo_camera(args.camera) if args.camera else None
    files = list_photos(args.images, args.only)
    result = run(files, cam_cfg, cfg, gps_sigma_m=args.gps_sigma_m, hold_out=args.hold_out, max_turn_deg=args.max_turn_deg,
                 hold_out_bare=args.hold_out_bare, say=lambda s: print(s, flush=True))
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1))
        print(f"\nwrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
