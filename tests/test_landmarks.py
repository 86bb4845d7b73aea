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
