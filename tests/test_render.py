"""The simulated camera agrees with the camera model it renders for."""

import time

import cv2
import numpy as np

from auxgps.core.camera import CameraPose
from auxgps.core.geometry import R_BODY_CAM_DOWN, R_ned_body_from_euler
from auxgps.sim.render import Renderer, face_shade
from tests.conftest import make_world

tol_px = 1.0


def tilted_pose():
    return CameraPose(np.array([-3.0, -2.0, -15.0]), R_ned_body_from_euler(0.06, -0.04, 0.4) @ R_BODY_CAM_DOWN)


def test_rendered_cube_corners_are_where_the_camera_projects_them(camera):
    world = make_world([{"east_m": 1.0, "north_m": 2.0, "size_m": 3.0, "color": "white", "yaw_deg": 25}])
    frame = Renderer(world, camera).render(tilted_pose())
    gray = cv2.cvtColor(frame.image_bgr, cv2.COLOR_BGR2GRAY)
    # The cube's silhouette polygon, found in the image, has its corners at projected vertices.
    mask = (np.abs(gray.astype(int) - 128) > 20).astype(np.uint8)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    outline = max(contours, key=cv2.contourArea).reshape(-1, 2).astype(float)
    hull = cv2.convexHull(frame.visible_vertices_px.astype(np.float32)).reshape(-1, 2)
    # Every projected silhouette vertex has rendered pixels of the cube within 1 px.
    for v in hull:
        assert np.min(np.linalg.norm(outline - v, axis=1)) <= tol_px + 0.5


def test_rendered_point_map_matches_geometry(camera):
    world = make_world([{"east_m": 0.0, "north_m": 0.0, "size_m": 2.0, "color": "red"}])
    pose = CameraPose(np.array([0.0, 0.0, -10.0]), R_BODY_CAM_DOWN)
    frame = Renderer(world, camera).render(pose)
    P = frame.points_ned()
    assert np.allclose(P[360, 640], [0.0, 0.0, -2.0], atol=1e-3)  # top of the cube below the camera
    assert np.allclose(P[5, 5, 2], 0.0, atol=1e-3)  # ground in the corner


def test_faces_differ_in_brightness():
    world = make_world([{"east_m": 0.0, "north_m": 0.0, "size_m": 1.0, "color": "white"}])
    shades = [round(face_shade(n), 3) for _, n in world.cubes[0].faces()]
    assert len(set(shades)) == len(shades)


def test_near_cube_hides_far_cube(camera):
    # A tall cube between the camera and a small one: the small one's hidden side must not show through.
    world = make_world(
        [
            {"east_m": 5.0, "north_m": 0.0, "size_m": 3.0, "color": "blue"},
            {"east_m": 6.8, "north_m": 0.0, "size_m": 0.5, "color": "red"},
        ]
    )
    frame = Renderer(world, camera).render(CameraPose(np.array([0.0, 0.0, -10.0]), R_BODY_CAM_DOWN))
    reddish = (frame.image_bgr[..., 2] > 100) & (frame.image_bgr[..., 0] < 100)
    assert not reddish.any()
    small_top = world.cubes[1].vertices_ned()[4:]
    uv, _ = frame.pose.project(camera, small_top)
    depth_there = frame.depth_m[np.rint(uv[:, 1]).astype(int), np.rint(uv[:, 0]).astype(int)]
    assert np.all(depth_there < frame.pose.ned_to_cam(small_top)[:, 2])  # something nearer covers it


def test_textured_ground_is_warped_by_the_ground_homography(camera, tmp_path):
    tex = np.zeros((400, 400, 3), np.uint8)
    tex[190:211, 190:211] = 255  # a 1.05 m white square centred on the origin (0.05 m/px)
    cv2.imwrite(str(tmp_path / "tex.png"), tex)
    world = make_world([], ground={"texture": str(tmp_path / "tex.png"), "m_per_px": 0.05})
    frame = Renderer(world, camera).render(CameraPose(np.array([0.0, 0.0, -10.0]), R_BODY_CAM_DOWN))
    ys, xs = np.nonzero(frame.image_bgr[..., 0] > 128)
    assert abs(xs.mean() - 640.0) < 0.5 and abs(ys.mean() - 360.0) < 0.5  # principal point (W/2, H/2)
    assert abs((xs.max() - xs.min() + 1) - 67) <= 2  # 1.05 m at 10 m with f = 640 px


def test_full_frame_renders_fast_enough_to_be_useful(camera):
    # Not a speed target (those live in `auxgps bench`): a guard against an accidental per-pixel Python loop.
    world = make_world([{"east_m": float(e), "north_m": 0.0, "size_m": 1.0} for e in range(-6, 7, 3)])
    r = Renderer(world, camera)
    r.render(tilted_pose())
    t0 = time.perf_counter()
    r.render(tilted_pose())
    assert time.perf_counter() - t0 < 2.0


def test_a_lens_on_the_ground_sees_nothing(camera, tmp_path):
    # A mission starts and ends standing on the ground, where the ground-plane homography degenerates (the
    # texture warp never returned): the frame is black, its depth 0, and a few centimetres up it is the ground.
    tex = np.full((400, 400, 3), 200, np.uint8)
    cv2.imwrite(str(tmp_path / "tex.png"), tex)
    world = make_world([], ground={"texture": str(tmp_path / "tex.png"), "m_per_px": 0.05})
    r = Renderer(world, camera)
    for down_m in (0.0, -0.04, 0.3):
        frame = r.render(CameraPose(np.array([0.0, 0.0, down_m]), R_BODY_CAM_DOWN))
        assert frame.image_bgr.max() == 0 and frame.depth_m.max() == 0.0
    up = r.render(CameraPose(np.array([0.0, 0.0, -0.1]), R_BODY_CAM_DOWN))
    assert up.image_bgr.min() == 200 and np.allclose(up.depth_m, 0.1, atol=1e-5)
