"""The autopilot's heading error: what a map geotagged with it does to a fix, and how it is solved.

Ground points with unique descriptors are seen by a camera flying north at 40 m; the mapper geotags them with the
telemetry's heading, which is off by a known error. The real mapper and localiser are used, so that what
``auxgps.core.heading`` assumes is checked against what they do, not against itself.
"""

import numpy as np

from auxgps.config import HeadingConfig, PipelineConfig
from auxgps.core.camera import camera_from_config
from auxgps.core.features import Features
from auxgps.core.geometry import R_body_cam_from_mount, R_ned_body_from_euler
from auxgps.core.heading import HeadingEstimate, HeadingTracker, MotionView, ground_points_ne, heading_from_motion
from auxgps.core.landmarks import LandmarkMap
from auxgps.core.localise import Fix, Localiser, PositionPrior
from auxgps.core.mapping import Mapper
from auxgps.core.nav import NavSample

ALT_M = 40.0


class Scene:
    """Random ground points, and the features a camera at ``c_ne`` with heading ``yaw`` sees of them."""

    def __init__(self, pipeline: PipelineConfig, seed: int = 0) -> None:
        rng = np.random.default_rng(seed)
        self.cfg = pipeline
        self.camera = camera_from_config(pipeline.camera)
        m = pipeline.mount
        self.R_body_cam = R_body_cam_from_mount(*np.deg2rad([m.roll_deg, m.pitch_deg, m.yaw_deg]))
        n = 20000
        self.points = np.column_stack([rng.uniform(-80, 280, n), rng.uniform(-120, 120, n), np.zeros(n)])
        self.descriptors = rng.integers(0, 256, (n, 32), dtype=np.uint8)
        self.rng = rng

    def features(self, c_ne: np.ndarray, yaw_rad: float) -> Features:
        from auxgps.core.camera import CameraPose

        pose = CameraPose(np.array([c_ne[0], c_ne[1], -ALT_M]), R_ned_body_from_euler(0.0, 0.0, yaw_rad) @ self.R_body_cam)
        uv, front = pose.project(self.camera, self.points)
        inside = front & self.camera.in_image(np.nan_to_num(uv, nan=-1e6), -20.0)
        keep = np.flatnonzero(inside)
        keep = keep[self.rng.permutation(len(keep))[:600]]
        uv = uv[keep] + self.rng.normal(0, 0.3, (len(keep), 2))
        return Features(uv, self.descriptors[keep], np.zeros(len(keep), int))


def _views_along_north(scene, pipeline, b_rad, k_from, k_to, spacing_m=2.0):
    """The mapper's views of a flight north at 40 m whose telemetry heading is ``b_rad`` off (true heading 0)."""
    lm = LandmarkMap()
    mapper = Mapper(pipeline, scene.camera, scene.R_body_cam, lm)
    R_told = R_ned_body_from_euler(0.0, 0.0, b_rad)
    views = []
    for k in range(k_from, k_to):
        c = np.array([spacing_m * k, 0.0])
        feats = scene.features(c, 0.0)
        res = mapper.process(feats, NavSample(0.25 * k, np.array([c[0], c[1], -ALT_M]), ALT_M, R_told))
        sel = np.flatnonzero(res.landmark_ids >= 0)
        cam = np.array([c[0], c[1], -ALT_M])
        rays = scene.camera.pixels_to_rays_cam(feats.uv_px[sel]) @ (R_told @ scene.R_body_cam).T
        g = ground_points_ne(cam, rays, lm.p_ned_m[res.landmark_ids[sel], 2].astype(float))
        order = np.argsort(res.landmark_ids[sel])
        views.append(MotionView(0.25 * k, c, res.landmark_ids[sel][order], g[order]))
    return lm, views


def test_the_same_landmarks_seen_from_two_places_give_the_heading_error(pipeline):
    """Two mapping frames 16 m apart: their ground points of the same landmarks are b * B^perp apart, and the
    median of that over the baseline is the heading error."""
    scene = Scene(pipeline)
    for b_deg in (1.5, -0.8):
        _, views = _views_along_north(scene, pipeline, np.deg2rad(b_deg), 0, 9)
        m = heading_from_motion(views[8], views[0], shift_sigma_m=0.02, min_shared=15)
        assert m is not None and m.n > 100 and abs(m.baseline_m - 16.0) < 1e-9
        assert abs(np.rad2deg(m.offset_rad) - b_deg) < 3 * np.rad2deg(np.sqrt(m.var_rad2)) + 0.02
        assert np.sqrt(m.var_rad2) < np.deg2rad(0.2)


def test_a_map_made_with_a_heading_error_is_right_on_its_track_and_off_beside_it(pipeline):
    """What the error does: the map is turned about the way out, so a frame on that track is located nearly right
    (the map cannot show the error against itself), one 35 m to the side is off by about the turn times 35 m."""
    scene = Scene(pipeline, seed=2)
    b = np.deg2rad(1.5)
    lm, _ = _views_along_north(scene, pipeline, b, 0, 40)
    localiser = Localiser(pipeline, scene.camera, scene.R_body_cam, lm)
    R_told = R_ned_body_from_euler(0.0, 0.0, b)
    aside = np.array([60.0, 35.0])  # a return leg 35 m to the side of the way out
    fix = localiser.locate(scene.features(aside, 0.0), 11.0, R_told, ALT_M, PositionPrior(np.array([*aside, -ALT_M]), 0.5))
    assert isinstance(fix, Fix), fix
    off_aside = np.linalg.norm(fix.p_ned_m[:2] - aside)
    assert off_aside > 0.5 * b * 35.0  # decimetres: the map is turned about the way out
    on_track = np.array([60.0, 0.0])
    fix = localiser.locate(scene.features(on_track, 0.0), 11.0, R_told, ALT_M, PositionPrior(np.array([*on_track, -ALT_M]), 0.5))
    assert np.linalg.norm(fix.p_ned_m[:2] - on_track) < 0.3 * off_aside


def test_positioning_on_a_true_map_measures_the_heading_error_as_a_turn(pipeline):
    scene = Scene(pipeline, seed=1)
    lm = LandmarkMap()
    mapper = Mapper(pipeline, scene.camera, scene.R_body_cam, lm)
    for k in range(40):
        c = np.array([2.0 * k, 0.0])
        mapper.process(scene.features(c, 0.0), NavSample(0.25 * k, np.array([c[0], c[1], -ALT_M]), ALT_M, np.eye(3)))
    localiser = Localiser(pipeline, scene.camera, scene.R_body_cam, lm)
    b = np.deg2rad(1.2)
    c_now = np.array([60.0, 0.0])
    fix = localiser.locate(scene.features(c_now, 0.0), 11.0, R_ned_body_from_euler(0.0, 0.0, b), ALT_M,
                           PositionPrior(np.array([c_now[0], c_now[1], -ALT_M]), 0.3), heading_sigma_rad=np.deg2rad(2.0))
    assert fix.heading_turn_rad is not None
    assert abs(fix.heading_turn_rad + b) < 3.0 * np.sqrt(fix.heading_turn_var_rad2) + np.deg2rad(0.05)
    assert np.linalg.norm(fix.p_ned_m[:2] - c_now) < 0.05


def test_tracker_follows_a_wandering_error_and_refuses_a_jump():
    cfg = HeadingConfig(sigma_deg=2.0, tau_s=120.0, reset_after=3)
    tr = HeadingTracker(cfg)
    rng = np.random.default_rng(3)
    b_true = np.deg2rad(1.5)
    for k in range(200):
        t = 0.5 * k
        b_true += np.deg2rad(0.01) * rng.standard_normal()
        tr.observe(t, b_true + np.deg2rad(0.4) * rng.standard_normal(), np.deg2rad(0.4) ** 2)
    est = tr.at(100.0)
    assert est.p_off > 0.99 and np.isclose(est.offset_rad, tr.if_off(100.0).offset_rad, rtol=0.01)
    assert abs(est.offset_rad - b_true) < 3 * est.sigma_rad
    assert est.sigma_rad < np.deg2rad(0.35)  # down from 2 deg (steady state: (q R dt)^(1/4) = 0.27 deg)
    before, n_refused = tr.if_off(100.5).offset_rad, tr.n_refused
    assert not tr.observe(100.5, b_true + np.deg2rad(5.0), np.deg2rad(0.4) ** 2)  # 5 deg off: refused, kept
    assert tr.if_off(100.5).offset_rad == before and tr.n_refused == n_refused + 1
    # A positioning frame turned by x against the map, located with the heading less u: the error is u - x.
    assert tr.observe_turn(101.0, -0.001, np.deg2rad(0.1) ** 2, before) and tr.if_off(101.0).offset_rad > before
    # Refused reset_after times in a row: the error has jumped, and the estimate reopens to follow it.
    for k in range(3):
        tr.observe(102.0 + k, b_true + np.deg2rad(5.0), np.deg2rad(0.4) ** 2)
    assert tr.if_off(105.0).sigma_rad > 0.9 * np.deg2rad(cfg.sigma_deg)
    assert tr.observe(105.5, b_true + np.deg2rad(5.0), np.deg2rad(0.4) ** 2)
    # Without evidence, the uncertainty grows back towards the prior, and so do the odds that it is off at all.
    assert tr.if_off(2000.0).sigma_rad > 0.95 * np.deg2rad(cfg.sigma_deg)
    assert abs(tr.at(1e5).p_off - cfg.off_prior) < 1e-6


def test_a_heading_that_is_right_is_not_corrected_by_the_noise_of_its_measurements():
    """The same measurements' noise (0.4 deg each), around no error and around a 1 deg one. Around none, the
    evidence says "right" and what is taken out stays a small part of the filter's estimate, which wanders with
    the noise; around 1 deg, "off", and the estimate is the filter's."""
    cfg = HeadingConfig(sigma_deg=2.0, tau_s=300.0)
    noise = np.deg2rad(0.4) * np.random.default_rng(5).standard_normal(100)
    right, off = HeadingTracker(cfg), HeadingTracker(cfg)
    wander, taken_out = [], []
    for k, e in enumerate(noise):
        right.observe(2.0 * k, e, np.deg2rad(0.4) ** 2)
        off.observe(2.0 * k, np.deg2rad(1.0) + e, np.deg2rad(0.4) ** 2)
        wander.append(right.if_off(2.0 * k).offset_rad)
        taken_out.append(right.at(2.0 * k).offset_rad)
    assert right.at(200.0).p_off < 0.1 and off.at(200.0).p_off > 0.99
    assert np.std(taken_out[20:]) < 0.2 * np.std(wander[20:])
    est = off.at(200.0)
    assert abs(np.degrees(est.offset_rad) - 1.0) < 3 * np.degrees(est.sigma_rad) and np.degrees(est.sigma_rad) < 0.5
    # The mixture's sigma covers the filter's estimate it did not take out.
    e = right.at(200.0)
    assert abs(right.if_off(200.0).offset_rad - e.offset_rad) < 3 * e.sigma_rad + 1e-9 or e.p_off < 1e-3


def test_tracker_pairs_each_view_with_one_far_enough_back(pipeline):
    scene = Scene(pipeline, seed=4)
    b = np.deg2rad(-1.2)
    _, views = _views_along_north(scene, pipeline, b, 0, 30)
    tr = HeadingTracker(HeadingConfig())
    found = [tr.observe_view(v, shift_sigma_m=0.05) for v in views]
    got = [m for m in found if m is not None]
    assert found[0] is None and len(got) > 15  # the first has none before it; pairs need 8 m
    assert all(m.baseline_m >= HeadingConfig().min_baseline_m for m in got)
    est = tr.at(views[-1].t_s)
    assert abs(est.offset_rad - b) < max(3 * est.sigma_rad, np.deg2rad(0.05))


def test_a_burst_of_correlated_frames_tells_what_a_few_independent_ones_do():
    """40 positioning frames in 2 s, all with the same 0.4 deg fit error (they fit the same landmarks): the tracker
    takes them as a few measurements' worth (1/n weights: 1 + 1/2 + ... + 1/40, 4.3), not 40; and frames 2 s
    apart count in full again."""
    cfg = HeadingConfig(sigma_deg=2.0, tau_s=1e6, rotation_floor_deg=0.1)  # (no drift over these seconds)
    sigma_frame = np.hypot(0.3, cfg.rotation_floor_deg)
    tr = HeadingTracker(cfg)
    for k in range(40):
        tr.observe_turn(0.05 * k, -np.deg2rad(0.4), np.deg2rad(0.3) ** 2, 0.0)
    est = tr.if_off(2.0)
    harmonic = sum(1.0 / n for n in range(1, 41))
    assert np.rad2deg(est.sigma_rad) > 0.95 * sigma_frame / np.sqrt(harmonic)  # 40 independent: sigma / 6.3
    assert np.rad2deg(est.sigma_rad) < 1.05 * sigma_frame / np.sqrt(harmonic)
    spaced = HeadingTracker(cfg)
    for k in range(5):
        spaced.observe_turn(2.5 * k, -np.deg2rad(0.4), np.deg2rad(0.3) ** 2, 0.0)
    assert np.rad2deg(spaced.if_off(10.0).sigma_rad) < 1.05 * sigma_frame / np.sqrt(5)


def test_a_restored_heading_error_is_aged_toward_the_prior_by_the_time_since_it_was_saved():
    """Read back from a checkpoint seconds after a crash, the saved estimate is nearly as it was; read back after
    many correlation times (a map reused another day), it is the prior again."""
    cfg = HeadingConfig(solve=True)
    fresh = HeadingTracker(cfg)
    fresh.restore(np.deg2rad(1.5), np.deg2rad(0.2), elapsed_s=2.0)
    e = fresh.at(100.0)
    assert abs(np.degrees(e.offset_rad) - 1.5) < 0.02 and np.degrees(e.sigma_rad) < 0.35  # 0.2 deg, and 2 s of drift
    stale = HeadingTracker(cfg)
    stale.restore(np.deg2rad(1.5), np.deg2rad(0.2), elapsed_s=20 * cfg.tau_s)
    e = stale.at(100.0)
    # the prior: the mixture of "off" (sigma_deg) and "right" (none)
    prior_deg = np.sqrt(cfg.off_prior) * cfg.sigma_deg
    assert abs(np.degrees(e.offset_rad)) < 1e-6 and np.isclose(np.degrees(e.sigma_rad), prior_deg)
    # Read back the moment it was saved (or with the clock stepped back): taken as it was, and evidence still moves it.
    at_once = HeadingTracker(cfg)
    at_once.restore(np.deg2rad(1.5), np.deg2rad(0.2), elapsed_s=0.0)
    assert np.isclose(np.degrees(at_once.at(0.0).offset_rad), 1.5, atol=1e-3)
    assert at_once.observe(1.0, np.deg2rad(1.4), np.deg2rad(0.4) ** 2) and 0.5 < at_once.at(1.0).p_off < 1.0
    broken = HeadingTracker(cfg)
    broken.restore(float("nan"), 0.01, 1.0)
    assert broken.at(0.0).offset_rad == 0.0 and np.isclose(np.degrees(broken.at(0.0).sigma_rad), prior_deg)


def _map_north_while_solving(scene, pipeline, b_true_rad, corrections_rad, turn):
    """A flight north at 40 m mapped as the estimator maps it while its heading solver converges: frame ``k``
    geotagged with the correction ``corrections_rad[k]`` taken out of the telemetry's heading, and (``turn``) the map
    turned to each new correction before the frame that uses it."""
    lm = LandmarkMap()
    mapper = Mapper(pipeline, scene.camera, scene.R_body_cam, lm)
    turned_to = corrections_rad[0]
    for k, b in enumerate(corrections_rad):
        if turn and b != turned_to:
            lm.turn(b, turned_to, 0.25 * k - 30.0)
            turned_to = b
        c = np.array([2.0 * k, 0.0])
        R_used = R_ned_body_from_euler(0.0, 0.0, b_true_rad - b)
        heading = HeadingEstimate(0.25 * k, b, 0.0) if turn else None
        mapper.process(scene.features(c, 0.0), NavSample(0.25 * k, np.array([c[0], c[1], -ALT_M]), ALT_M, R_used, heading))
    return lm


def test_a_map_turned_as_the_solver_learns_is_right_beside_the_way_out(pipeline):
    """The solver starts 1.5 deg off and converges over the first frames; the landmarks those frames geotagged are
    turned with it. A frame 35 m beside the first part of the way out is then located as on a map made with the
    true heading; without the turns it is off by decimetres."""
    scene = Scene(pipeline, seed=3)
    b_true = np.deg2rad(1.0)
    corrections = b_true + np.deg2rad(1.5) * 0.85 ** np.arange(40)
    aside = np.array([20.0, 35.0])
    off_m = {}
    for turn in (False, True):
        lm = _map_north_while_solving(scene, pipeline, b_true, corrections, turn)
        localiser = Localiser(pipeline, scene.camera, scene.R_body_cam, lm)
        fix = localiser.locate(scene.features(aside, 0.0), 11.0, np.eye(3), ALT_M, PositionPrior(np.array([*aside, -ALT_M]), 0.5))
        assert isinstance(fix, Fix), fix
        off_m[turn] = float(np.linalg.norm(fix.p_ned_m[:2] - aside))
    assert off_m[True] < 0.03 < 0.2 < off_m[False], off_m  # 0.011 against 0.39 m
