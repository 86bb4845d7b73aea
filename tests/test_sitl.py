"""The closed loop on ArduPilot's own copter SITL: found through ARDUPILOT_SITL, skipped without it."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import load_tool

REPO = Path(__file__).resolve().parent.parent
SITL = os.environ.get("ARDUPILOT_SITL")


needs_sitl = pytest.mark.skipif(not SITL or not Path(SITL).exists(), reason="set ARDUPILOT_SITL to an ArduCopter SITL binary to fly the real autopilot")


@pytest.fixture(scope="module")
def sitl_flight(tmp_path_factory):
    """The closed loop flown on SITL by tools/sitl_flight.py; then its recording's replay, started in the background
    (a replay keeps no clock: it runs beside test_check_is_green_on_sitl..., whose SITL mostly waits, and
    test_the_sitl_flight_replays... waits for it). Yields the flight's folder, the replay and the time it hides
    GPS1 from."""
    import csv

    from auxgps.io.recording import open_recording

    flight = tmp_path_factory.mktemp("sitl_flight")
    proc = subprocess.run([sys.executable, str(REPO / "tools" / "sitl_flight.py"), "--sitl", SITL, "--out", str(flight)],
                          capture_output=True, text=True, timeout=1500, cwd=REPO)
    (flight / "tool.stderr").write_text(proc.stderr)
    replay = deny_after_s = None
    if (flight / "rec" / "recording.json").exists() and (flight / "truth.csv").exists():
        # GPS1 hidden from 60 s before the flight's own failure.
        first_s = next(open_recording(flight / "rec").messages())[1]
        failed_s = next((float(r["t_s"]) for r in csv.DictReader(open(flight / "truth.csv")) if r["gps1_failed"] == "1"), None)
        if failed_s is not None:
            deny_after_s = round(failed_s - first_s - 60.0, 1)
            replay = subprocess.Popen(
                [sys.executable, "-m", "auxgps.cli", "replay", str(flight / "rec"), "--deny-gps-after", str(deny_after_s),
                 "--out", str(flight / "denied"), "--json", str(flight / "denied.json"), "--report", str(flight / "denied.png")],
                cwd=REPO, stdout=open(flight / "replay.stdout", "w"), stderr=open(flight / "replay.stderr", "w"))
    try:
        yield flight, replay, deny_after_s
    finally:
        if replay is not None and replay.poll() is None:
            replay.kill()
            replay.wait(timeout=20)


@pytest.mark.sitl
@needs_sitl
def test_sitl_flies_home_on_auxgps_through_a_gps1_failure(sitl_flight):
    flight, _, _ = sitl_flight
    result = json.loads((flight / "result.json").read_text())
    print(json.dumps(result))
    assert result["landed"] and result["landing_error_m"] <= 1.0, (flight / "tool.stderr").read_text()[-2000:]
    assert 3 in result["gps2_fix_types_seen"]  # the autopilot's GPS2 carried auxgps's 3D fix while GPS1 was down
    assert result["denied_s"] >= 180  # the closed loop: GPS1 down for at least 3 minutes
    assert len((flight / "truth.csv").read_text().splitlines()) > 1000  # the truth track, to score it again


atol_replay_m = 1e-3  # 1 mm: the replay is the flight's own computation


def test_lag_correlation_known_answers():
    """Errors made of a constant shared part and fresh per-frame noise of equal variance correlate 0.5 at every lag;
    fresh noise alone does not correlate; a lag with no pair inside the tolerance gives None."""
    sf = load_tool("sitl_flight")
    rng = np.random.default_rng(3)
    t = np.arange(0.0, 600.0, 0.1)
    shared = np.repeat(rng.standard_normal((len(t) // 100, 2)), 100, axis=0)  # constant over 10 s blocks
    fresh = rng.standard_normal((len(t), 2))
    corr = sf.lag_correlation(t, shared + fresh, lags_s=(0.1, 1.0))
    assert corr["0.1s"] == pytest.approx([0.5, 0.5], abs=0.05) and corr["1s"] == pytest.approx([0.45, 0.45], abs=0.05)
    assert sf.lag_correlation(t, fresh, lags_s=(0.1,))["0.1s"] == pytest.approx([0.0, 0.0], abs=0.05)
    assert sf.lag_correlation(t, fresh, lags_s=(0.05,), tol_s=0.01)["0.05s"] is None


def start_sitl(scratch: Path, log: Path) -> subprocess.Popen:
    """ArduCopter SITL with copter.parm and the project's parameter file, home at the demo world's origin."""
    from auxgps.sim.world import load_world

    origin = load_world(REPO / "config" / "worlds" / "cubes4_0.5m_different.yaml").frame
    defaults = f"{Path(SITL).parent / 'copter.parm'},{REPO / 'config' / 'ardupilot' / 'auxgps-gps2.parm'}"
    return subprocess.Popen([SITL, "--model", "quad", "--speedup", "1", "-I0", "--defaults", defaults,
                             "--home", f"{origin.lat_deg},{origin.lon_deg},{origin.alt_amsl_m},0"],
                            cwd=scratch, stdout=open(log, "w"), stderr=subprocess.STDOUT)


def check(*args: str) -> subprocess.CompletedProcess:
    p = subprocess.run([sys.executable, "-m", "auxgps.cli", "check", "--connect", "tcp:127.0.0.1:5760", "--timeout", "30", *args],
                       cwd=REPO, capture_output=True, text=True, timeout=180)
    print(p.stdout, p.stderr[-1500:])
    return p


def check_until_green(within_s: float) -> subprocess.CompletedProcess:
    """SITL takes about 40 s from start until GPS1 and the EKF are ready: check until all green, or time out."""
    import time

    deadline = time.monotonic() + within_s
    while True:
        p = check()
        if p.returncode == 0 or time.monotonic() > deadline:
            return p
        time.sleep(5)


@pytest.mark.sitl
@needs_sitl
def test_check_is_green_on_sitl_names_what_is_wrong_and_fixes_it(tmp_path):
    import os

    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink import mavutil

    sitl = start_sitl(tmp_path, tmp_path / "sitl.log")
    try:
        green = check_until_green(120)
        assert green.returncode == 0 and "all green" in green.stdout
        assert "ArduPilot 4." in green.stdout
        gcs = mavutil.mavlink_connection("tcp:127.0.0.1:5760", source_system=255)
        gcs.wait_heartbeat(timeout=30)
        for name, value in ((b"GPS2_TYPE", 0), (b"GPS2_DELAY_MS", 50)):
            gcs.mav.param_set_send(1, 1, name, value, mavutil.mavlink.MAV_PARAM_TYPE_REAL32)
            gcs.recv_match(type="PARAM_VALUE", blocking=True, timeout=5)
        gcs.close()
        wrong = check()
        assert wrong.returncode == 1
        bad = [line for line in wrong.stdout.splitlines() if line.strip().startswith("BAD")]
        assert any("GPS2_TYPE = 0, want 14" in line for line in bad) and any("GPS2_DELAY_MS = 50, want 100" in line for line in bad)
        fixed = check("--fix", "--yes", "--reboot")
        assert fixed.returncode == 0 and "reboot asked for" in fixed.stdout
        after = check_until_green(120)
        assert after.returncode == 0 and "all green" in after.stdout
    finally:
        sitl.terminate()
        sitl.wait(timeout=20)


@pytest.mark.sitl
@needs_sitl
def test_the_sitl_flight_replays_as_flown_then_scores_the_hidden_gps1(sitl_flight):
    """The flight's recording replayed with GPS1 hidden from 60 s before the flight's own failure: until then the
    same GPS_INPUT as flown (fix types, positions within 1 mm: the replay is the flight's own computation); from
    then on scored against the GPS1 it hid and against SITL's truth. (One replay for both; a whole flight replayed
    to the last output is tests/test_closed_loop.py's, on the emulator.)"""
    import csv

    from auxgps.core.geometry import LocalFrame
    from auxgps.io.recording import open_recording

    flight, replay, deny_after_s = sitl_flight
    assert replay is not None, f"the flight left no recording and truth to replay: {sorted(p.name for p in flight.iterdir())}"
    rc = replay.wait(timeout=1200)
    stdout, stderr = (flight / "replay.stdout").read_text(), (flight / "replay.stderr").read_text()
    print(stdout)
    print(stderr[-3000:])
    assert rc == 0 and "Traceback" not in stderr
    first_s = next(open_recording(flight / "rec").messages())[1]
    flown = list(csv.DictReader(open(flight / "run" / "gps_input.csv")))
    replayed = list(csv.DictReader(open(flight / "denied" / "gps_input.csv")))
    assert len(replayed) == len(flown) > 1000
    # Outputs asked for before GPS1 was hidden (a second's margin) have seen nothing of the hiding.
    before = [k for k, r in enumerate(flown) if float(r["t_s"]) < first_s + deny_after_s - 1.0]
    assert len(before) > 500
    assert [replayed[k]["fix_type"] for k in before] == [flown[k]["fix_type"] for k in before]
    frame = LocalFrame(float(flown[0]["lat_deg"]), float(flown[0]["lon_deg"]), 0.0)

    def ne(rows):
        return frame.to_ned(lat_deg=np.array([float(r["lat_deg"]) for r in rows]), lon_deg=np.array([float(r["lon_deg"]) for r in rows]),
                            alt_amsl_m=np.zeros(len(rows)))[:, :2]

    worst = float(np.max(np.linalg.norm(ne([flown[k] for k in before]) - ne([replayed[k] for k in before]), axis=1)))
    print(json.dumps({"replay": {"gps_input_compared": len(before), "max_position_difference_m": worst}}))
    assert worst <= atol_replay_m
    score = json.loads((flight / "denied.json").read_text())["score"]
    print(json.dumps({"denied_replay": score}))
    assert score["scored"] and score["gps1"]["seconds_compared"] >= 50
    assert score["gps1"]["rms_m"] < 1.0 and score["truth"]["rms_m"] < 1.0
