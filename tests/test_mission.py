"""Mission files (QGC WPL 110 and QGroundControl .plan), the path a simulated multirotor flies for them, and a
mission flown through `auxgps eval --mission`."""

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from auxgps.core.geometry import LocalFrame
from auxgps.errors import ConfigError
from auxgps.io.mission import load_mission
from auxgps.sim.flight import VehicleConfig, fly, mission_waypoints_ned

REPO = Path(__file__).resolve().parent.parent
MISSION = REPO / "config" / "missions" / "cubes_out_and_back.waypoints"
FRAME = LocalFrame(47.397742, 8.545594, 488.0)


def lat_lon(north_m, east_m):
    lat, lon, _ = FRAME.to_geodetic(np.array([north_m, east_m, 0.0]))
    return float(lat), float(lon)


def wpl(tmp_path, *lines, header="QGC WPL 110"):
    path = tmp_path / "m.waypoints"
    path.write_text("\n".join([header, *("\t".join(str(v) for v in line) for line in lines)]) + "\n")
    return path


def test_a_waypoints_file_reads_with_home_apart_and_items_numbered_as_in_the_file(tmp_path):
    m = load_mission(MISSION)
    assert m.home == (47.397742, 8.545594, 488.0)
    assert [it.seq for it in m.items] == [1, 2, 3, 4, 5, 6]
    assert [it.name for it in m.items] == ["NAV_TAKEOFF"] + ["NAV_WAYPOINT"] * 4 + ["NAV_RETURN_TO_LAUNCH"]
    path, owner = mission_waypoints_ned(m, FRAME)
    np.testing.assert_allclose(path[1], [0, 0, -15])  # the take-off climbs where it is
    np.testing.assert_allclose(path[2], [-3.0, -10.0, -15.0], atol=0.06)
    np.testing.assert_allclose(path[-2:], [[0, 0, -15], [0, 0, 0]], atol=1e-9)  # home at the height it has, then down
    assert owner.tolist() == [-1, 1, 2, 3, 4, 5, 6, 6]


def test_heights_by_frame_a_forced_height_and_a_mission_that_does_not_come_home(tmp_path):
    (lat, lon), (lat2, lon2) = lat_lon(20.0, 5.0), lat_lon(20.0, 10.0)
    path = wpl(tmp_path,
               (0, 1, 0, 16, 0, 0, 0, 0, 47.397742, 8.545594, 488.0, 1),
               (1, 0, 3, 178, 0, 8, -1, 0, 0, 0, 0, 1),  # DO_CHANGE_SPEED: no place, skipped
               (2, 0, 0, 16, 0, 0, 0, 0, lat, lon, 528.0, 1),  # AMSL: 40 m above home
               (3, 0, 10, 16, 0, 0, 0, 0, lat2, lon2, 30.0, 1))  # terrain: 30 m above the flat ground
    m = load_mission(path)
    p, owner = mission_waypoints_ned(m, FRAME)
    # A waypoint before any take-off: ArduPilot takes off to it; climbed first here.
    np.testing.assert_allclose(p[1], [0, 0, -40.0], atol=1e-6)
    np.testing.assert_allclose(p[2], [20.0, 5.0, -40.0], atol=1e-3)
    np.testing.assert_allclose(p[3], [20.0, 10.0, -30.0], atol=1e-3)
    np.testing.assert_allclose(p[-2:], [[0, 0, -30.0], [0, 0, 0]], atol=1e-9)  # given a return and a landing
    assert owner.tolist() == [-1, 2, 2, 3, -1, -1]
    forced, _ = mission_waypoints_ned(m, FRAME, alt_m=60.0)
    assert np.all(forced[1:-1, 2] == -60.0)


def test_a_plan_file_with_a_survey_expands_its_items(tmp_path):
    def simple(cmd, lat=0.0, lon=0.0, alt=0.0, frame=3):
        return {"type": "SimpleItem", "command": cmd, "frame": frame, "params": [0, 0, 0, None, lat, lon, alt], "autoContinue": True}

    survey = {"type": "ComplexItem", "complexItemType": "survey",
              "TransectStyleComplexItem": {"Items": [simple(16, 47.3978, 8.5457, 50), simple(16, 47.3979, 8.5457, 50)]}}
    plan = {"fileType": "Plan", "version": 1,
            "mission": {"items": [simple(22, alt=50), survey, simple(178), simple(21, 47.3977, 8.5456)],
                        "plannedHomePosition": [47.397742, 8.545594, 488]}}
    path = tmp_path / "m.plan"
    path.write_text(json.dumps(plan))
    m = load_mission(path)
    assert [(it.seq, it.name) for it in m.items] == [(1, "NAV_TAKEOFF"), (2, "NAV_WAYPOINT"), (3, "NAV_WAYPOINT"),
                                                     (4, "DO_CHANGE_SPEED"), (5, "NAV_LAND")]
    assert m.home == (47.397742, 8.545594, 488.0)
    p, owner = mission_waypoints_ned(m, FRAME)
    assert p[-1, 2] == 0.0 and owner[-1] == 5  # lands where item 5 says


@pytest.mark.parametrize("make, says", [
    (lambda t: wpl(t, (0, 1, 0, 16, 0, 0, 0, 0, 1, 2, 3, 1), header="QGC WPL 999"), "Unsupported waypoint format"),
    (lambda t: wpl(t, (0, 1, 0, 16, 0, 0, 0, 0, 1, 2, 3, 1), (1, 0, 1, 16, 0, 0, 0, 0, 5, 5, 10, 1)), "frame 1"),
    (lambda t: wpl(t, (0, 1, 0, 16, 0, 0, 0, 0, 1, 2, 3, 1), (1, 0, 3, 16, 0, 0, 0, 0, 5, 5)), "has 12 values"),
    (lambda t: wpl(t, (0, 1, 0, 16, 0, 0, 0, 0, 1, 2, 3, 1), (1, 0, 3, 178, 0, 8, -1, 0, 0, 0, 0, 1)), "no item that goes"),
    (lambda t: (t / "m.plan").write_text("{not json") and t / "m.plan", "not a QGroundControl plan"),
    (lambda t: (t / "m.txt").write_text("hello") and t / "m.txt", "neither QGC WPL"),
    (lambda t: t / "missing.waypoints", "no such file"),
])
def test_bad_mission_files_are_refused_naming_the_file_and_what_is_wrong(tmp_path, make, says):
    path = make(tmp_path)
    with pytest.raises(ConfigError) as err:
        load_mission(path)
    assert str(path) in str(err.value) and says in str(err.value)


def test_a_mission_of_somewhere_else_is_refused(tmp_path):
    far = wpl(tmp_path, (0, 1, 0, 16, 0, 0, 0, 0, 46.8, -91.9, 158, 1), (1, 0, 3, 16, 0, 0, 0, 0, 46.8, -91.9, 40, 1))
    with pytest.raises(ConfigError, match="km from the world's origin"):
        mission_waypoints_ned(load_mission(far), FRAME)


def test_the_flight_says_when_it_reached_each_waypoint():
    path, _ = mission_waypoints_ned(load_mission(MISSION), FRAME)
    traj = fly(path, 2.0, VehicleConfig(gust_sigma_m_s2=0.0), np.random.default_rng(1))
    assert len(traj.reached_t_s) == len(path) and np.all(np.diff(traj.reached_t_s) > 0)
    for k in range(1, len(path)):
        i = traj.index_at(traj.reached_t_s[k])
        assert np.linalg.norm(traj.p_ned_m[i] - path[k]) <= VehicleConfig().waypoint_radius_m + 0.05


def test_eval_flies_a_mission_maps_on_the_way_out_and_scores_the_return(tmp_path):
    out = tmp_path / "mission.json"
    done = subprocess.run([sys.executable, "-m", "auxgps.cli", "eval", "--world", "cubes4_0.5m_different", "--altitude", "15",
                           "--mission", str(MISSION), "--speed-m-s", "2", "--gps-lost-at-waypoint", "3", "--quiet",
                           "--json", str(out)], cwd=REPO, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    figures = json.loads(out.read_text())
    assert figures["scenario"]["mission"] == {"path": str(MISSION), "speed_m_s": 2.0, "gps_lost_at_seq": 3, "maps": []}
    # Mapped on the way out (only there: the estimator maps only while GPS1 is good), positioned on the way back.
    assert figures["landmarks"]["count"] >= 10
    assert figures["denied_s"] > 20.0
    assert figures["fixes"]["count"] >= 20 and figures["fused"]["count"] > 100
    assert figures["fused"]["within_3sigma"] >= 0.97
    assert figures["gate"]["accepted_over_0_5m"] == 0
    assert any("GPS1 lost" in line for _, line in figures["notes"])


def test_eval_refuses_a_mission_without_the_item_gps1_is_lost_at(tmp_path):
    for extra, says in ((["--gps-lost-at-waypoint", "9"], "no mission item 9"), ([], "go together")):
        done = subprocess.run([sys.executable, "-m", "auxgps.cli", "eval", "--world", "cubes4_0.5m_different", "--altitude", "15",
                               "--mission", str(MISSION), *extra], cwd=REPO, capture_output=True, text=True, timeout=120)
        assert done.returncode != 0 and says in done.stderr and "Traceback" not in done.stderr, done.stderr


def test_the_sitl_tool_uploads_items_as_the_file_numbers_them_at_the_height_asked():
    sys.path.insert(0, str(REPO / "tools"))
    try:
        import sitl_flight
    finally:
        sys.path.remove(str(REPO / "tools"))
    M = sitl_flight.M
    m = load_mission(MISSION)
    items = sitl_flight.mission_items(m, (47.397742, 8.545594, 488.0), 40.0)
    assert [i.seq for i in items] == list(range(7)) and items[0].command == M.MAV_CMD_NAV_WAYPOINT  # 0: home
    assert [i.command for i in items[1:]] == [it.command for it in m.items]
    assert all(i.z == 40.0 and i.frame == M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT for i in items[1:-1])
    assert items[-1].command == M.MAV_CMD_NAV_RETURN_TO_LAUNCH and items[-1].z == 0.0
    assert (items[2].x, items[2].y) == (473977150, 85454610)
    own = sitl_flight.mission_items(m, (47.397742, 8.545594, 488.0), None)
    assert [i.z for i in own[1:-1]] == [15.0] * 5


def test_eval_crosses_a_featureless_lake_says_so_and_positions_again_after_it(tmp_path):
    """Out along a strip of blotchy ground at 15 m and 4 m/s, GPS1 lost at the far end, and back across an 80 m
    lake (about 16 s with no feature in view) to ground mapped on the way out. The mission flies its own heights
    (no --altitude)."""
    rng = np.random.default_rng(7)
    texture = sum(cv2.resize(rng.normal(0.0, 1.0, (1000 // k, 4800 // k)), (4800, 1000), interpolation=cv2.INTER_CUBIC)
                  for k in (1, 4, 16, 64))  # 240 m east-west by 50 m, 5 cm per pixel
    cv2.imwrite(str(tmp_path / "ground.png"), np.clip(128 + 40 * texture, 0, 255).astype(np.uint8))
    lake = [[-25.0, 10.0], [25.0, 10.0], [25.0, 90.0], [-25.0, 90.0]]  # north, east, m
    (tmp_path / "w.yaml").write_text(yaml.safe_dump({
        "origin": {"lat_deg": FRAME.lat_deg, "lon_deg": FRAME.lon_deg, "alt_amsl_m": FRAME.alt_amsl_m},
        "ground": {"texture": "ground.png", "m_per_px": 0.05},
        "patches": [{"name": "lake", "color": [70, 55, 45], "corners_m": lake}]}))
    west, east = lat_lon(0.0, -40.0), lat_lon(0.0, 100.0)
    mission = wpl(tmp_path, (0, 1, 0, 16, 0, 0, 0, 0, FRAME.lat_deg, FRAME.lon_deg, FRAME.alt_amsl_m, 1),
                  (1, 0, 3, 22, 0, 0, 0, 0, 0, 0, 15, 1), (2, 0, 3, 16, 0, 0, 0, 0, *west, 15, 1),
                  (3, 0, 3, 16, 0, 0, 0, 0, *east, 15, 1), (4, 0, 3, 16, 0, 0, 0, 0, *west, 15, 1),
                  (5, 0, 3, 21, 0, 0, 0, 0, 0, 0, 0, 1))
    out = tmp_path / "lake.json"
    done = subprocess.run([sys.executable, "-m", "auxgps.cli", "eval", "--world", str(tmp_path / "w.yaml"), "--mission", str(mission),
                           "--speed-m-s", "4", "--gps-lost-at-waypoint", "3", "--quiet", "--json", str(out)],
                          cwd=REPO, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    figures = json.loads(out.read_text())
    f = figures["featureless"]
    assert f is not None and f["crossings"] == 1 and f["seconds_over"] > 15.0
    assert f["accepted_fix_max_m"] is None or f["accepted_fix_max_m"] <= 0.02 * 15.0
    assert f["within_3_reported"] >= 0.97
    assert f["said_no_fix"] == 1 and f["no_fix_after_s"] < f["seconds_over"]  # GPS_INPUT said "no fix" over it
    assert f["fix_3d_again_s"] is not None and f["fix_3d_again_s"] < 5.0  # and a 3D fix came back with the texture
    said = [line for _, line in figures["notes"]]
    assert any(line.startswith("featureless ground: ") for line in said), said
    assert any(line.startswith("featureless ground over") for line in said), said
    assert figures["height_agl"]["max_m"] == pytest.approx(15.0, abs=0.5)
    assert figures["scenario"]["altitude_m"] is None
