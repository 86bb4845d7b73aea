"""auxgps ortho build: photos projected onto the ground and blended, and the seams between them measured.

Synthetic photos of a known ground (a texture on the plane down = 0, photographed from known poses) are
mosaicked with those poses: the orthophoto must be that ground, and a pose moved by a known amount must show
as that seam offset. A real survey (Brighton Beach, when present) goes through the whole command.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import rasterio

from auxgps.core.camera import CameraPose, PinholeCamera
from auxgps.core.geometry import R_ned_body_from_euler
from auxgps.photo.ortho import GroundPlane, Mosaic, OrthoPhoto, edge_weight, fit_ground_plane, footprint_ne
from auxgps.photo.types import R_ned_cam_nadir

TEX_M = 0.02  # the ground texture's cell, m
TEX_SIDE_M = 80.0
GSD_M = 0.05


def _texture(seed: int = 0) -> np.ndarray:
    """An (N, N, 3) uint8 ground over north, east in [-40, 40) m: smooth colour plus blobs of all sizes."""
    import cv2

    rng = np.random.default_rng(seed)
    n = int(TEX_SIDE_M / TEX_M)
    out = np.zeros((n, n, 3), np.float32)
    for size in (8, 32, 128, 512):
        small = rng.random((size, size, 3)).astype(np.float32)
        out += cv2.resize(small, (n, n), interpolation=cv2.INTER_CUBIC)
    out -= out.min()
    return (255 * out / out.max()).astype(np.uint8)


def _ground_at(tex: np.ndarray, north_m: np.ndarray, east_m: np.ndarray) -> np.ndarray:
    import cv2

    col = ((east_m + TEX_SIDE_M / 2) / TEX_M - 0.5).astype(np.float32)
    row = ((TEX_SIDE_M / 2 - north_m) / TEX_M - 0.5).astype(np.float32)
    return cv2.remap(tex, col, row, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


def _photograph(tex: np.ndarray, camera: PinholeCamera, pose: CameraPose) -> np.ndarray:
    """What the camera sees of the ground plane down = 0 (every ray meets it)."""
    vv, uu = np.mgrid[0 : camera.height_px, 0 : camera.width_px]
    rays = pose.rays_ned(camera, np.column_stack([uu.ravel(), vv.ravel()]).astype(float))
    s = -pose.p_cam_in_ned_m[2] / rays[:, 2]
    p = pose.p_cam_in_ned_m + s[:, None] * rays
    return _ground_at(tex, p[:, 0].reshape(uu.shape), p[:, 1].reshape(uu.shape))


def _survey():
    camera = PinholeCamera(640, 480, np.array([[520.0, 0, 319.5], [0, 520.0, 239.5], [0, 0, 1]]), np.array([-0.05, 0.01, 0, 0]))
    poses = []
    for k, (n, e, heading_deg, tilt_deg) in enumerate([(-8, -8, 0, 0), (-8, 8, 90, 3), (8, -8, 200, -2), (8, 8, 30, 4)]):
        R = R_ned_cam_nadir(np.deg2rad(heading_deg))
        R = R_ned_body_from_euler(np.deg2rad(tilt_deg), np.deg2rad(-tilt_deg / 2), 0.0) @ R
        poses.append(CameraPose(np.array([n, e, -30.0 - k]), R))
    return camera, poses


def _grid():
    n_top, e_left = 25.0, -25.0

    def ne_of_colrow(col, row):
        return n_top - np.asarray(row) * GSD_M, e_left + np.asarray(col) * GSD_M

    def colrow_of_ne(n, e):
        return (np.asarray(e) - e_left) / GSD_M, (n_top - np.asarray(n)) / GSD_M

    return ne_of_colrow, colrow_of_ne, int(50.0 / GSD_M)


def _mosaic(tex, camera, poses, moved=None):
    photos = {f"p{k}": _photograph(tex, camera, pose) for k, pose in enumerate(poses)}
    if moved is not None:  # the mosaic is told a pose the photo was not taken from
        k, delta = moved
        poses = list(poses)
        poses[k] = CameraPose(poses[k].p_cam_in_ned_m + delta, poses[k].R_ned_cam)
    ortho = [OrthoPhoto(f"p{k}", camera, pose) for k, pose in enumerate(poses)]
    ne_of, colrow_of, side = _grid()
    return Mosaic(ortho, photos.__getitem__, GroundPlane(0.0, 0.0, 0.0, 0.0, 0), ne_of, colrow_of), side


def test_mosaic_of_true_poses_is_the_ground_and_its_seams_are_closed():
    tex = _texture()
    camera, poses = _survey()
    mosaic, side = _mosaic(tex, camera, poses)
    rgb, seen = mosaic.tile(0, 0, side, side)
    ne_of, _, _ = _grid()
    cc, rr = np.meshgrid(np.arange(side) + 0.5, np.arange(side) + 0.5)
    truth = _ground_at(tex, *ne_of(cc, rr))
    assert seen.mean() > 0.5
    err = np.abs(rgb.astype(float) - truth.astype(float))[seen]
    assert np.median(err) < 3.0, np.median(err)  # grey levels: resampled twice, nothing misplaced
    assert np.percentile(err, 99) < 25.0
    seams = mosaic.seam_offsets(GSD_M)
    assert len(seams) >= 4  # the four photos overlap side by side and across
    assert max(s.offset_m for s in seams) < 0.4 * GSD_M, [s.offset_m for s in seams]


def test_a_pose_told_wrong_shows_as_its_seam_offset():
    tex = _texture(1)
    camera, poses = _survey()
    delta = np.array([0.30, -0.20, 0.0])  # north, east, m
    mosaic, _ = _mosaic(tex, camera, poses, moved=(2, delta))
    seams = mosaic.seam_offsets(GSD_M)
    with_moved = [s for s in seams if "p2" in (s.a, s.b)]
    others = [s for s in seams if "p2" not in (s.a, s.b)]
    assert with_moved and others
    for s in with_moved:
        # The grid's x is east and its y north; photo p2 drawn delta away from where it was taken.
        sign = 1.0 if s.b == "p2" else -1.0
        assert np.allclose(sign * s.offset_xy_m, [delta[1], delta[0]], atol=0.03), (s.a, s.b, s.offset_xy_m)
    assert max(s.offset_m for s in others) < 0.03


def test_ground_plane_fit_ignores_trees_and_footprints_need_the_ground():
    rng = np.random.default_rng(2)
    p = np.column_stack([rng.uniform(-100, 100, 500), rng.uniform(-100, 100, 500), np.zeros(500)])
    p[:, 2] = 0.02 * p[:, 0] - 0.01 * p[:, 1] + 60.0 + rng.normal(0, 0.1, 500)
    p[:40, 2] -= 12.0  # tree tops
    plane = fit_ground_plane(p)
    assert abs(plane.a - 0.02) < 2e-3 and abs(plane.b + 0.01) < 2e-3 and abs(plane.c - 60.0) < 0.05
    assert plane.n_points <= 460 and plane.rms_m < 0.15
    with pytest.raises(ValueError, match="at least 3 points"):
        fit_ground_plane(p[:2])
    camera, poses = _survey()
    plane0 = GroundPlane(0.0, 0.0, 0.0, 0.0, 0)
    assert footprint_ne(OrthoPhoto("down", camera, poses[0]), plane0) is not None
    forward = CameraPose(np.array([0.0, 0.0, -30.0]), R_ned_body_from_euler(0.0, 0.0, 0.0) @ np.array([[0, 0, 1], [1, 0, 0], [0, 1, 0.0]]))
    assert footprint_ne(OrthoPhoto("horizon", camera, forward), plane0) is None
    w = edge_weight(64, 48)
    assert w[0].max() < 0.01 and 0.85 < w[24, 32] <= w.max() <= 1.0


BRIGHTON = Path(__file__).resolve().parents[2] / "shared" / "data" / "brighton_beach" / "images"


@pytest.mark.skipif(not BRIGHTON.is_dir(), reason=f"the Brighton Beach survey is not at {BRIGHTON}")
def test_ortho_build_command_on_a_real_survey(tmp_path):
    from auxgps.cli import main

    out = tmp_path / "brighton.tif"
    images = tmp_path / "images"
    images.mkdir()
    for name in ("DJI_0018.JPG", "DJI_0019.JPG", "DJI_0020.JPG", "DJI_0032.JPG", "DJI_0033.JPG", "DJI_0034.JPG"):
        shutil.copy(BRIGHTON / name, images / name)
    config = Path(__file__).resolve().parents[1] / "config" / "cameras" / "dji_fc300s.yaml"
    assert main(["ortho", "build", "--images", str(images), "--camera", str(config), "--out", str(out), "--gsd-m", "0.1",
                 "--max-side", "800", "--quiet"]) == 0
    with rasterio.open(out) as ds:
        assert ds.crs.to_epsg() == 32615  # UTM 15N, Duluth's zone
        assert ds.res == pytest.approx((0.1, 0.1))
        assert ds.count == 3 and len(ds.overviews(1)) >= 2
        mask = ds.read_masks(1)
        assert 0.3 < (mask > 0).mean() < 1.0  # the photos' footprints, and no data around them
        centre = ds.xy(ds.height // 2, ds.width // 2)
    report = json.loads(out.with_suffix(".json").read_text())
    assert len(report["photos"]) == 6 and report["seams"]["pairs"] >= 5
    assert report["seams"]["median_m"] < 1.0
    lon, lat = rasterio.warp.transform(ds.crs, "EPSG:4326", [centre[0]], [centre[1]])
    assert abs(lat[0] - 46.8427) < 0.001 and abs(lon[0] + 91.9944) < 0.001
