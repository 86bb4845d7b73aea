"""Following a fix's inliers into the next frames by optical flow (auxgps.core.tracking, Localiser.locate_followed)."""

import cv2
import numpy as np
import pytest

from auxgps.config import load_pipeline_config
from auxgps.core.camera import CameraPose
from auxgps.core.geometry import R_BODY_CAM_DOWN, R_ned_body_from_euler
from auxgps.core.localise import Fix, Localiser, NoFix
from auxgps.core.tracking import Followed, InlierFlow, spread_over
from auxgps.evaluation.scenario import run_once
from auxgps.sim.texture import gravel_texture
from tests.test_pipeline import synthetic_map, two_cubes_crossed


def textured(seed: int = 4) -> np.ndarray:
    return cv2.cvtColor(cv2.resize(gravel_texture(256, seed=seed), (640, 480), interpolation=cv2.INTER_LINEAR), cv2.COLOR_BGR2GRAY)


def shifted(grey: np.ndarray, du: float, dv: float) -> np.ndarray:
    return cv2.warpAffine(grey, np.float32([[1, 0, du], [0, 1, dv]]), grey.shape[::-1], flags=cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_REFLECT)


def corners(grey: np.ndarray, n: int = 80) -> np.ndarray:
    return cv2.goodFeaturesToTrack(grey, n, 0.01, 12, mask=None, blockSize=7)[:, 0].astype(float)


def test_the_flow_carries_each_point_to_where_the_image_moved():
    a = textured()
    b = shifted(a, 6.3, -2.6)
    uv0 = corners(a)
    uv0 = uv0[(uv0[:, 0] > 30) & (uv0[:, 0] < 610) & (uv0[:, 1] > 30) & (uv0[:, 1] < 450)]
    flow = InlierFlow()
    flow.remember(a, Followed(uv0, np.arange(len(uv0)), 1.0, 2.0))
    guess = uv0 + [4.0, -1.0]  # a prediction 2 px off
    guess[0] = np.nan  # a landmark the prediction puts behind the camera
    got = flow.follow(b, guess)
    assert 0 not in got.lm_id and len(got.lm_id) >= 0.9 * (len(uv0) - 1)
    assert np.abs(got.uv_px - (uv0[got.lm_id] + [6.3, -2.6])).max() < 0.15
    assert got.scale == 1.0 and got.from_full_s == 2.0


def test_points_on_ground_that_changed_do_not_come_back_and_are_dropped():
    a = textured()
    b = shifted(a, 3.0, 1.0)
    b[:, 320:] = shifted(textured(seed=9), 3.0, 1.0)[:, 320:]  # the right half is other ground now
    # Points are taken 120 px or more from the border: on the pyramid's top level a 21 px window spans 168 px.
    uv0 = corners(a)
    uv0 = uv0[(uv0[:, 1] > 30) & (uv0[:, 1] < 450) & ((uv0[:, 0] < 200) | (uv0[:, 0] > 440)) & (uv0[:, 0] > 30) & (uv0[:, 0] < 610)]
    flow = InlierFlow()
    flow.remember(a, Followed(uv0, np.arange(len(uv0)), 1.0, 0.0))
    got = flow.follow(b, uv0 + [3.0, 1.0])
    left = uv0[:, 0] < 320
    kept = np.isin(np.arange(len(uv0)), got.lm_id)
    assert kept[left].mean() > 0.9
    # Most are dropped. Started where they should be, a few sit still on the new ground both ways: their landmarks'
    # fit (locate_followed) must drop those.
    assert kept[~left].mean() < 0.35
    with pytest.raises(ValueError, match="follows one of 640x480"):
        flow.follow(a[:, :600], uv0)


@pytest.fixture
def scene(camera):
    rng = np.random.default_rng(7)
    pts = np.column_stack([rng.uniform(-6, 6, 40), rng.uniform(-6, 6, 40), -rng.uniform(0, 3, 40)])
    lm, _ = synthetic_map(camera, pts)
    R = R_ned_body_from_euler(0.05, -0.03, 0.4)
    pose = CameraPose(np.array([1.0, -0.5, -15.0]), R @ R_BODY_CAM_DOWN)
    uv, _ = pose.project(camera, pts)
    return lm, R, uv


def test_followed_pairs_locate_the_frame_and_a_few_wrong_ones_do_not_move_it(camera, pipeline, scene):
    lm, R, uv = scene
    loc = Localiser(pipeline, camera, R_BODY_CAM_DOWN, lm)
    ids = np.arange(len(uv))
    fix = loc.locate_followed(Followed(uv, ids, 1.0, 4.0), 4.1, R, 15.0)
    assert isinstance(fix, Fix) and fix.followed and fix.n_inliers == len(uv)
    assert np.linalg.norm(fix.p_ned_m[:2] - [1.0, -0.5]) < 0.05
    assert fix.inliers.from_full_s == 4.0 and set(fix.inliers.lm_id) == set(ids)
    wrong = ids.copy()
    wrong[:8] = np.roll(wrong[:8], 1)  # eight pixels slid onto their neighbours' landmarks
    bad = loc.locate_followed(Followed(uv, wrong, 1.0, 4.0), 4.1, R, 15.0)
    assert isinstance(bad, Fix) and bad.n_inliers == len(uv) - 8
    assert np.linalg.norm(bad.p_ned_m - fix.p_ned_m) < 0.02


def test_pairs_the_flow_lost_give_no_fix_and_the_frame_is_a_full_one(camera, pipeline, scene):
    lm, R, uv = scene
    loc = Localiser(pipeline, camera, R_BODY_CAM_DOWN, lm)
    ids = np.arange(len(uv))
    lost = ids.copy()
    lost[:24] = np.roll(lost[:24], 5)  # most of them on the wrong landmark
    res = loc.locate_followed(Followed(uv, lost, 1.0, 4.0), 4.1, R, 15.0)
    assert isinstance(res, NoFix) and "followed landmarks stay inliers" in res.reason
    res = loc.locate_followed(Followed(uv[:3], ids[:3], 1.0, 4.0), 4.1, R, 15.0)
    assert isinstance(res, NoFix) and res.reason.startswith("3 landmarks followed")


@pytest.mark.slow
def test_at_30_frames_a_second_positioning_follows_two_frames_in_three_and_mapping_keeps_to_10():
    """The estimator follows a full frame's inliers into the frames of the next 0.08 s (positioning.follow_for_s)
    and maps at most a frame every 0.08 s (mapping.min_interval_s): at 30 frames a second two positioning frames
    in three are followed, as accurate as the full ones, and the survey maps about as many frames as at 10."""
    pipeline = load_pipeline_config()
    world, sim = two_cubes_crossed()
    at30 = run_once(world, 12.0, 30.0, 11, pipeline, sim)
    at10 = run_once(world, 12.0, 10.0, 11, pipeline, sim, mapping_fps=10.0)
    followed = at30.fix_followed
    err = np.linalg.norm(at30.fix_err_ne_m, axis=1)
    assert 0.45 < followed.mean() < 0.7
    assert np.sqrt(np.mean(err[followed] ** 2)) < 0.15 and err[followed].max() < 0.5
    assert not at10.fix_followed.any()
    # The simulator steps 10 ms: "30" frames a second are a frame every 0.03 s, so every third is mapped, 0.09 s apart
    # against 0.1 at 10 frames a second.
    assert len(at30.mapping_ms) == pytest.approx(len(at10.mapping_ms) / 0.9, rel=0.05)


def test_points_kept_are_spread_over_the_image_and_all_kept_when_few():
    rng = np.random.default_rng(2)
    crowd = np.column_stack([rng.uniform(0, 100, 300), rng.uniform(0, 100, 300)])  # one corner of a 400x400 image
    few = np.array([[350.0, 350.0], [50.0, 350.0], [350.0, 50.0]])
    uv = np.vstack([crowd, few])

    keep = spread_over(uv, 400, 400, 10)
    assert len(keep) == 10 and len(set(keep)) == 10
    assert {300, 301, 302} <= set(keep)  # each lone point of its cell comes first
    assert len(spread_over(uv[:5], 400, 400, 10)) == 5
