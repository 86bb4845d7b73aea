"""Featureless patches (a lake, a bare field, a uniform roof) on a simulated world's ground: the renderer paints
exactly their colour where they are and nothing else, and the world says which one is under a point."""

import cv2
import numpy as np
import pytest
import yaml

from auxgps.core.camera import CameraPose
from auxgps.core.geometry import R_BODY_CAM_DOWN, R_ned_body_from_euler
from auxgps.errors import ConfigError
from auxgps.sim.render import Renderer, face_shade
from auxgps.sim.world import load_world
from tests.test_orthophoto_world import ORIGIN, UTM, write_ortho

LAKE = {"name": "lake", "color": [150, 90, 40],
        "corners_m": [[-3.0, -5.0], [-2.0, 4.0], [3.5, 2.0], [1.0, -1.0], [2.5, -6.0]]}  # north, east, m; not convex
edge_px = 2  # the anti-aliased edge: OpenCV's blends the patch with the ground up to about 2 px out of its outline
atol_blend_grey = 1.5  # an edge pixel off the line from the ground's colour to the patch's: uint8 rounding per channel


def write_world(tmp_path, ground, patches=(), name="world.yaml"):
    path = tmp_path / name
    path.write_text(yaml.safe_dump({"origin": ORIGIN, "ground": ground, "patches": list(patches)}))
    return path


def ground_of_kind(tmp_path, kind):
    if kind == "color":
        return {"color": "grey"}
    if kind == "texture":
        texture = np.random.default_rng(3).integers(0, 256, (300, 300, 3), dtype=np.uint8)
        cv2.imwrite(str(tmp_path / "tex.png"), texture)
        return {"texture": "tex.png", "m_per_px": 0.05}
    return {"orthophoto": str(write_ortho(tmp_path / "ortho.tif", UTM, half_m=12.0, res_m=0.1, overviews=()))}


def inside_and_outside(frame, world):
    """(H, W) bool twice: pixels whose ground point is on patch 0, and off every patch, both at least ``edge_px``
    from the outline."""
    H, W = frame.depth_m.shape
    on = (world.patch_at(frame.points_ned()[..., :2].reshape(-1, 2)) == 0).reshape(H, W).astype(np.uint8)
    kernel = np.ones((2 * edge_px + 1, 2 * edge_px + 1), np.uint8)
    return cv2.erode(on, kernel).astype(bool), ~cv2.dilate(on, kernel).astype(bool)


@pytest.mark.parametrize("kind", ["color", "texture", "orthophoto"])
def test_a_patch_is_its_exact_colour_and_leaves_the_rest_alone(tmp_path, camera, kind):
    ground = ground_of_kind(tmp_path, kind)
    plain = load_world(write_world(tmp_path, ground, name="plain.yaml"))
    lake = load_world(write_world(tmp_path, ground, [LAKE], name="lake.yaml"))
    pose = CameraPose(np.array([0.0, 0.0, -10.0]), R_BODY_CAM_DOWN)
    before, after = Renderer(plain, camera).render(pose), Renderer(lake, camera).render(pose)
    inside, outside = inside_and_outside(after, lake)
    assert inside.sum() > 0.1 * inside.size  # the lake fills a good part of the view
    assert np.all(after.image_bgr[inside] == LAKE["color"])
    assert np.array_equal(after.image_bgr[outside], before.image_bgr[outside])
    assert np.array_equal(after.depth_m, before.depth_m)


def test_a_patch_reaching_behind_a_tilted_camera_has_no_fold(tmp_path, camera):
    # Low and pitched 45 degrees up from straight down: the patch's southern corners are behind the lens, and would
    # project mirrored into the image without the near-plane clip.
    field = {"name": "field", "color": "green", "corners_m": [[-30.0, -20.0], [-30.0, 20.0], [40.0, 6.0], [25.0, -12.0]]}
    world = load_world(write_world(tmp_path, {"color": "grey"}, [field]))
    pose = CameraPose(np.array([0.0, 0.0, -5.0]), R_ned_body_from_euler(0.0, np.deg2rad(45.0), 0.2) @ R_BODY_CAM_DOWN)
    assert np.any(pose.ned_to_cam(np.column_stack([world.patches[0].corners_ne_m, np.zeros(4)]))[:, 2] < 0)
    frame = Renderer(world, camera).render(pose)
    inside, outside = inside_and_outside(frame, world)
    assert inside.any() and outside.any()
    assert np.all(frame.image_bgr[inside] == world.patches[0].color_bgr)
    assert np.all(frame.image_bgr[outside] == world.ground_color_bgr)
    # The edge blends the two colours: every pixel lies between them.
    grey, green = np.array(world.ground_color_bgr, float), np.array(world.patches[0].color_bgr, float)
    t = np.clip((frame.image_bgr - grey) @ (green - grey) / np.sum((green - grey) ** 2), 0.0, 1.0)
    assert np.abs(frame.image_bgr - (grey + t[..., None] * (green - grey))).max() <= atol_blend_grey


def test_a_cube_on_a_patch_hides_it(tmp_path, camera):
    path = write_world(tmp_path, {"color": "grey"}, [LAKE])
    path.write_text(path.read_text() + "cubes: [{north_m: 0.0, east_m: 0.0, size_m: 1.0, color: white}]\n")
    world = load_world(path)
    frame = Renderer(world, camera).render(CameraPose(np.array([0.0, 0.0, -10.0]), R_BODY_CAM_DOWN))
    assert world.patch_at(np.zeros((1, 2)))[0] == 0
    top_bgr = np.rint(np.multiply(world.cubes[0].color_bgr, face_shade(np.array([0.0, 0.0, -1.0]))))
    np.testing.assert_array_equal(frame.image_bgr[360, 640], top_bgr)  # the cube's top, straight below


def test_patch_at_names_the_patch_on_top(tmp_path):
    field = {"color": "green", "corners_m": [[-10.0, -10.0], [-10.0, 10.0], [10.0, 10.0], [10.0, -10.0]]}
    roof = {"name": "roof", "color": "red", "corners_m": [[0.0, 0.0], [0.0, 2.0], [2.0, 2.0], [2.0, 0.0]]}
    world = load_world(write_world(tmp_path, {"color": "grey"}, [field, roof]))
    assert [p.name for p in world.patches] == ["", "roof"]
    np.testing.assert_array_equal(world.patch_at(np.array([[20.0, 0.0], [-5.0, 3.0], [1.0, 1.5]])), [-1, 0, 1])
    none = load_world(write_world(tmp_path, {"color": "grey"}, name="none.yaml"))
    assert none.patch_at(np.zeros((3, 2))).tolist() == [-1, -1, -1]


TRIANGLE_M = [[0.0, 0.0], [1.0, 1.0], [0.0, 1.0]]
GREY = {"color": "grey"}


@pytest.mark.parametrize(
    "ground, patch, message",
    [
        (GREY, {"color": "blue", "corners_m": TRIANGLE_M[:2]}, "patches.0.corners_m: List should have at least 3"),
        (GREY, {"color": "blue", "corners_m": [[0.0, 0.0], [1.0, float("nan")], [0.0, 1.0]]},
         "patches.0.corners_m.1.1: Input should be a finite number"),
        (GREY, {"color": "sky", "corners_m": TRIANGLE_M}, "unknown colour name 'sky'"),
        # refused before the rasters are opened: they need not exist
        ({"orthophoto": "o.tif", "dsm": "d.tif"}, {"color": "blue", "corners_m": TRIANGLE_M}, "patches lie on flat ground"),
    ],
)
def test_a_bad_patch_is_a_config_error_naming_it(tmp_path, ground, patch, message):
    path = write_world(tmp_path, ground, [patch])
    with pytest.raises(ConfigError) as err:
        load_world(path)
    assert str(path) in str(err.value) and message in str(err.value)
