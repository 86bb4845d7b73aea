"""tools/gps_consistency.py: pass grouping, placing a block on GPS, and a pass's offset found from the others.

The synthetic cases know the answer; the Brighton Beach run (slow, skipped without the photos) checks that the
real block is built and measured as the tool's report says.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import load_tool

REPO = Path(__file__).resolve().parent.parent
BRIGHTON = REPO.parent / "shared" / "data" / "brighton_beach" / "images"
CAMERA = REPO / "config" / "cameras" / "dji_fc300s.yaml"

gc = load_tool("gps_consistency")

atol_m = 1e-9


def serpentine(n_passes=3, per_pass=6, step_m=13.5, spacing_m=20.0, heading_deg=45.0) -> np.ndarray:
    """True camera positions (north, east, m) in capture order: parallel passes flown alternately both ways."""
    h = np.deg2rad(heading_deg)
    along, across = np.array([np.cos(h), np.sin(h)]), np.array([np.sin(h), -np.cos(h)])
    rows = []
    for k in range(n_passes):
        s = np.arange(per_pass) * step_m
        if k % 2:
            s = s[::-1]
        rows.append(s[:, None] * along + k * spacing_m * across)
    return np.vstack(rows)


def as_block(true_ne_m: np.ndarray) -> np.ndarray:
    """What photogrammetry gives without GPS: the true geometry at some other scale, rotation and place."""
    return gc.Similarity2D(0.87, np.deg2rad(25.0), np.array([40.0, -7.0])).apply(true_ne_m)


def test_similarity_fit_recovers_a_known_transform():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(10, 2)) * 30
    sim = gc.Similarity2D(1.3, -0.4, np.array([2.0, -5.0]))
    fit = gc.fit_similarity_2d(src, sim.apply(src))
    assert fit.scale == pytest.approx(1.3, abs=1e-12)
    assert fit.rotation_rad == pytest.approx(-0.4, abs=1e-12)
    np.testing.assert_allclose(fit.t_ne_m, [2.0, -5.0], atol=atol_m)


def test_passes_split_at_the_turns():
    true = serpentine()
    assert gc.group_passes(true) == [list(range(0, 6)), list(range(6, 12)), list(range(12, 18))]
    # GPS noise of decimetres does not split a pass
    noisy = true + np.random.default_rng(2).normal(scale=0.3, size=true.shape)
    assert gc.group_passes(noisy) == [list(range(0, 6)), list(range(6, 12)), list(range(12, 18))]


@pytest.mark.parametrize("middle_gps_offset_ne_m", [(0.0, 0.0), (-1.2, 0.4)])
def test_a_pass_offset_is_found_from_the_other_passes(middle_gps_offset_ne_m):
    true = serpentine()
    rng = np.random.default_rng(3)
    gps = true + rng.normal(scale=0.05, size=true.shape)
    gps[6:12] += middle_gps_offset_ne_m  # the middle pass's receiver is off by this
    block = as_block(true)
    passes = gc.group_passes(gps)
    placed = gc.place_block(block, gps, passes[0] + passes[2])
    mean_middle = placed.offset_ne_m[6:12].mean(axis=0)
    # solved minus GPS: the block puts the middle pass opposite its GPS's offset
    np.testing.assert_allclose(mean_middle, -np.array(middle_gps_offset_ne_m), atol=0.1)
    everyone = gc.pass_offsets(gc.place_block(block, gps, list(range(18))).offset_ne_m, gps, passes)
    middle_vs_outer = everyone[1].mean_offset_ne_m - (everyone[0].mean_offset_ne_m + everyone[2].mean_offset_ne_m) / 2
    np.testing.assert_allclose(middle_vs_outer, -np.array(middle_gps_offset_ne_m), atol=0.1)
    assert all(po.spread_rms_m < 0.15 for po in everyone)


def test_along_and_across_a_heading():
    a, c = gc.along_cross(np.array([0.0, 1.0]), 90.0)  # 1 m east, flying east
    assert (a, c) == pytest.approx((1.0, 0.0), abs=1e-12)
    a, c = gc.along_cross(np.array([-1.0, 0.0]), 90.0)  # 1 m south, flying east: to the right
    assert (a, c) == pytest.approx((0.0, 1.0), abs=1e-12)


@pytest.mark.measurement
@pytest.mark.skipif(not BRIGHTON.is_dir(), reason=f"Brighton Beach photos not found at {BRIGHTON}")
def test_brighton_block(tmp_path):
    """All 18 photos in one block with a 100 m GPS prior (about 2 min on one core): the figures of
    docs/photos.md, re-run on demand with ``pytest -m measurement`` (the tool's logic is tested above)."""
    out = tmp_path / "gps.json"
    assert gc.main(["--images", str(BRIGHTON), "--camera", str(CAMERA), "--json", str(out)]) == 0
    r = json.loads(out.read_text())
    assert [len(p) for p in r["passes"]] == [6, 6, 6]
    assert r["passes"][1][0] == "DJI_0024.JPG"
    assert max(r["block"]["rms_px"]) < 1.5  # the images agree with one geometry to about a pixel
    assert abs(r["block"]["similarity"]["rotation_deg"]) < 1.0
    # Measured (focal length held within 2 %): the block placed on the outer passes puts the middle pass 0.78 m
    # south (and 0.23 m east) of its own GPS, each photo within 1.15 m of it; after one shift per pass, each pass's
    # photos agree with their GPS to 0.23-0.32 m.
    middle = next(h for h in r["leave_one_pass_out"] if h["pass"] == 2)
    assert middle["mean_offset_ne_m"][0] < -0.3
    assert middle["max_dist_m"] < 1.5
    assert r["all_gps"]["within_pass_rms_m"] < 0.5


def test_hold_out_bare_needs_a_pass_to_hold_out():
    with pytest.raises(SystemExit):
        gc.main(["--images", str(BRIGHTON), "--hold-out-bare"])
