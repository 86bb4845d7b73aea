"""Known answers and round trips for frames, rotations, the camera model and the local frame."""

import numpy as np
import pytest

from auxgps.core.camera import CameraPose, PinholeCamera
from auxgps.core.geometry import (
    cross_matrix,
    R_BODY_CAM_DOWN,
    LocalFrame,
    R_body_cam_from_mount,
    R_ned_body_from_euler,
    euler_from_R_ned_body,
    intersect_rays_with_horizontal_plane,
)
from auxgps.errors import CameraError

atol_m = 1e-9  # 1 nanometre
atol_px = 1e-6
atol_rad = 1e-12


def level_pose(n=0.0, e=0.0, alt=15.0, yaw=0.0):
    return CameraPose(np.array([n, e, -alt]), R_ned_body_from_euler(0.0, 0.0, yaw) @ R_BODY_CAM_DOWN)


@pytest.mark.parametrize("roll,pitch,yaw", [(0.1, -0.2, 0.3), (-1.0, 0.5, -3.0), (0.0, 0.0, np.pi / 2)])
def test_euler_round_trip(roll, pitch, yaw):
    R = R_ned_body_from_euler(roll, pitch, yaw)
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.allclose(euler_from_R_ned_body(R), (roll, pitch, yaw), atol=atol_rad)


def test_yaw_90_turns_nose_east():
    R = R_ned_body_from_euler(0.0, 0.0, np.pi / 2)
    assert np.allclose(R @ [1, 0, 0], [0, 1, 0], atol=1e-12)


def test_positive_pitch_raises_nose():
    R = R_ned_body_from_euler(0.0, 0.1, 0.0)
    assert (R @ [1, 0, 0])[2] < 0  # nose points up (negative down)


def test_default_mount_looks_down_with_image_top_forward():
    assert np.allclose(R_BODY_CAM_DOWN @ [0, 0, 1], [0, 0, 1])  # optical axis = body down
    assert np.allclose(R_BODY_CAM_DOWN @ [0, -1, 0], [1, 0, 0])  # image up = nose
    assert np.allclose(R_body_cam_from_mount(), R_BODY_CAM_DOWN)


def test_centre_pixel_of_level_camera_maps_to_point_below(camera):
    pose = level_pose(3.0, -2.0, 15.0)
    ray = pose.rays_ned(camera, np.array([[640.0, 360.0]]))
    p, ok = intersect_rays_with_horizontal_plane(pose.p_cam_in_ned_m, ray)
    assert ok[0]
    assert np.allclose(p[0], [3.0, -2.0, 0.0], atol=atol_m)


def test_image_corner_at_45_degrees_for_90_degree_hfov(camera):
    pose = level_pose(alt=10.0)
    p, _ = intersect_rays_with_horizontal_plane(pose.p_cam_in_ned_m, pose.rays_ned(camera, np.array([[1280.0, 360.0]])))
    assert np.allclose(p[0], [0.0, 10.0, 0.0], atol=1e-9)  # right edge of the image = east at yaw 0


def test_project_unproject_round_trip(camera):
    rng = np.random.default_rng(3)
    pose = CameraPose(np.array([1.0, 2.0, -12.0]), R_ned_body_from_euler(0.05, -0.04, 1.2) @ R_BODY_CAM_DOWN)
    pts = np.column_stack([rng.uniform(-5, 5, 50), rng.uniform(-5, 5, 50), rng.uniform(-3, 0, 50)]) + [1, 2, 0]
    uv, front = pose.project(camera, pts)
    assert front.all()
    rays = pose.rays_ned(camera, uv)
    # Each point lies on its own ray.
    off = pts - pose.p_cam_in_ned_m
    perp = off - np.sum(off * rays, axis=1, keepdims=True) * rays
    assert np.abs(perp).max() < atol_m * 1e3  # 1 micrometre


def test_distorted_camera_round_trip():
    K = np.array([[700.0, 0, 650.0], [0, 705.0, 350.0], [0, 0, 1]])
    cam = PinholeCamera(1280, 720, K, np.array([-0.2, 0.05, 0.001, -0.001, 0.0]))
    uv = np.array([[10.0, 20.0], [640.0, 360.0], [1200.0, 700.0]])
    rays = cam.pixels_to_rays_cam(uv)
    back, front = cam.project_cam(rays * 5.0)
    assert front.all()
    assert np.allclose(back, uv, atol=1e-3)


def test_bad_camera_is_named():
    with pytest.raises(CameraError, match="focal"):
        PinholeCamera(1280, 720, np.diag([-1.0, 1.0, 1.0]))
    with pytest.raises(CameraError, match="field of view"):
        PinholeCamera.from_hfov(1280, 720, 4.0)


def test_local_frame_round_trip_through_pymap3d():
    frame = LocalFrame(47.397742, 8.545594, 488.0)
    p = np.array([[10.0, -20.0, -15.0], [0.0, 0.0, 0.0], [-300.0, 250.0, 3.0]])
    lat, lon, alt = frame.to_geodetic(p)
    back = frame.to_ned(lat_deg=lat, lon_deg=lon, alt_amsl_m=alt)
    assert np.allclose(back, p, atol=1e-6)  # 1 micrometre
    assert lat[0] > frame.lat_deg and lon[0] < frame.lon_deg and alt[0] == pytest.approx(503.0, abs=1e-3)


def test_cross_matrix_is_the_cross_product_one_or_many():
    rng = np.random.default_rng(2)
    v, u = rng.normal(size=(5, 3)), rng.normal(size=(5, 3))
    np.testing.assert_allclose(np.einsum("kij,kj->ki", cross_matrix(v), u), np.cross(v, u), atol=1e-12)
    np.testing.assert_allclose(cross_matrix(v[0]) @ u[0], np.cross(v[0], u[0]), atol=1e-12)
