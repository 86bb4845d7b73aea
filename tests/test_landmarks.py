"""The landmark map's spatial index: it must return exactly what a scan of every landmark returns."""

import numpy as np
import pytest

from auxgps.core.landmarks import GridIndex, LandmarkMap
from auxgps.core.mapping import ray_bias_terms, ray_information


def random_map(n, rng, spread_m=60.0, capacity=16):
    lm = LandmarkMap(capacity=capacity)
    p = np.column_stack([rng.uniform(-spread_m, spread_m, (n, 2)), rng.uniform(-3.0, 0.0, n)])
    lm.add(rng.integers(0, 256, (n, 32), dtype=np.uint8), p, np.repeat(np.eye(3)[None] * 100.0, n, 0), np.ones(n))
    return lm


def random_boxes(rng, k, spread_m=70.0):
    for _ in range(k):
        n0, e0 = rng.uniform(-spread_m, spread_m, 2)
        size = rng.choice([0.0, 0.5, 3.0, 17.0, 48.0, 300.0])
        yield (n0, n0 + size * rng.uniform(0, 1)), (e0, e0 + size * rng.uniform(0, 1))


def test_index_returns_the_same_ids_as_a_scan():
    rng = np.random.default_rng(5)
    lm = random_map(20000, rng)
    for north, east in random_boxes(rng, 200):
        assert np.array_equal(lm.ids_in_box(north, east), lm.ids_in_box_scan(north, east))


def test_index_follows_additions_and_moves():
    """Landmarks added in batches and moved by observations (across cells) are still found exactly."""
    rng = np.random.default_rng(6)
    lm = random_map(3000, rng)
    for step in range(30):
        lm.ids_in_box((-10.0, 10.0), (-10.0, 10.0))  # a query between updates, as a flight does
        more = random_map(200, rng)
        lm.add(more.descriptors[:200], more.p_ned_m[:200], np.repeat(np.eye(3)[None] * 100.0, 200, 0), np.ones(200))
        ids = rng.choice(len(lm), 500, replace=False)
        target = lm.p_ned_m[ids].astype(float) + rng.normal(0.0, 3.0, (500, 3))  # metres: many change cell
        A_obs = np.repeat(np.eye(3)[None] * 1e6, 500, 0)  # a strong observation pulls each onto its target
        lm.observe(ids, A_obs, np.einsum("nij,nj->ni", A_obs, target), lm.descriptors[ids], np.zeros(500), np.zeros(500))
        for north, east in random_boxes(rng, 10):
            assert np.array_equal(lm.ids_in_box(north, east), lm.ids_in_box_scan(north, east)), f"step {step}"


def test_box_bounds_on_cell_borders_are_inclusive():
    lm = LandmarkMap()
    pts = np.array([[2.0, 4.0, 0.0], [-2.0, -4.0, 0.0], [1.9999999, 3.9999999, 0.0], [0.0, 0.0, 0.0]])
    lm.add(np.zeros((4, 32), np.uint8), pts, np.repeat(np.eye(3)[None], 4, 0), np.ones(4))
    for north, east in [((2.0, 2.0), (4.0, 4.0)), ((-2.0, 2.0), (-4.0, 4.0)), ((1.9999999, 2.0), (0.0, 4.0))]:
        assert np.array_equal(lm.ids_in_box(north, east), lm.ids_in_box_scan(north, east))


def test_reindex_after_direct_writes():
    rng = np.random.default_rng(7)
    lm = random_map(1000, rng)
    lm.ids_in_box((0.0, 1.0), (0.0, 1.0))
    lm.p_ned_m[: len(lm), :2] += 25.0  # written directly: the caller must say so
    lm.reindex()
    assert np.array_equal(lm.ids_in_box((0.0, 30.0), (0.0, 30.0)), lm.ids_in_box_scan((0.0, 30.0), (0.0, 30.0)))


def test_index_memory_is_counted():
    lm = random_map(5000, np.random.default_rng(8), capacity=5000)
    lm.ids_in_box((0.0, 1.0), (0.0, 1.0))
    mem = lm.memory_bytes()
    assert mem["index"] == 8 * 5000 and mem["slack"] == 0
    assert mem["total"] == mem["columns"] + mem["index"]


def test_bad_cell_size_is_refused():
    with pytest.raises(ValueError):
        GridIndex(cell_m=0.0)


def test_variance_across_rays_equals_the_projected_covariance():
    rng = np.random.default_rng(5)
    lm = LandmarkMap()
    rays = rng.normal(size=(50, 4, 3))
    rays /= np.linalg.norm(rays, axis=2, keepdims=True)
    info = np.einsum("nk,nkij->nij", rng.uniform(100.0, 1e4, (50, 4)), np.eye(3) - rays[..., :, None] * rays[..., None, :])
    ids = lm.add(rng.integers(0, 256, (50, 32), dtype=np.uint8), rng.normal(size=(50, 3)), info, np.ones(50))
    cov = lm.covariance(ids)
    d = rng.normal(size=(50, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    P = np.eye(3) - d[:, :, None] * d[:, None, :]
    expected = np.einsum("kij,kjl,kli->k", P, cov, P) / 2.0
    np.testing.assert_allclose(lm.variance_across_rays_m2(ids, d), expected, rtol=1e-9)
    down = np.tile([0.0, 0.0, 1.0], (50, 1))  # straight down: the mean horizontal variance
    np.testing.assert_allclose(lm.variance_across_rays_m2(ids, down), (cov[:, 0, 0] + cov[:, 1, 1]) / 2.0, rtol=1e-9)


def test_first_seen_times_are_kept_a_loaded_map_counts_as_old_and_demoted_landmarks_are_never_usable():
    lm = LandmarkMap(capacity=2)
    info = np.repeat(np.eye(3)[None] * 100.0, 3, axis=0)
    ids = lm.add(np.zeros((3, 32), np.uint8), np.zeros((3, 3)), info, np.ones(3, np.float16), t_first_s=12.5)  # grows
    assert np.all(lm.t_first_s[ids] == 12.5) and np.all(np.isneginf(lm.t_first_s[3:]))
    loaded = LandmarkMap.from_columns({k: v for k, v in lm.columns().items() if k != "t_first_s"})  # a map file's
    assert np.all(np.isneginf(loaded.t_first_s[: len(loaded)]))
    lm.n_seen[ids] = 20
    lm.n_visible[ids] = 20
    assert lm.usable(ids, 5, 3.0, 0.5).all()
    lm.demote(ids[:2])
    assert lm.usable(ids, 5, 3.0, 0.5).tolist() == [False, False, True]


def _observe_at(lm, ids, point_ned_m, t_s, rng):
    A = np.repeat(np.eye(3)[None] * 400.0, len(ids), 0)
    b = A @ np.asarray(point_ned_m, float)
    lm.count_visible(ids, t_s)
    lm.observe(ids, A, b, rng.integers(0, 256, (len(ids), 32), dtype=np.uint8), np.full(len(ids), 0.99, np.float16),
               np.full(len(ids), 0.5), 7.0, t_s)


def test_roll_back_puts_every_column_and_the_index_back_as_they_were_and_takes_newer_landmarks_out_of_use():
    rng = np.random.default_rng(3)
    lm = random_map(200, rng)
    lm.keep_journal(30.0)
    ids = np.arange(0, 200, 3)
    _observe_at(lm, ids, [1.0, 2.0, -1.0], 10.0, rng)
    before = {k: v.copy() for k, v in lm.columns().items()}
    # After 10 s: older landmarks observed from a dragged pose (twice, some in both), and new ones geotagged.
    _observe_at(lm, ids[::2], [30.0, -20.0, 0.0], 11.0, rng)
    _observe_at(lm, ids[:20], [31.0, -21.0, 0.0], 12.0, rng)
    new = lm.add(rng.integers(0, 256, (5, 32), dtype=np.uint8), np.full((5, 3), 40.0), np.repeat(np.eye(3)[None], 5, 0),
                 np.ones(5, np.float16), t_first_s=12.0)
    restored, dropped, complete = lm.roll_back(10.0)
    assert complete
    assert np.array_equal(dropped, new) and np.array_equal(restored, np.union1d(ids[::2], ids[:20]))
    after = lm.columns()
    for name, value in before.items():
        np.testing.assert_array_equal(after[name][:200], value, err_msg=name)
    assert not lm.usable(new, 1, 3.0, 0.0).any()
    for north, east in [((0.0, 5.0), (-5.0, 5.0)), ((25.0, 35.0), (-25.0, -15.0)), ((-60.0, 60.0), (-60.0, 60.0))]:
        assert np.array_equal(lm.ids_in_box(north, east), lm.ids_in_box_scan(north, east))


def test_a_journal_says_when_it_cannot_reach_back_and_keeps_only_its_span():
    rng = np.random.default_rng(4)
    lm = random_map(50, rng)
    lm.keep_journal(5.0)
    for t in np.arange(0.0, 20.0, 1.0):
        _observe_at(lm, np.arange(10), [t, 0.0, 0.0], float(t), rng)
    assert lm.journal_bytes < 6 * 2 * 10 * 120  # about 6 frames of 10 landmarks, two entries each
    p_at_16 = lm.p_ned_m[:10].copy()
    _, _, complete = lm.roll_back(16.0)  # inside the span
    assert complete
    _observe_at(lm, np.arange(10), [50.0, 0.0, 0.0], 17.0, rng)
    _observe_at(lm, np.arange(10), [50.0, 0.0, 0.0], 18.0, rng)
    restored, _, complete = lm.roll_back(2.0)  # beyond it: what it kept is undone, and it says it could not do more
    assert not complete and np.array_equal(restored, np.arange(10))
    assert np.abs(lm.p_ned_m[:10] - p_at_16).max() > 0.0  # the changes it had let go of stay
    no_journal = random_map(5, rng)
    _observe_at(no_journal, np.arange(5), [1.0, 0.0, 0.0], 1.0, rng)
    assert no_journal.journal_bytes == 0 and no_journal.roll_back(0.0)[0].size == 0



def _rz(a_rad):
    c, s = np.cos(a_rad), np.sin(a_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _map_leg(lm, L, cameras, corrections_rad, true_rad, t0_s=0.0, turn=True, step_rad=np.deg2rad(0.01)):
    """Map landmarks ``L`` (K, 3) from each camera in turn, as the mapper does: each view's rays turned by what the
    heading correction of its moment leaves of the true error; between views, the map turned (in steps) as the
    correction moves, then to the true error at the end (``turn``). Returns the ids and the largest error before
    that last turn."""
    from auxgps.core.geometry import intersect_rays_with_horizontal_plane
    from auxgps.core.mapping import ray_information
    from auxgps.core.retag import HeadingView

    def turn_to(b_from, b_to):
        steps = np.linspace(b_from, b_to, int(abs(b_to - b_from) / step_rad) + 2)
        for b_before, b in zip(steps[:-1], steps[1:]):
            lm.turn(b, b_before, t0_s - 1.0)

    ids = None
    for k, (c, b) in enumerate(zip(cameras, corrections_rad)):
        if turn and k:
            turn_to(corrections_rad[k - 1], b)
        d = (L - c) / np.linalg.norm(L - c, axis=1, keepdims=True) @ _rz(true_rad - b).T
        A = ray_information(d, np.full(len(L), 0.05))
        view = HeadingView(b, c) if turn else None
        if ids is None:
            p0, _ = intersect_rays_with_horizontal_plane(c, d, 0.0)
            A[:, 2, 2] += 1.0 / 3.0**2
            ids = lm.add(np.zeros((len(L), 32), np.uint8), p0, A, np.ones(len(L), np.float16), t_first_s=t0_s + k, view=view)
        else:
            lm.observe(ids, A, np.einsum("nij,j->ni", A, c), np.zeros((len(L), 32), np.uint8), np.ones(len(L), np.float16),
                       np.zeros(len(L)), t_s=t0_s + k, view=view)
    err_m = np.abs(lm.p_ned_m[ids] - L).max()
    if turn:
        turn_to(corrections_rad[-1], true_rad)
    return ids, err_m


def test_turn_geotags_landmarks_again_as_the_heading_solved_later_puts_them():
    """A leg mapped while the solver's heading correction moved (2, 1.4, then 0.8 deg, the true error): rays turned
    by different amounts put landmarks up to a metre off, in height as well; turned again as the correction moved,
    every landmark is where the true heading puts it, within millimetres. Landmarks seen before the window and a
    loaded map's (no views kept) stay as they are."""
    rng = np.random.default_rng(5)
    L = np.column_stack([rng.uniform(-20, 40, 30), rng.uniform(-25, 25, 30), np.zeros(30)])
    cameras = [np.array([n, 0.0, -40.0]) for n in (0.0, 8.0, 16.0, 24.0)]
    true_rad = np.deg2rad(0.8)
    corrections = np.deg2rad([2.0, 1.4, 0.8, 0.8])
    not_turned = LandmarkMap()
    ids_not_turned, _ = _map_leg(not_turned, L, cameras, corrections, true_rad, turn=False)
    assert np.abs(not_turned.p_ned_m[ids_not_turned] - L).max() > 0.8
    lm = LandmarkMap()
    loaded = lm.merge(not_turned)
    old, _ = _map_leg(lm, L, cameras, corrections, true_rad, t0_s=0.0)
    ids, _ = _map_leg(lm, L, cameras, corrections, true_rad, t0_s=100.0)
    assert np.abs(lm.p_ned_m[ids] - L).max() < 0.005
    # The first leg's landmarks left the window (last seen 100 s earlier) before the second leg turned the map.
    assert np.abs(lm.p_ned_m[old] - L).max() < 0.005 and len(lm.recent_views) == len(ids)
    np.testing.assert_array_equal(lm.p_ned_m[loaded], not_turned.p_ned_m[ids_not_turned])
    # Views that share one correction are turned exactly, however far: one turn of 1.2 deg.
    at_once = LandmarkMap()
    ids_at_once, _ = _map_leg(at_once, L, cameras, np.deg2rad([2.0, 2.0, 2.0, 2.0]), true_rad, step_rad=np.deg2rad(5.0))
    assert np.abs(at_once.p_ned_m[ids_at_once] - L).max() < 0.005
    p_now = lm.p_ned_m[ids].copy()
    lm.turn(true_rad, true_rad, 99.0)  # to the same correction: nothing moves
    np.testing.assert_allclose(lm.p_ned_m[ids], p_now, atol=1e-5)
    assert np.array_equal(lm.ids_in_box((-30.0, 50.0), (-30.0, 30.0)), lm.ids_in_box_scan((-30.0, 50.0), (-30.0, 30.0)))


def test_an_undo_forgets_the_views_of_what_it_put_back():
    rng = np.random.default_rng(6)
    L = np.column_stack([rng.uniform(-20, 40, 10), rng.uniform(-25, 25, 10), np.zeros(10)])
    lm = LandmarkMap()
    lm.keep_journal(30.0)
    ids, _ = _map_leg(lm, L, [np.array([n, 0.0, -40.0]) for n in (0.0, 8.0, 16.0)], np.deg2rad([1.0, 1.0, 1.0]), np.deg2rad(1.0))
    assert len(lm.recent_views) == len(ids)
    lm.roll_back(0.5)
    assert len(lm.recent_views) == 0 and np.all(lm.recent_views.rows(ids) < 0)


def _triangulate(rng, cameras_ned_m, point_ned_m, sigma_rad, height_sigma_m=3.0):
    """A landmark placed as the mapper places it: on the ground plane with a loose height from the first noisy ray,
    then every further noisy ray fused. Returns the map holding it (id 0)."""
    lm = LandmarkMap()
    for k, c in enumerate(cameras_ned_m):
        d = point_ned_m - c
        t = np.linalg.norm(d)
        d = d / t
        e = np.cross(d, rng.normal(size=3))  # a random direction across the ray
        d = d + sigma_rad * rng.normal() * e / np.linalg.norm(e) + sigma_rad * rng.normal() * np.cross(d, e / np.linalg.norm(e))
        d /= np.linalg.norm(d)
        sigma_perp = np.array([t * sigma_rad])
        A = ray_information(d[None], sigma_perp)
        bias = ray_bias_terms(d[None], np.array([t]), np.array([sigma_rad]), sigma_perp)
        if k == 0:
            A[:, 2, 2] += 1.0 / height_sigma_m**2
            p0 = c + d * (point_ned_m[2] - c[2]) / d[2]  # on the true ground plane
            lm.add(np.zeros((1, 32), np.uint8), p0[None], A, np.ones(1), ray_bias=bias)
        else:
            lm.observe(np.array([0]), A, np.einsum("nij,j->ni", A, c), np.zeros((1, 32), np.uint8), np.ones(1), np.zeros(1),
                       ray_bias=bias)
    return lm


def test_the_triangulation_bias_model_expects_what_noisy_rays_do_to_a_landmark_seen_from_a_short_baseline():
    """Eleven views over 9 m from 40 m, 3.8 mrad of noise on each ray: the fused point lies toward the cameras
    (up), and triangulation_bias_m expects about as much; over 40 m of baseline, neither is more than 3 cm."""
    rng = np.random.default_rng(3)
    point = np.array([0.0, 0.0, 0.0])
    for baseline_m, check in [(9.0, "short"), (40.0, "wide")]:
        cameras = np.column_stack([np.linspace(-baseline_m / 2, baseline_m / 2, 11), np.full(11, 3.0), np.full(11, -40.0)])
        err, expected = [], []
        for _ in range(400):
            lm = _triangulate(rng, cameras, point, 3.8e-3)
            err.append(lm.p_ned_m[0].astype(float) - point)
            expected.append(lm.triangulation_bias_m(np.array([0]))[0])
        err_d, expected_d = np.mean(err, axis=0)[2], np.mean(expected, axis=0)[2]
        if check == "short":
            assert err_d < -0.1  # too high: toward the cameras, by 0.2 m (tools/triangulation_bias.py)
            assert 0.6 < expected_d / err_d < 1.3, (expected_d, err_d)
        else:
            assert abs(err_d) < 0.03 and abs(expected_d) < 0.03, (expected_d, err_d)


def test_the_expected_bias_counts_in_the_variance_across_a_ray_and_only_across_it():
    rng = np.random.default_rng(4)
    cameras = np.column_stack([np.linspace(-4.5, 4.5, 11), np.zeros(11), np.full(11, -40.0)])
    lm = _triangulate(rng, cameras, np.zeros(3), 3.8e-3)
    ids = np.array([0])
    b = lm.triangulation_bias_m(ids)[0]
    along = b / np.linalg.norm(b)
    across = np.cross(along, [1.0, 0.0, 0.0])
    across /= np.linalg.norm(across)
    for d, grows_by in [(along, 0.0), (across, 0.5 * float(b @ b))]:
        var = lm.variance_across_rays_m2(ids, d[None], with_bias=False)[0]
        assert lm.variance_across_rays_m2(ids, d[None])[0] == pytest.approx(var + grows_by, rel=1e-6, abs=1e-12)


def test_a_heading_error_widens_a_landmark_beside_the_track_along_it_as_the_mapper_says():
    """A landmark 20 m beside a track at 40 m, seen from 11 cameras over 9 m, each ray off by 1 mrad of tilt and by
    a turn of 0.5 deg about the vertical through its camera (the telemetry's heading noise): the turn moves the
    ray's far end 17 cm along the track. The fused point's scatter along the track is what the information with
    the heading's part (ray_information's ``sigma_turn_m``) says, and several times what it says without."""
    rng = np.random.default_rng(8)
    point = np.array([0.0, 20.0, 0.0])
    cameras = np.column_stack([np.linspace(-4.5, 4.5, 11), np.zeros(11), np.full(11, -40.0)])
    s_tilt, s_heading = 1e-3, np.deg2rad(0.5)
    fused, covs = [], {}
    for _ in range(300):
        A_sum, b_sum = {"with": np.zeros((3, 3)), "without": np.zeros((3, 3))}, {"with": np.zeros(3), "without": np.zeros(3)}
        for c in cameras:
            v = point - c
            t = np.linalg.norm(v)
            turn = s_heading * rng.normal()
            Rz = np.array([[np.cos(turn), -np.sin(turn), 0.0], [np.sin(turn), np.cos(turn), 0.0], [0.0, 0.0, 1.0]])
            d = Rz @ (v / t)
            e1 = np.cross(d, [1.0, 0.0, 0.0])
            e1 /= np.linalg.norm(e1)
            d = d + s_tilt * (rng.normal() * e1 + rng.normal() * np.cross(d, e1))
            d /= np.linalg.norm(d)
            sigma_perp = np.array([t * s_tilt])
            for kind, turn_m in [("with", s_heading * t * np.hypot(d[0], d[1])), ("without", None)]:
                A = ray_information(d[None], sigma_perp, None if turn_m is None else np.array([turn_m]))[0]
                A_sum[kind] += A
                b_sum[kind] += A @ c
        fused.append(np.linalg.solve(A_sum["with"], b_sum["with"]))
        covs = {k: np.linalg.inv(A_sum[k]) for k in A_sum}
    var_north = np.var(np.array(fused)[:, 0])
    assert 0.7 < var_north / covs["with"][0, 0] < 1.4, (var_north, covs["with"][0, 0])
    assert var_north / covs["without"][0, 0] > 4.0, (var_north, covs["without"][0, 0])
