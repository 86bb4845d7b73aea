"""The landmark map's spatial index: it must return exactly what a scan of every landmark returns."""

import numpy as np
import pytest

from auxgps.core.landmarks import GridIndex, LandmarkMap


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
