"""Mapping and positioning: known answers on synthetic views, robustness to bad frames, and a short flight."""

import dataclasses

import cv2
import numpy as np
import pytest

from auxgps.config import PipelineConfig, parse_as
from auxgps.core.camera import CameraPose, PinholeCamera
from auxgps.core.features import Features, FeatureDetector
from auxgps.core.geometry import R_BODY_CAM_DOWN, R_ned_body_from_euler, cross_matrix
from auxgps.core.landmarks import LandmarkMap
from auxgps.core.localise import Fix, Localiser, NoFix, PositionPrior, _Correspondences, _prefix_spread_order, _ransac_seeds, _Reading, _spread_by_rivals
from auxgps.core.mapping import Mapper
from auxgps.core.nav import NavSample
from auxgps.errors import FrameError
from auxgps.evaluation.scenario import run_once
from auxgps.sim.flight import SimConfig
from auxgps.sim.render import Renderer
from auxgps.sim.texture import gravel_texture
from tests.conftest import make_world

atol_fix_m = 0.05  # 5 cm: noise-free views, pixel quantisation only
atol_equal_m = 1e-9  # 1 nm: two routes to the same numbers, rounding only
rtol_equal = 1e-9


def synthetic_map(camera, points_ned, n_seen=20, seed=0):
    """A map holding ``points_ned`` with random distinct descriptors, as if each had been seen ``n_seen`` times."""
    rng = np.random.default_rng(seed)
    lm = LandmarkMap()
    desc = rng.integers(0, 256, (len(points_ned), 32), dtype=np.uint8)
    ids = lm.add(desc, points_ned, np.repeat(np.eye(3)[None] * 1e4, len(points_ned), axis=0), np.ones(len(points_ned)))
    lm.n_seen[ids] = n_seen
    return lm, desc


def view(camera, pose, points_ned, desc):
    uv, _ = pose.project(camera, points_ned)
    return Features(uv, desc.copy(), np.zeros(len(uv), int))


@pytest.fixture
def scene(camera):
    rng = np.random.default_rng(7)
    pts = np.column_stack([rng.uniform(-6, 6, 40), rng.uniform(-6, 6, 40), -rng.uniform(0, 3, 40)])
    lm, desc = synthetic_map(camera, pts)
    return pts, lm, desc


def locate(pipeline, camera, lm, feats, R_ned_body, alt_m, prior):
    return Localiser(pipeline, camera, R_BODY_CAM_DOWN, lm).locate(feats, 1.0, R_ned_body, alt_m, prior)


def test_tilted_view_is_located_to_its_true_position(camera, pipeline, scene):
    pts, lm, desc = scene
    R = R_ned_body_from_euler(0.08, -0.06, 0.7)  # 4.6 and 3.4 degrees of tilt
    pose = CameraPose(np.array([1.0, -0.5, -15.0]), R @ R_BODY_CAM_DOWN)
    res = locate(pipeline, camera, lm, view(camera, pose, pts, desc), R, 15.0, PositionPrior(np.array([1.5, -1.0, -15.0]), 1.0))
    assert isinstance(res, Fix)
    assert np.linalg.norm(res.p_ned_m[:2] - [1.0, -0.5]) < atol_fix_m
    assert res.n_inliers == len(pts)


def test_a_fix_says_when_its_landmarks_were_mapped(camera, pipeline, scene):
    """A fix carries the median time its inliers were first geotagged (the estimator looks up how well the heading
    was known then); landmarks of a loaded map, with no such time, do not count."""
    pts, lm, desc = scene
    lm.t_first_s[: len(pts)] = np.arange(len(pts), dtype=float)
    lm.t_first_s[:10] = -np.inf
    pose = CameraPose(np.array([1.0, -0.5, -15.0]), R_BODY_CAM_DOWN)
    res = locate(pipeline, camera, lm, view(camera, pose, pts, desc), np.eye(3), 15.0, PositionPrior(pose.p_cam_in_ned_m, 0.5))
    assert isinstance(res, Fix) and res.n_inliers == len(pts)
    assert res.t_mapped_s == pytest.approx(np.median(np.arange(10.0, len(pts))))
    lm.t_first_s[: len(pts)] = -np.inf
    res = locate(pipeline, camera, lm, view(camera, pose, pts, desc), np.eye(3), 15.0, PositionPrior(pose.p_cam_in_ned_m, 0.5))
    assert isinstance(res, Fix) and np.isnan(res.t_mapped_s)


def test_a_wrong_match_does_not_move_the_fix(camera, pipeline, scene):
    pts, lm, desc = scene
    R = R_ned_body_from_euler(0.0, 0.0, 0.2)
    pose = CameraPose(np.array([0.0, 0.0, -15.0]), R @ R_BODY_CAM_DOWN)
    feats = view(camera, pose, pts, desc)
    clean = locate(pipeline, camera, lm, feats, R, 15.0, None)
    wrong = feats.descriptors.copy()
    wrong[[0, 1]] = wrong[[1, 0]]  # two features swap their landmarks
    bad = locate(pipeline, camera, lm, Features(feats.uv_px, wrong, feats.octave), R, 15.0, None)
    assert isinstance(clean, Fix) and isinstance(bad, Fix)
    assert np.linalg.norm(bad.p_ned_m - clean.p_ned_m) < 0.01
    assert bad.n_inliers == clean.n_inliers - 2


def test_identical_cubes_one_in_view_give_no_fix(camera, pipeline):
    """Two identical 'cubes' (the same 8 corners and descriptors) 30 m apart; only one is in view."""
    cube = np.array([[n, e, d] for n in (-0.5, 0.5) for e in (-0.5, 0.5) for d in (0.0, -1.0)])
    a, b = cube + [0.0, 0.0, 0.0], cube + [0.0, 30.0, 0.0]
    lm, desc = synthetic_map(camera, np.vstack([a, b]))
    lm.descriptors[8:16] = lm.descriptors[:8]  # the second cube looks exactly like the first
    R = np.eye(3)
    pose = CameraPose(np.array([0.0, -1.5, -5.0]), R_BODY_CAM_DOWN)  # only cube a is in the 10 m wide view
    feats = view(camera, pose, a, desc[:8])
    assert camera.in_image(feats.uv_px).all()
    assert isinstance(locate(pipeline, camera, lm, feats, R, 5.0, None), NoFix)
    # With the filter's prior near the truth, the same frame is located.
    res = locate(pipeline, camera, lm, feats, R, 5.0, PositionPrior(np.array([0.2, -1.7, -5.0]), 0.3))
    assert isinstance(res, Fix) and np.linalg.norm(res.p_ned_m[:2] - [0.0, -1.5]) < atol_fix_m


def test_a_confident_but_biased_prior_does_not_outvote_the_image(camera, pipeline):
    """Two 1 m cubes whose bottom corners look like the top corners above them (as from straight above).

    Seen off-nadir, the bottom features taken for the top landmarks make a second reading, 0.3 m from the truth
    (with the attitude correction it needs), with half the inliers. A filter that a few such fixes pulled there believes itself to 3 cm; the image must
    still win: the fix is the true position, not the prior's.
    """
    top = np.array([[n, e, -1.0] for n in (-0.5, 0.5) for e in (-0.5, 0.5)])
    cubes = [top + [-1.5, 2.0, 0.0], top + [1.5, 2.0, 0.0]]
    tops = np.vstack(cubes)
    bottoms = tops + [0.0, 0.0, 1.0]
    lm, desc = synthetic_map(camera, np.vstack([tops, bottoms]))
    lm.descriptors[8:16] = lm.descriptors[:8]
    p_true = np.array([0.0, -6.0, -15.0])
    pose = CameraPose(p_true, R_BODY_CAM_DOWN)
    feats = view(camera, pose, np.vstack([tops, bottoms]), lm.descriptors[:16])
    wrong_shift = np.array([0.0, 0.38])  # beyond the bottoms-as-tops reading, as a filter pulled by such fixes would be
    prior = PositionPrior(p_true + np.array([*wrong_shift, 0.0]), 0.03)
    res = locate(pipeline, camera, lm, feats, np.eye(3), 15.0, prior)
    assert isinstance(res, Fix) and np.linalg.norm(res.p_ned_m[:2] - p_true[:2]) < atol_fix_m
    assert res.n_inliers == 16


def test_a_small_cube_read_off_by_its_height_loses_on_its_fit(camera, pipeline):
    """A 1 m cube 4 m off nadir from 10 m: two top corners and the bottom corners below them, each found twice
    (two pyramid levels), and bottom landmarks that look like the top ones. Taking the top corners for the bottom
    ones gives a second reading 0.32 m away with as many inliers, 2 to 3 px off where the true one is within a
    pixel. The filter's prior has drifted 0.2 m towards it: the better fit must still decide, not the prior. A
    corner found twice is one measurement of its landmark: four inliers, not eight."""
    top = np.array([[n, e, -1.0] for n in (-0.5, 0.5) for e in (-0.5, 0.5)])
    corners = np.vstack([top, top + [0.0, 0.0, 1.0]])
    lm, _ = synthetic_map(camera, corners)
    lm.descriptors[4:8] = lm.descriptors[:4]
    p_true = np.array([-1.0, -4.0, -10.0])
    seen = [0, 1, 4, 5]
    uv, _ = CameraPose(p_true, R_BODY_CAM_DOWN).project(camera, corners[seen])
    uv += np.random.default_rng(1).normal(0.0, 0.3, uv.shape)
    feats = Features(np.vstack([uv, uv + 0.2]), np.vstack([lm.descriptors[seen]] * 2), np.repeat([0, 1], len(seen)))
    prior = PositionPrior(p_true + [0.0, 0.2, 0.0], 0.12)
    res = locate(pipeline, camera, lm, feats, np.eye(3), 10.0, prior)
    assert isinstance(res, Fix), res.reason
    assert np.linalg.norm(res.p_ned_m[:2] - p_true[:2]) < atol_fix_m
    assert res.n_inliers == 4


def test_a_corner_mapped_twice_and_found_twice_is_one_inlier(camera, pipeline):
    """Three corners of a cube, and a fourth mapped twice over (two landmarks on one spot, from the two features a
    corner gives on two pyramid levels) and found twice at one spot of the frame: three physical points, two
    landmarks and two features for one of them. That is three inliers, not four: no fix from them (one such fix
    on SITL, 4 inliers with one corner twice and a phantom, claimed 0.2 m and was 0.55 m off). A fourth distinct
    corner makes it a fix of four."""
    corners = np.array([[n, e, -1.0] for n in (-0.5, 0.5) for e in (-0.5, 0.5)])
    twice = np.vstack([corners[:3], corners[2] + [0.004, -0.003, 0.0]])  # mapped again, a few mm apart
    lm, _ = synthetic_map(camera, twice)
    lm.descriptors[3] = lm.descriptors[2]
    p_true = np.array([1.0, -2.0, -12.0])
    uv, _ = CameraPose(p_true, R_BODY_CAM_DOWN).project(camera, twice)
    uv[3] = uv[2] + [0.4, 0.3]  # the second pyramid level's position of the same corner
    prior = PositionPrior(p_true, 0.12)
    res = locate(pipeline, camera, lm, Features(uv, lm.descriptors.copy(), np.array([0, 0, 0, 1])), np.eye(3), 12.0, prior)
    assert isinstance(res, NoFix) and "4 inliers" in res.reason, res.reason

    four, _ = synthetic_map(camera, np.vstack([twice, corners[3]]))
    four.descriptors[3] = four.descriptors[2]
    uv4, _ = CameraPose(p_true, R_BODY_CAM_DOWN).project(camera, np.vstack([twice, corners[3]]))
    uv4[3] = uv4[2] + [0.4, 0.3]
    res = locate(pipeline, camera, four, Features(uv4, four.descriptors.copy(), np.array([0, 0, 0, 1, 0])), np.eye(3), 12.0, prior)
    assert isinstance(res, Fix) and res.n_inliers == 4, res
    assert np.linalg.norm(res.p_ned_m[:2] - p_true[:2]) < atol_fix_m


def test_a_corner_found_on_two_pyramid_levels_is_mapped_once(camera, pipeline):
    """Two features 1 px apart (one corner, two pyramid levels) become one landmark, and a frame after that finds
    the corner twice again feeds that landmark and adds none: a corner is not mapped twice over (SITL's maps held up
    to eight landmarks within 0.1 m of one corner, and a fix that counted one corner twice was 0.59 m off)."""
    rng = np.random.default_rng(5)
    corners = np.array([[n, e, 0.0] for n in (-1.0, 1.0) for e in (-1.0, 1.0)])
    desc = rng.integers(0, 256, (4, 32), dtype=np.uint8)
    nav = NavSample(0.0, np.array([0.0, 0.0, -12.0]), 12.0, np.eye(3))
    uv, _ = nav.camera_pose(R_BODY_CAM_DOWN).project(camera, corners)
    twice_uv = np.vstack([uv, uv[0] + [0.8, -0.6]])
    twice = Features(twice_uv, np.vstack([desc, desc[0]]), np.array([0, 0, 0, 0, 1]))
    lm = LandmarkMap()
    mapper = Mapper(pipeline, camera, R_BODY_CAM_DOWN, lm)
    first = mapper.process(twice, nav)
    assert first.n_added == 4 and len(lm) == 4
    assert first.landmark_ids[4] == -1
    again = mapper.process(twice, dataclasses.replace(nav, t_s=0.1))
    assert again.n_added == 0 and again.n_matched == 4 and len(lm) == 4


def three_corners_here_four_there(camera, shift_east_m):
    """A frame from 15 m with three corners of a cube where they are, and four corners of another object seen as
    from ``shift_east_m`` east of the camera's true position: the map, the true position and the features."""
    cube = np.array([[n, e, d] for n in (-0.5, 0.5) for e in (-0.5, 0.5) for d in (0.0, -1.0)])
    other = np.array([[n, e, 0.0] for n in (-0.5, 0.5) for e in (2.5, 3.5)])
    lm, _ = synthetic_map(camera, np.vstack([cube, other]))
    p_true = np.array([0.0, -1.0, -15.0])
    uv_cube, _ = CameraPose(p_true, R_BODY_CAM_DOWN).project(camera, cube[:3])
    uv_other, _ = CameraPose(p_true + [0.0, shift_east_m, 0.0], R_BODY_CAM_DOWN).project(camera, other)
    feats = Features(np.vstack([uv_cube, uv_other]), lm.descriptors[[0, 1, 2, 8, 9, 10, 11]].copy(), np.zeros(7, int))
    return lm, p_true, feats


def test_no_fix_when_the_most_probable_reading_has_too_few_inliers(camera, pipeline):
    """Three corners of one object seen where the filter expects them, and four of another seen as from 0.5 m
    away (a reading that takes some features for the wrong landmarks): the better explanation has too few
    inliers to be a fix, and the one with enough must not become a fix in its place."""
    lm, p_true, feats = three_corners_here_four_there(camera, 0.5)
    res = locate(pipeline, camera, lm, feats, np.eye(3), 15.0, PositionPrior(p_true, 0.12))
    assert isinstance(res, NoFix) and "fewer than" in res.reason


def test_a_fix_read_where_a_weaker_reading_disagrees_reports_the_doubt(camera, pipeline):
    """As above, the four corners seen as from 0.3 m east, and the filter's prior drifted half way there: the
    wrong reading (four inliers) now wins over the right one (three), which has too few inliers to be a fix and
    is no ground for calling the frame ambiguous. The fix must carry the doubt: its reported sigma covers its
    0.3 m error (alone, the wrong reading reports 0.06 m, five sigma off)."""
    lm, p_true, feats = three_corners_here_four_there(camera, 0.3)
    res = locate(pipeline, camera, lm, feats, np.eye(3), 15.0, PositionPrior(p_true + [0.0, 0.15, 0.0], 0.12))
    assert isinstance(res, Fix) and res.n_inliers == 4
    err_east_m = res.p_ned_m[1] - p_true[1]
    assert err_east_m == pytest.approx(0.3, abs=atol_fix_m)  # the wrong reading won
    assert abs(err_east_m) / np.sqrt(res.cov_ned_m2[1, 1]) < 2.0


def test_rivals_spread_the_covariance_by_their_probability():
    """Known answers: a rival as probable as the best, 0.3 m north of it, adds half its squared distance to the
    north variance; one 10 units less probable, 1 m east, adds exp(-10) / (2 + exp(-10)) of a square metre."""
    def reading(n, e):
        return _Reading(np.array([n, e, -15.0]), np.eye(3) * 0.01, np.ones(4, bool), 4.0, 1.0, 0.0)

    readings = [reading(0.0, 0.0), reading(0.3, 0.0), reading(0.0, 1.0)]
    out = _spread_by_rivals(readings[0], readings, np.array([2.0, 2.0, -8.0]))
    w_far = np.exp(-10.0) / (2.0 + np.exp(-10.0))
    w_near = 1.0 / (2.0 + np.exp(-10.0))
    expected = np.eye(3) * 0.01
    expected[0, 0] += w_near * 0.09
    expected[1, 1] += w_far * 1.0
    np.testing.assert_allclose(out.cov, expected, rtol=rtol_equal, atol=1e-15)
    np.testing.assert_array_equal(out.p, readings[0].p)  # the best reading's position is kept
    alone = _spread_by_rivals(readings[0], readings[:1], np.array([2.0]))
    np.testing.assert_array_equal(alone.cov, readings[0].cov)


def refine_by_jacobians(loc, p0, corr, inl, alt_m):
    """The localiser's refinement written out with a (K, 3, 6) Jacobian per correspondence, ``J_k = [-P_k,
    t_k [d_k]x]``: the reference that its closed-form normal equations are checked against."""
    noise, f, d, L = loc.cfg.noise, loc.camera.focal_px, corr.d, corr.L
    P = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
    lm_var = np.einsum("kij,kjl,kli->k", P, loc.map.covariance(corr.lm_id), P) / 2.0  # across the ray, per axis
    height_mse = loc.map.covariance(corr.lm_id)[:, 2, 2] + loc.map.triangulation_bias_m(corr.lm_id)[:, 2] ** 2
    dx = cross_matrix(d)
    prior_info = np.diag([0.0, 0.0, 1.0 / noise.altitude_m**2] + [1.0 / np.deg2rad(noise.attitude_deg) ** 2] * 2
                         + [1.0 / np.deg2rad(noise.heading_deg) ** 2])
    p, dtheta = np.asarray(p0, float), np.zeros(3)
    for _ in range(3):
        t = np.einsum("ki,ki->k", d, L - p)
        w = 1.0 / ((t * noise.pixel_px / f) ** 2 + lm_var)
        J = np.concatenate([-P, t[:, None, None] * dx], axis=2)
        c = np.einsum("kij,kj->ki", P, L)
        A = np.einsum("k,kji,kjl->il", w[inl], J[inl], J[inl]) + prior_info
        b = -np.einsum("k,kji,kj->i", w[inl], J[inl], c[inl])
        b[2] += -alt_m * prior_info[2, 2]
        z = np.linalg.solve(A, b)
        p, dtheta = z[:3], z[3:]
        resid = c + np.einsum("kij,j->ki", J, z)
        err_px = np.linalg.norm(resid, axis=1) / np.maximum(t, 1e-6) * f
        chi2 = float(np.sum(w[inl] * np.sum(resid[inl] ** 2, axis=1)))
        cov = np.linalg.inv(A)[:3, :3] * max(1.0, chi2 / max(2 * int(inl.sum()) - 3, 1))
        # every landmark lowered by 1 m together: how far that moves the solution, times their mean squared height error
        g = np.linalg.solve(A, -np.einsum("k,kji,kj->i", w[inl], J[inl], P[inl][:, :, 2]))[:2]
        cov[:2, :2] += np.outer(g, g) * np.mean(height_mse[inl])
        inl = inl & (err_px <= loc.cfg.positioning.inlier_px)
    return p, cov, inl, float(dtheta @ prior_info[3:, 3:] @ dtheta)


def test_the_fix_covariance_carries_a_lift_its_landmarks_share(camera, pipeline, monkeypatch):
    """The refinement weighs its landmarks' errors as independent, but their heights share much of theirs. Its
    covariance also carries their mean squared height error (0.3 m here) as one lift they all share, through how
    far such a lift moves the solution (found here by lifting them 1 cm), with the attitude known to 1 degree:
    a grid around nadir does not move, a grid at one side of the image, 25 to 35 m off nadir from 40 m, moves
    by most of the lift."""
    p_true = np.array([0.0, 0.0, -40.0])
    grid = np.array([[n, e, 0.0] for n in np.linspace(-15.0, 15.0, 7) for e in np.linspace(-15.0, 15.0, 7)])

    def refine(pts, lift_m=0.0, height_mse=True):
        info = np.repeat(np.diag([1e4, 1e4, 1.0 / 0.3**2])[None], len(pts), axis=0)
        lm = LandmarkMap()
        lm.add(np.zeros((len(pts), 32), np.uint8), pts + [0.0, 0.0, lift_m], info, np.ones(len(pts)))
        if not height_mse:
            monkeypatch.setattr(lm, "height_mse_m2", lambda ids: np.zeros(len(ids)))
        loc = Localiser(pipeline, camera, R_BODY_CAM_DOWN, lm)
        uv, _ = CameraPose(p_true, R_BODY_CAM_DOWN).project(camera, pts)
        d = camera.pixels_to_rays_cam(uv) @ R_BODY_CAM_DOWN.T
        L = lm.p_ned_m[: len(pts)].astype(float)
        corr = _Correspondences(np.arange(len(pts)), np.arange(len(pts)), L, d, L[:, :2], np.full(len(pts), 0.1))
        fit = loc._refine(p_true, corr, np.ones(len(pts), bool), 40.0, prior_info=loc._prior_info(np.deg2rad(1.0), None))
        assert fit.inl.all()
        return fit

    for pts, least, most in ((grid, 0.0, 0.01), (grid * [0.6, 0.3, 0.0] + [0.0, 30.0, 0.0], 0.6, 1.0)):
        fit = refine(pts)
        g = (refine(pts, lift_m=0.01).p[:2] - fit.p[:2]) / 0.01
        assert least <= np.linalg.norm(g) <= most
        cov_apart = refine(pts, height_mse=False).cov
        np.testing.assert_allclose(fit.cov[:2, :2] - cov_apart[:2, :2], np.outer(g, g) * 0.3**2, rtol=0.02, atol=1e-6)


def test_a_seed_whose_members_cannot_come_near_the_best_is_not_refined(camera, pipeline, monkeypatch):
    """A hundred points, 35 of them mapped a second time 1 m east (the same descriptor) and found twice on one
    spot (two pyramid levels), and ten landmarks in view that the frame does not show. The copies' seeds are a
    hypothesis 1 m off with 70 supporting features but 35 members one to one, where the right reading scores
    about 70: refined, it would weigh e^-20 or less beside the best, so it is not refined, and the fix is the
    one that refining it gives."""
    import auxgps.core.localise as localise

    rng = np.random.default_rng(11)
    pts = np.column_stack([rng.uniform(-9, 9, 110), rng.uniform(-9, 9, 110), np.zeros(110)])
    copies = pts[:35] + [0.0, 1.0, 0.0]
    lm, desc = synthetic_map(camera, np.vstack([pts, copies]))
    lm.descriptors[110:145] = lm.descriptors[:35]
    p_true = np.array([0.5, -0.3, -20.0])
    seen = view(camera, CameraPose(p_true, R_BODY_CAM_DOWN), pts[:100], desc[:100])  # the last ten unseen
    feats = Features(np.vstack([seen.uv_px, seen.uv_px[:35] + [0.4, 0.3]]), np.vstack([desc[:100], desc[:35]]),
                     np.r_[np.zeros(100, int), np.ones(35, int)])
    prior = PositionPrior(p_true + [0.2, 0.1, 0.0], 0.5)

    def refined(negligible_ll):
        monkeypatch.setattr(localise, "_NEGLIGIBLE_LL", negligible_ll)
        seeds = []
        loc = Localiser(pipeline, camera, R_BODY_CAM_DOWN, lm)
        reading = loc._reading
        monkeypatch.setattr(loc, "_reading", lambda *a: seeds.append(a[2]) or reading(*a))
        return loc.locate(feats, 1.0, np.eye(3), 20.0, prior), len(seeds)

    fix, n_refined = refined(20.0)
    fix_all, n_refined_all = refined(np.inf)  # no seed skipped: every distinct one refined
    assert isinstance(fix, Fix) and isinstance(fix_all, Fix)
    assert (n_refined, n_refined_all) == (1, 2)
    assert np.linalg.norm(fix.p_ned_m[:2] - p_true[:2]) < atol_fix_m
    np.testing.assert_allclose(fix.p_ned_m, fix_all.p_ned_m, rtol=0, atol=atol_equal_m)
    np.testing.assert_allclose(fix.cov_ned_m2, fix_all.cov_ned_m2, rtol=rtol_equal, atol=1e-15)


def test_refinement_in_closed_form_equals_the_jacobian_form(camera, pipeline, scene):
    """Noisy pixels, a telemetry attitude 0.3 degrees off and three features 10 px off (dropped as outliers):
    the localiser's refinement and the per-correspondence Jacobian form agree to rounding."""
    pts, lm, _ = scene
    rng = np.random.default_rng(3)
    R_true = R_ned_body_from_euler(0.08, -0.06, 0.7)
    R_tel = R_true @ R_ned_body_from_euler(*np.deg2rad([0.3, -0.2, 0.3]))
    uv, _ = CameraPose(np.array([1.0, -0.5, -15.0]), R_true @ R_BODY_CAM_DOWN).project(camera, pts)
    uv += rng.normal(0.0, 0.5, uv.shape)
    uv[:3] += [[8.0, -6.0], [-10.0, 0.0], [0.0, 10.0]]
    lm_id = np.arange(len(pts))
    d = camera.pixels_to_rays_cam(uv) @ (R_tel @ R_BODY_CAM_DOWN).T
    L = pts[lm_id]
    hyp = L[:, :2] - ((L[:, 2] + 15.0) / d[:, 2])[:, None] * d[:, :2]
    corr = _Correspondences(np.arange(len(pts)), lm_id, L, d, hyp, np.full(len(pts), 0.1))
    loc = Localiser(pipeline, camera, R_BODY_CAM_DOWN, lm)
    inl = np.ones(len(pts), bool)
    p0 = np.array([*np.median(hyp, axis=0), -15.0])
    fit = loc._refine(p0, corr, inl, 15.0)
    p, cov, inl_out, attitude_m2 = fit.p, fit.cov, fit.inl, fit.attitude_m2
    p_ref, cov_ref, inl_ref, attitude_m2_ref = refine_by_jacobians(loc, p0, corr, inl, 15.0)
    assert not inl_out[:3].any() and inl_out[3:].all()
    np.testing.assert_array_equal(inl_out, inl_ref)
    np.testing.assert_allclose(p, p_ref, rtol=0.0, atol=atol_equal_m)
    np.testing.assert_allclose(cov, cov_ref, rtol=rtol_equal, atol=0.0)
    assert attitude_m2 == pytest.approx(attitude_m2_ref, rel=rtol_equal)


@pytest.mark.parametrize("image", [np.zeros((720, 1280, 3), np.uint8), np.full((720, 1280), 128, np.uint8)])
def test_featureless_frame_gives_no_fix(camera, pipeline, scene, image):
    _, lm, _ = scene
    feats = FeatureDetector(pipeline.detector).detect(image)
    assert len(feats) == 0
    res = locate(pipeline, camera, lm, feats, np.eye(3), 15.0, None)
    assert isinstance(res, NoFix) and "features" in res.reason


def test_nan_attitude_gives_no_fix(camera, pipeline, scene):
    pts, lm, desc = scene
    pose = CameraPose(np.array([0.0, 0.0, -15.0]), R_BODY_CAM_DOWN)
    R = np.full((3, 3), np.nan)
    assert isinstance(locate(pipeline, camera, lm, view(camera, pose, pts, desc), R, 15.0, None), NoFix)


@pytest.mark.parametrize("bad", [np.zeros((10, 10, 4), np.uint8), np.zeros((10, 10), np.float32), "frame"])
def test_malformed_frame_is_a_named_error(pipeline, bad):
    with pytest.raises(FrameError):
        FeatureDetector(pipeline.detector).detect(bad)


def gravel_image(contrast: float, seed: int = 3) -> np.ndarray:
    """A 1280x720 grey view of the benchmark's gravel, its contrast scaled by ``contrast``: corners everywhere."""
    grey = cv2.cvtColor(gravel_texture(1280, seed)[:720], cv2.COLOR_BGR2GRAY).astype(float)
    return np.clip(128.0 + contrast * (grey - grey.mean()), 0, 255).astype(np.uint8)


def sorted_features(feats):
    order = np.lexsort(feats.uv_px.T)
    return feats.uv_px[order], feats.descriptors[order]


def test_a_frame_rich_in_corners_gets_the_same_features_from_the_first_higher_threshold(pipeline):
    cfg = pipeline.detector
    assert cfg.fast_threshold_first > cfg.fast_threshold
    image = gravel_image(contrast=1.0)
    two_pass = FeatureDetector(cfg)
    assert len(two_pass.ladder[0].detect(image)) >= cfg.n_features  # the first threshold fills the budget here
    one_pass = FeatureDetector(parse_as(type(cfg), dict(fast_threshold_first=cfg.fast_threshold), "test"))
    R = R_ned_body_from_euler(0.0, 0.0, 0.4) @ R_BODY_CAM_DOWN
    uv_two, desc_two = sorted_features(two_pass.detect(image, R))
    uv_one, desc_one = sorted_features(one_pass.detect(image, R))
    np.testing.assert_array_equal(uv_two, uv_one)
    np.testing.assert_array_equal(desc_two, desc_one)


def test_a_frame_poor_in_corners_is_detected_again_at_the_lower_threshold(pipeline):
    cfg = pipeline.detector
    image = gravel_image(contrast=0.2)  # corners the floor sees, and the first threshold not
    two_pass = FeatureDetector(cfg)
    assert len(two_pass.ladder[0].detect(image)) < 0.1 * cfg.n_features
    one_pass = FeatureDetector(parse_as(type(cfg), dict(fast_threshold_first=cfg.fast_threshold), "test"))
    uv_two, desc_two = sorted_features(two_pass.detect(image))
    assert len(uv_two) >= 0.9 * cfg.n_features
    uv_one, desc_one = sorted_features(one_pass.detect(image))
    np.testing.assert_array_equal(uv_two, uv_one)
    np.testing.assert_array_equal(desc_two, desc_one)


class _CountingOrb:
    """An ORB whose detect calls are counted (cv2's own objects take no attributes)."""

    def __init__(self, orb):
        self.orb, self.calls = orb, 0

    def detect(self, image, mask):
        self.calls += 1
        return self.orb.detect(image, mask)

    def __getattr__(self, name):
        return getattr(self.orb, name)


def test_a_frame_filled_at_a_middle_threshold_keeps_its_features_and_the_next_frame_starts_there(pipeline):
    """Ground where the first threshold never fills the budget and a middle one does (Seneca's fields): those
    features are the floor's own, and later frames start at the middle threshold, trying the first again only
    after a run of frames filled there; frames poorer still move the start down."""
    cfg = pipeline.detector
    assert cfg.fast_threshold_rungs >= 3
    image = gravel_image(contrast=0.44)  # the middle threshold finds twice each pyramid level's share here
    detector = FeatureDetector(cfg)
    assert len(detector.ladder[0].detect(image)) < cfg.n_features <= len(detector.ladder[1].detect(image))
    floor = FeatureDetector(parse_as(type(cfg), dict(fast_threshold_first=cfg.fast_threshold), "test"))
    uv_floor, desc_floor = sorted_features(floor.detect(image))
    uv, desc = sorted_features(detector.detect(image))
    np.testing.assert_array_equal(uv, uv_floor)
    np.testing.assert_array_equal(desc, desc_floor)
    detector.ladder = [_CountingOrb(o) for o in detector.ladder]
    for _ in range(FeatureDetector._CLIMB_AFTER):
        detector.detect(image)
    assert [o.calls for o in detector.ladder] == [0, FeatureDetector._CLIMB_AFTER, 0]
    detector.detect(image)  # a run filled at the middle: the first threshold is tried again, once
    assert [o.calls for o in detector.ladder] == [1, FeatureDetector._CLIMB_AFTER + 1, 0]
    detector.detect(gravel_image(contrast=0.2))  # poorer ground: down to the floor
    detector.detect(gravel_image(contrast=0.2))
    assert [o.calls for o in detector.ladder] == [1, FeatureDetector._CLIMB_AFTER + 2, 2]


def test_a_first_threshold_below_the_floor_is_a_named_error():
    from auxgps.config import DetectorConfig
    from auxgps.errors import ConfigError

    with pytest.raises(ConfigError, match="fast_threshold_first"):
        parse_as(DetectorConfig, dict(fast_threshold=20, fast_threshold_first=10), "test")


def test_mapping_puts_a_cube_corner_on_the_corner(camera, pipeline):
    """Views from three sides of a 3 m cube: the top corner lands on the corner, height included."""
    world = make_world([{"east_m": 0.0, "north_m": 0.0, "size_m": 3.0, "color": "white"}])
    renderer = Renderer(world, camera)
    lm = LandmarkMap()
    mapper = Mapper(pipeline, camera, R_BODY_CAM_DOWN, lm)
    det = FeatureDetector(pipeline.detector)
    for n in np.linspace(-6, 6, 25):
        for e in (-4.0, 0.0, 4.0):
            pose = CameraPose(np.array([n, e, -15.0]), R_BODY_CAM_DOWN)
            frame = renderer.render(pose)
            mapper.process(det.detect(frame.image_bgr), NavSample(0.0, pose.p_cam_in_ned_m, 15.0, np.eye(3)))
    used = np.flatnonzero(lm.n_seen[: len(lm)] >= pipeline.mapping.min_seen)
    assert len(used) >= 4
    corners = world.cubes[0].vertices_ned()
    err = np.min(np.linalg.norm(lm.p_ned_m[used][:, None, :] - corners[None], axis=2), axis=1)
    assert np.median(err) < 0.10  # 10 cm in 3D, with heights 0 m and 3 m told apart
    tops = lm.p_ned_m[used][:, 2] < -1.5
    assert tops.any() and np.all(np.abs(lm.p_ned_m[used][tops, 2] + 3.0) < 0.3)


def test_a_frame_detected_shrunk_finds_the_corners_in_full_resolution_pixels(camera, pipeline):
    """A 1 m cube from 5 m, detected at 0.4 scale: its top corners, in full-resolution pixels, within 2.5 px
    (one detection pixel) of where the camera model projects them, and the features say their scale."""
    world = make_world([{"east_m": 0.3, "north_m": -0.2, "size_m": 1.0, "color": "red", "yaw_deg": 25}])
    pose = CameraPose(np.array([0.0, 0.0, -5.0]), R_BODY_CAM_DOWN)
    image = Renderer(world, camera).render(pose).image_bgr
    feats = FeatureDetector(pipeline.detector).detect(image, pose.R_ned_cam, scale=0.4)
    assert feats.scale == 0.4
    top = world.cubes[0].vertices_ned()
    top = top[top[:, 2] < -0.5]
    uv, _ = pose.project(camera, top)
    nearest = np.min(np.linalg.norm(uv[:, None, :] - feats.uv_px[None], axis=2), axis=1)
    assert np.all(nearest < 2.5), nearest


def test_detection_scale_follows_the_range_the_map_saw_its_landmarks_at(camera, pipeline):
    pts = np.column_stack([np.linspace(-3, 3, 20), np.linspace(3, -3, 20), np.zeros(20)])
    lm, _ = synthetic_map(camera, pts)
    mapped_from = np.array([0.0, 0.0, -16.0])
    lm.descriptor_range_m[: len(pts)] = np.linalg.norm(pts - mapped_from, axis=1)
    loc = Localiser(pipeline, camera, R_BODY_CAM_DOWN, lm)
    prior = PositionPrior(np.array([0.0, 0.0, -8.0]), 0.2)
    assert 0.45 < loc.detection_scale(8.0, prior) < 0.55  # about half the range: about half the size
    assert loc.detection_scale(14.0, prior) == 1.0  # within the detector's own pyramid step
    assert loc.detection_scale(16.0, prior) == 1.0  # where the map was made
    assert loc.detection_scale(1.0, prior) == pipeline.positioning.min_detection_scale
    assert loc.detection_scale(8.0, None) == 1.0  # no prior: no idea which landmarks are in view
    lm.descriptor_range_m[: len(pts)] = np.nan  # a map from before the ranges were kept
    assert loc.detection_scale(8.0, prior) == 1.0


def two_cubes_crossed():
    """Two different cubes, a small survey over them and a crossing flight: (world, sim config)."""
    world = make_world(
        [
            {"east_m": 1.0, "north_m": 1.0, "size_m": 1.0, "color": "red"},
            {"east_m": -2.0, "north_m": -2.0, "size_m": 1.0, "color": "blue", "yaw_deg": 30},
        ]
    )
    small = dict(north_min_m=-4.0, north_max_m=4.0, east_min_m=-4.0, east_max_m=4.0, spacing_m=2.0)
    return world, parse_as(SimConfig, {"mapping": small, "positioning": dict(small, legs="ew", offset_m=1.0)}, "test")


@pytest.mark.slow
def test_short_mapping_then_positioning_flight(pipeline):
    """A small survey over two different cubes, then a crossing flight without GPS: per-frame thresholds."""
    world, sim = two_cubes_crossed()
    rec = run_once(world, 12.0, 3.0, 11, pipeline, sim)
    lm_err = np.linalg.norm(rec.landmark_err_ne_m, axis=1)
    fix_err = np.linalg.norm(rec.fix_err_ne_m, axis=1)
    assert len(lm_err) >= 10 and np.sqrt(np.mean(lm_err**2)) < 0.15
    assert rec.n_eligible_fixed / rec.n_eligible_frames > 0.8
    assert np.sqrt(np.mean(fix_err**2)) < 0.15 and fix_err.max() < 0.5


def test_ransac_seed_bound_known_answers():
    """Half the seeds in the set: two draws find one with probability 0.75; certainty takes every seed."""
    assert _ransac_seeds(0.5, 0.75) == pytest.approx(2.0, rel=rtol_equal)
    assert _ransac_seeds(0.084, 0.999) == pytest.approx(np.log(0.001) / np.log(1.0 - 0.084), rel=rtol_equal)
    assert _ransac_seeds(1.0, 0.999) == 1.0
    assert _ransac_seeds(0.3, 1.0) == np.inf


def test_prefix_spread_order_is_a_permutation_whose_prefixes_spread():
    np.testing.assert_array_equal(_prefix_spread_order(8), [0, 4, 2, 6, 1, 5, 3, 7])
    order = _prefix_spread_order(300)
    np.testing.assert_array_equal(np.sort(order), np.arange(300))
    assert np.max(np.diff(np.sort(order[:32]))) <= 2 * 300 // 32  # no gap wider than twice an even spread's


def consensus_scene(n_features=400, n_right=300, seed=5):
    """Correspondences of ``n_features`` features: ``n_right`` of them with one whose hypothesis is near (1, 2) m,
    every feature with two wrong ones spread over 6 m by 6 m; tau 0.1 m."""
    rng = np.random.default_rng(seed)
    right = np.arange(n_right)
    feat_i = np.sort(np.concatenate([right, np.repeat(np.arange(n_features), 2)]))
    hyp = rng.uniform(-3.0, 3.0, (len(feat_i), 2))
    first = np.searchsorted(feat_i, right)  # each right feature's first correspondence is its right one
    hyp[first] = np.array([1.0, 2.0]) + rng.normal(0.0, 0.02, (n_right, 2))
    K = len(feat_i)
    return _Correspondences(feat_i, np.arange(K), np.zeros((K, 3)), np.tile([0.0, 0.0, 1.0], (K, 1)), hyp, np.full(K, 0.1))


def support_by_brute_force(corr, seeds):
    near = np.linalg.norm(corr.hyp[:, None, :] - corr.hyp[seeds][None], axis=2) <= corr.tau[:, None]
    return np.array([len(np.unique(corr.feat_i[near[:, s]])) for s in range(len(seeds))])


def test_consensus_at_full_confidence_seeds_the_whole_even_spread(camera, pipeline):
    corr = consensus_scene()
    cfg = parse_as(PipelineConfig, {"positioning": {"seed_confidence": 1.0}}, "test")
    seeds, support = Localiser(cfg, camera, R_BODY_CAM_DOWN, LandmarkMap())._consensus(corr)
    max_seeds = cfg.positioning.max_seeds
    np.testing.assert_array_equal(np.sort(seeds), np.linspace(0, len(corr.hyp) - 1, max_seeds).astype(int))
    np.testing.assert_array_equal(support, support_by_brute_force(corr, seeds))


def test_consensus_stops_seeding_once_a_strong_consensus_is_found(camera, pipeline):
    """300 of 1100 correspondences agree: far fewer seeds than max_seeds are enough by the RANSAC bound, and
    they find the consensus with the support all the seeds find."""
    corr = consensus_scene()
    seeds, support = Localiser(pipeline, camera, R_BODY_CAM_DOWN, LandmarkMap())._consensus(corr)
    cfg = parse_as(PipelineConfig, {"positioning": {"seed_confidence": 1.0}}, "test")
    _, support_all = Localiser(cfg, camera, R_BODY_CAM_DOWN, LandmarkMap())._consensus(corr)
    w = pipeline.positioning.rival_min_share * support.max() / len(corr.hyp)
    assert len(seeds) >= _ransac_seeds(w, pipeline.positioning.seed_confidence)
    assert len(seeds) < pipeline.positioning.max_seeds / 2
    np.testing.assert_array_equal(support, support_by_brute_force(corr, seeds))
    assert support.max() == support_all.max()


@pytest.mark.parametrize("radix", [True, False])
def test_pairs_within_equals_brute_force_in_order(monkeypatch, radix):
    """Every pair within the radius, bound included, ordered by i then j: by the radix sorts of 16-bit indices and
    by the one sort of (i, j) keys that larger index sets take."""
    import auxgps.core.features as features

    if not radix:
        monkeypatch.setattr(features, "_RADIX_SORTABLE", 0)
    rng = np.random.default_rng(11)
    a = rng.uniform(0, 200, (300, 2)).round()  # whole pixels: some pairs exactly at the radius
    b = rng.uniform(0, 200, (500, 2)).round()
    i, j = features.pairs_within(a, b, 10.0)
    i_ref, j_ref = np.nonzero(np.linalg.norm(a[:, None] - b[None], axis=2) <= 10.0)  # row-major: i then j
    np.testing.assert_array_equal(i, i_ref)
    np.testing.assert_array_equal(j, j_ref)
    assert i.dtype == j.dtype == np.int64


@pytest.mark.parametrize("radix", [True, False])
def test_pairs_within_unordered_are_the_same_pairs_and_pair_order_orders_them(monkeypatch, radix):
    """``ordered=False`` gives the same set of pairs in the trees' order; :func:`pair_order` puts any subset of
    them in order of i then j, as the mapper does with the few it keeps."""
    import auxgps.core.features as features

    if not radix:
        monkeypatch.setattr(features, "_RADIX_SORTABLE", 0)
    rng = np.random.default_rng(12)
    a = rng.uniform(0, 200, (300, 2)).round()
    b = rng.uniform(0, 200, (500, 2)).round()
    i, j = features.pairs_within(a, b, 10.0)
    iu, ju = features.pairs_within(a, b, 10.0, ordered=False)
    assert set(zip(iu.tolist(), ju.tolist())) == set(zip(i.tolist(), j.tolist()))
    keep = rng.random(len(iu)) < 0.1
    order = features.pair_order(iu[keep], ju[keep], len(a), len(b))
    ref = np.lexsort((ju[keep], iu[keep]))
    np.testing.assert_array_equal(iu[keep][order], iu[keep][ref])
    np.testing.assert_array_equal(ju[keep][order], ju[keep][ref])


def test_pairs_within_radii_gives_each_b_its_own_radius():
    """Every pair with ``|a_i - b_j| <= radius_j``, bound included, and no other, whichever group of radii ``b_j``
    is searched in (a radius on a group's edge, and one past the last)."""
    from auxgps.core.features import pairs_within_radii

    rng = np.random.default_rng(13)
    a = rng.uniform(0, 200, (300, 2)).round()
    b = rng.uniform(0, 200, (500, 2)).round()
    radius = rng.choice([0.5, 3.0, 5.0, 12.0, 20.0, 24.0, 30.0, 48.0], len(b))
    i, j = pairs_within_radii(a, b, radius)
    ref = set(zip(*(x.tolist() for x in np.nonzero(np.linalg.norm(a[:, None] - b[None], axis=2) <= radius[None]))))
    assert len(i) == len(ref) == len(set(zip(i.tolist(), j.tolist())))
    assert set(zip(i.tolist(), j.tolist())) == ref
    assert len(ref) > 1000  # pairs in every group
    assert pairs_within_radii(a[:0], b, radius)[0].size == 0


def test_mapper_pixel_sigma_is_the_landmark_covariance_carried_through_the_projection(pipeline):
    """The largest one-sigma of a landmark's predicted pixel: the square root of the largest eigenvalue of
    ``J C J^T`` (``J`` the projection's Jacobian, here by finite differences), from a tilted camera; a landmark loose
    along the ray to the camera does not move in the image."""
    camera = PinholeCamera.from_hfov(1280, 720, np.deg2rad(70.0))
    mapper = Mapper(pipeline, camera, R_BODY_CAM_DOWN, LandmarkMap())
    pose = CameraPose(np.array([3.0, -2.0, -40.0]), R_ned_body_from_euler(*np.deg2rad([4.0, -3.0, 30.0])) @ R_BODY_CAM_DOWN)
    rng = np.random.default_rng(3)
    L = np.column_stack([rng.uniform(-20, 20, (40, 2)), rng.uniform(-2, 2, 40)])
    G = rng.normal(0, 0.5, (40, 3, 3))
    cov = G @ G.transpose(0, 2, 1) + 0.01 * np.eye(3)
    got = mapper._pixel_sigma_px(L, cov, pose)
    for k in range(len(L)):
        J = np.column_stack([(pose.project(camera, L[k] + h)[0][0] - pose.project(camera, L[k] - h)[0][0]) / 2e-4
                             for h in np.eye(3) * 1e-4])
        assert got[k] == pytest.approx(np.sqrt(np.linalg.eigvalsh(J @ cov[k] @ J.T)[-1]), rel=1e-4)
    ray = (L[0] - pose.p_cam_in_ned_m) / np.linalg.norm(L[0] - pose.p_cam_in_ned_m)
    along = 9.0 * np.outer(ray, ray) + 1e-6 * np.eye(3)  # 3 m along the ray
    assert mapper._pixel_sigma_px(L[:1], along[None], pose)[0] < 0.05  # its largest sigma over its range: 60 px


@pytest.mark.parametrize("euler_deg", [(0.0, 0.0, 0.0), (4.0, -3.0, 30.0), (25.0, 10.0, -120.0)])
def test_box_in_view_holds_every_point_the_image_sees_down_to_its_depth(euler_deg):
    """Points through random pixels of the image (and its margin) at random depths down to the limit, from level and
    tilted cameras, with a distorted lens: all inside the box; a camera that sees the horizon has none."""
    cam = PinholeCamera.from_hfov(1280, 720, np.deg2rad(80.0))
    camera = PinholeCamera(cam.width_px, cam.height_px, cam.K, np.array([0.1, -0.05, 0.0, 0.0, 0.0]))
    pose = CameraPose(np.array([10.0, -5.0, -40.0]), R_ned_body_from_euler(*np.deg2rad(euler_deg)) @ R_BODY_CAM_DOWN)
    rng = np.random.default_rng(8)
    uv = np.column_stack([rng.uniform(-12, 1291, 5000), rng.uniform(-12, 731, 5000)])
    uv[:4] = [[-12, -12], [1291, -12], [-12, 731], [1291, 731]]
    rays = pose.rays_ned(camera, uv)
    depth = rng.uniform(0.1, 45.0, len(uv))
    depth[:4] = 45.0
    p = pose.p_cam_in_ned_m + rays * (depth / rays[:, 2])[:, None]
    (n0, n1), (e0, e1) = pose.box_in_view(camera, 45.0, 12.0)
    assert np.all((p[:, 0] >= n0 - 1e-9) & (p[:, 0] <= n1 + 1e-9) & (p[:, 1] >= e0 - 1e-9) & (p[:, 1] <= e1 + 1e-9))
    assert (n1 - n0) * (e1 - e0) < 1.3 * np.ptp(p[:, 0]) * np.ptp(p[:, 1])  # and not much more
    sideways = CameraPose(np.zeros(3), R_ned_body_from_euler(np.deg2rad(60.0), 0.0, 0.0) @ R_BODY_CAM_DOWN)
    assert sideways.box_in_view(camera, 45.0) is None


def test_hamming_pairs_is_hamming_of_the_gathered_rows():
    """Word by word, including the largest distance (every bit differs: 256, past a byte), and by the byte table
    for descriptors of another length."""
    from auxgps.core.features import hamming, hamming_pairs

    rng = np.random.default_rng(5)
    a = rng.integers(0, 256, (50, 32), dtype=np.uint8)
    b = rng.integers(0, 256, (70, 32), dtype=np.uint8)
    b[0] = ~a[0]
    ia, ib = rng.integers(0, 50, 1000), rng.integers(0, 70, 1000)
    ia[0], ib[0] = 0, 0
    got = hamming_pairs(a, ia, b, ib)
    np.testing.assert_array_equal(got, hamming(a[ia], b[ib]))
    assert got[0] == 256 and got.dtype == np.int32
    a16, b16 = a[:, :16], b[:, :16]
    np.testing.assert_array_equal(hamming_pairs(a16, ia, b16, ib), hamming(a16[ia], b16[ib]))
    assert len(hamming_pairs(a, np.zeros(0, int), b, np.zeros(0, int))) == 0


def _greedy_loop(a, b):
    used_a, used_b, kept = set(), set(), []
    for k, (x, y) in enumerate(zip(a.tolist(), b.tolist())):
        if x in used_a or y in used_b:
            continue
        used_a.add(x)
        used_b.add(y)
        kept.append(k)
    return np.array(kept, int)


@pytest.mark.parametrize("seed", range(6))
def test_greedy_one_to_one_in_rounds_keeps_the_pairs_the_loop_keeps(seed):
    """The mapper's one-to-one assignment in rounds of array work against the pair-by-pair loop it replaced, on
    pair lists as crowded as a frame's (about three candidate landmarks a feature, chains of shared ends)."""
    from auxgps.core.features import _greedy_one_to_one_in_rounds, greedy_one_to_one

    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 3000)) if seed < 5 else 12000  # the last over GREEDY_LOOP_MAX_PAIRS
    a = rng.integers(0, max(1, n // 3), n)
    b = rng.integers(0, max(1, n // 4), n)
    kept = greedy_one_to_one(a, b)
    np.testing.assert_array_equal(kept, _greedy_loop(a, b))
    np.testing.assert_array_equal(_greedy_one_to_one_in_rounds(a, b), kept)  # the long lists' way, on the same pairs
    assert len(np.unique(a[kept])) == len(np.unique(b[kept])) == len(kept)
    assert len(greedy_one_to_one(np.zeros(0, int), np.zeros(0, int))) == 0
    assert len(_greedy_one_to_one_in_rounds(np.zeros(0, int), np.zeros(0, int))) == 0


@pytest.mark.parametrize("seed", range(4))
def test_spots_are_the_connected_components_of_features_within_the_radius(seed):
    """Features chained within the radius share a spot id, numbered as scipy's connected components number them;
    checked against scipy on frames of clustered features (pyramid duplicates, and chains of several)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    from auxgps.core.features import spots

    rng = np.random.default_rng(seed)
    centres = rng.uniform([0, 0], [1280, 720], (300, 2))
    uv = np.concatenate([centres, centres[:120] + rng.normal(0, 1.0, (120, 2)), centres[:40] + rng.normal(0, 2.5, (40, 2))])
    uv = uv[rng.permutation(len(uv))]
    tree = cKDTree(uv)
    pairs = tree.query_pairs(2.0, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs), bool), (pairs[:, 0], pairs[:, 1])), shape=(len(uv), len(uv)))
    expected = connected_components(graph, directed=False)[1]
    got = spots(tree, 2.0)
    np.testing.assert_array_equal(got, expected)
    assert len(np.unique(got)) < len(uv)  # some features did share a spot
    np.testing.assert_array_equal(spots(cKDTree(uv[:1]), 2.0), [0])


def test_common_shift_is_the_mean_of_the_densest_cluster_of_offsets():
    """A frame's candidate offsets: a tight cluster at the GPS and attitude shift, a looser second cluster (a
    repeated pattern) and uniform clutter out to the match radius. The shift is the first cluster's mean; too few
    agreeing offsets give none; offsets left out (those of landmarks not yet established) do not vote."""
    rng = np.random.default_rng(3)
    true_shift = np.array([7.3, -4.1])
    cluster = true_shift + rng.normal(0, 0.5, (300, 2))
    decoy = np.array([-20.0, 15.0]) + rng.normal(0, 1.5, (200, 2))
    clutter = rng.uniform(-48, 48, (1500, 2))
    off = np.vstack([cluster, decoy, clutter])
    shift = Mapper._common_shift(off)
    near = np.linalg.norm(off - true_shift, axis=1) <= 2.0
    assert np.linalg.norm(shift - true_shift) < 0.15
    assert np.linalg.norm(shift - off[near].mean(axis=0)) < 0.15
    # The decoy alone counts when the cluster's landmarks are new ones.
    established = np.ones(len(off), bool)
    established[:300] = False
    assert np.linalg.norm(Mapper._common_shift(off[established]) - np.array([-20.0, 15.0])) < 0.5
    np.testing.assert_array_equal(Mapper._common_shift(rng.uniform(-48, 48, (2, 2))), np.zeros(2))
    # The histogram only picks whom to count exactly: the offset that counting every offset's neighbours finds,
    # or in a broad cluster of near-equal counts one whose shift is a fraction of a pixel from it.
    same = 0
    for seed in range(40):
        r = np.random.default_rng(seed)
        off = np.vstack([r.normal(r.uniform(-10, 10, 2), r.uniform(0.3, 3.0), (int(r.integers(0, 1500)), 2)),
                         r.uniform(-48, 48, (int(r.integers(3, 1500)), 2))])
        votes = np.count_nonzero(np.linalg.norm(off[:, None] - off[None], axis=2) <= 2.0, axis=1)
        ref = off[np.linalg.norm(off - off[np.argmax(votes)], axis=1) <= 2.0].mean(axis=0)
        got = Mapper._common_shift(off)
        same += np.array_equal(got, ref)
        assert np.linalg.norm(got - ref) < 0.5
    assert same >= 36
    far_apart = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [-10.0, -10.0]])
    np.testing.assert_array_equal(Mapper._common_shift(far_apart), np.zeros(2))


def test_ray_mahalanobis2_is_the_distance_across_the_ray_in_any_basis_of_that_plane():
    """Against its definition with a basis of the plane across each ray from an SVD: steep and shallow rays alike."""
    from auxgps.core.mapping import ray_mahalanobis2

    rng = np.random.default_rng(5)
    m = 400
    d = rng.normal(size=(m, 3))
    d[: m // 2, 2] = np.abs(d[: m // 2, 2]) * 20.0  # half of them near nadir
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    c = np.array([1.0, -2.0, -15.0])
    L = c + d * rng.uniform(5, 30, (m, 1)) + rng.normal(0, 0.3, (m, 3))
    A = rng.normal(size=(m, 3, 3)) * 0.1
    cov = A @ A.transpose(0, 2, 1) + 1e-3 * np.eye(3)
    sigma = rng.uniform(0.01, 0.2, m)
    got = ray_mahalanobis2(L, cov, c, d, sigma)
    for k in range(m):
        E = np.linalg.svd(d[k][None])[2][1:]  # (2, 3): orthonormal, across d
        r = E @ (L[k] - c)
        S = E @ cov[k] @ E.T + sigma[k] ** 2 * np.eye(2)
        assert got[k] == pytest.approx(r @ np.linalg.solve(S, r), rel=1e-9)


def test_features_far_off_nadir_are_dropped_as_the_camera_tilts(camera):
    """Points on the ground 0, 30, 40, 50 and 60 deg from straight down ahead of a camera 40 m up: those past 45 deg
    go. The angle is the ray's from the vertical, not from the lens's axis: pitched 20 deg nose down (as at speed),
    the same points go (the lens looks back: from its axis they are 20 to 80 deg off, and a limit there keeps one)."""
    from auxgps.core.features import near_nadir

    angles_deg = np.array([0.0, 30.0, 40.0, 50.0, 60.0])
    points = np.column_stack([40.0 * np.tan(np.deg2rad(angles_deg)), np.zeros(5), np.zeros(5)])
    for pitch_deg in (0.0, -20.0):
        R_ned_cam = R_ned_body_from_euler(0.0, np.deg2rad(pitch_deg), 0.0) @ R_BODY_CAM_DOWN
        pose = CameraPose(np.array([0.0, 0.0, -40.0]), R_ned_cam)
        feats = view(camera, pose, points, np.arange(5 * 32, dtype=np.uint8).reshape(5, 32))
        kept = near_nadir(feats, camera, R_ned_cam, 45.0)
        np.testing.assert_array_equal(kept.descriptors[:, 0], feats.descriptors[[0, 1, 2], 0])
        assert near_nadir(feats, camera, R_ned_cam, None) is feats
