"""Map files: round trip, atomic writes, and one clear error for every way a file can be bad."""

import json

import numpy as np
import pytest

from auxgps.core.geometry import LocalFrame
from auxgps.core.landmarks import LandmarkMap
from auxgps.errors import MapError
from auxgps.io.map_file import load_map, save_map, saved_heading

FRAME = LocalFrame(47.397742, 8.545594, 488.0)


def some_map(n=50, seed=0):
    rng = np.random.default_rng(seed)
    lm = LandmarkMap(capacity=8)
    lm.add(rng.integers(0, 256, (n, 32), dtype=np.uint8), rng.normal(0, 5, (n, 3)), np.repeat(np.eye(3)[None] * 100.0, n, 0), np.ones(n),
           rng.uniform(5.0, 20.0, n))
    lm.n_seen[:n] = rng.integers(1, 100, n)
    return lm


def test_round_trip(tmp_path):
    lm = some_map()
    save_map(tmp_path / "m.npz", lm, FRAME)
    back, frame = load_map(tmp_path / "m.npz")
    assert frame == FRAME and len(back) == len(lm)
    for name in LandmarkMap.COLUMNS:
        assert np.array_equal(getattr(back, name)[: len(lm)], getattr(lm, name)[: len(lm)])
    back.add(np.zeros((1, 32), np.uint8), np.zeros((1, 3)), np.eye(3)[None], np.ones(1))  # still growable
    assert len(back) == len(lm) + 1


def test_a_checkpoint_keeps_the_heading_error_its_flight_had_solved(tmp_path):
    heading = {"offset_rad": 0.031, "sigma_rad": 0.004, "unix_s": 1_800_000_000.0}
    save_map(tmp_path / "h.npz", some_map(), FRAME, heading=heading)
    assert saved_heading(tmp_path / "h.npz") == heading
    save_map(tmp_path / "none.npz", some_map(), FRAME)
    assert saved_heading(tmp_path / "none.npz") is None  # a map without it: the heading is learnt afresh
    save_map(tmp_path / "bad.npz", some_map(), FRAME, heading={"offset_rad": "north-ish"})
    assert saved_heading(tmp_path / "bad.npz") is None


def _older_file(tmp_path, lm, version: int, lacking: str):
    """``lm`` saved as a map file of an older ``version``, without the column it did not have yet."""
    save_map(tmp_path / "m.npz", lm, FRAME)
    with np.load(tmp_path / "m.npz") as data:
        arrays = {k: data[k] for k in data.files if k != lacking}
    meta = json.loads(str(arrays.pop("meta")))
    meta["version"] = version
    path = tmp_path / f"v{version}.npz"
    np.savez(path, meta=np.array(json.dumps(meta)), **arrays)
    return path


def test_version_2_file_is_read_with_unknown_descriptor_ranges(tmp_path):
    lm = some_map()
    back, _ = load_map(_older_file(tmp_path, lm, 2, "descriptor_range_m"))
    assert np.array_equal(back.p_ned_m[: len(lm)], lm.p_ned_m[: len(lm)])
    assert np.all(np.isnan(back.descriptor_range_m[: len(lm)]))


def test_the_expected_bias_sums_are_saved_and_an_older_file_expects_none(tmp_path):
    lm = some_map()
    n = len(lm)
    lm.ray_bias_sum[:n] = np.random.default_rng(2).normal(size=(n, 3))
    save_map(tmp_path / "m.npz", lm, FRAME)
    back, _ = load_map(tmp_path / "m.npz")
    assert np.array_equal(back.ray_bias_sum[:n], lm.ray_bias_sum[:n])
    old, _ = load_map(_older_file(tmp_path, lm, 4, "ray_bias_sum"))
    assert np.array_equal(old.p_ned_m[:n], lm.p_ned_m[:n]) and not np.any(old.ray_bias_sum[:n])


def test_truncated_file_is_one_clear_error(tmp_path):
    save_map(tmp_path / "m.npz", some_map(), FRAME)
    data = (tmp_path / "m.npz").read_bytes()
    for cut in (10, len(data) // 2, len(data) - 20):
        (tmp_path / "cut.npz").write_bytes(data[:cut])
        with pytest.raises(MapError, match="unreadable or truncated"):
            load_map(tmp_path / "cut.npz")


def test_missing_and_foreign_files(tmp_path):
    with pytest.raises(MapError, match="no such map file"):
        load_map(tmp_path / "absent.npz")
    (tmp_path / "text.npz").write_text("not a map")
    with pytest.raises(MapError):
        load_map(tmp_path / "text.npz")
    np.savez(tmp_path / "other.npz", meta=np.array('{"format": "auxgps-map", "version": 99, "count": 0}'))
    with pytest.raises(MapError, match="version 99"):
        load_map(tmp_path / "other.npz")


def test_failed_write_keeps_the_old_map(tmp_path, monkeypatch):
    target = tmp_path / "m.npz"
    save_map(target, some_map(seed=1), FRAME)
    before = target.read_bytes()

    def boom(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(np, "savez", boom)
    with pytest.raises(OSError):
        save_map(target, some_map(seed=2), FRAME)
    assert target.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["m.npz"]  # no temporary left behind


class _CutAfter:
    """A file that dies after ``limit`` bytes, as a process killed in the middle of a write."""

    def __init__(self, f, limit: int) -> None:
        self._f, self._left = f, limit

    def write(self, data) -> int:
        data = bytes(data)
        if len(data) > self._left:
            self._f.write(data[: self._left])
            self._f.flush()
            raise KeyboardInterrupt("killed mid-write")
        self._left -= len(data)
        return self._f.write(data)

    def __getattr__(self, name):
        return getattr(self._f, name)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self._f.close()


def test_a_checkpoint_cut_at_any_byte_leaves_the_previous_map_intact(tmp_path, monkeypatch):
    from auxgps.io import map_file

    target = tmp_path / "m.npz"
    old, new = some_map(n=12, seed=1), some_map(n=15, seed=2)
    save_map(target, old, FRAME)
    before = target.read_bytes()
    save_map(tmp_path / "new.npz", new, FRAME)
    size = (tmp_path / "new.npz").stat().st_size
    real_fdopen = map_file.os.fdopen
    for limit in range(size):
        monkeypatch.setattr(map_file.os, "fdopen", lambda fd, mode, _l=limit: _CutAfter(real_fdopen(fd, mode), _l))
        with pytest.raises(KeyboardInterrupt):
            save_map(target, new, FRAME)
        assert target.read_bytes() == before, f"cut at byte {limit}"
    monkeypatch.setattr(map_file.os, "fdopen", real_fdopen)
    back, _ = load_map(target)
    assert np.array_equal(back.p_ned_m[: len(back)], old.p_ned_m[: len(old)])


def test_a_temporary_left_by_a_killed_writer_is_ignored_then_cleared(tmp_path):
    target = tmp_path / "m.npz"
    save_map(target, some_map(n=12, seed=1), FRAME)
    save_map(tmp_path / "new.npz", some_map(n=15, seed=2), FRAME)
    (tmp_path / "m.npz.abc123.tmp").write_bytes((tmp_path / "new.npz").read_bytes()[:500])  # kill -9 mid-write
    assert len(load_map(target)[0]) == 12
    save_map(target, some_map(n=15, seed=2), FRAME)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.npz", "new.npz"]
    assert len(load_map(target)[0]) == 15


def test_a_map_cut_at_any_byte_is_one_clear_error(tmp_path):
    save_map(tmp_path / "m.npz", some_map(n=12), FRAME)
    data = (tmp_path / "m.npz").read_bytes()
    for cut in range(len(data)):
        (tmp_path / "cut.npz").write_bytes(data[:cut])
        with pytest.raises(MapError):
            load_map(tmp_path / "cut.npz")
