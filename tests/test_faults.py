"""Faults a real flight brings: a fault campaign through `auxgps eval`, and the vehicle emulator flown with
`auxgps run` as a separate process (a minute to minutes each: marked ``flight``, run by .ci/run after make test)."""

import csv
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from auxgps.io.map_file import load_map
from tests.conftest import free_port
from tests.test_closed_loop import start_emulator  # the same port and log options

REPO = Path(__file__).resolve().parent.parent
# The closed loop's cubes with a landing pad at home: these flights are about their faults, and without the pad the
# last 4.6 m of every descent are flown on the IMU alone (bare grey ground), landing 0.4 to 1.2 m from home by the
# draw of its noise (docs/faults.md).
WORLD = str(REPO / "config" / "worlds" / "cubes4_0.5m_different_pad.yaml")
GPS_TIMEOUT_S = 4.0  # AP_GPS: an instance with no message for this long is timed out


def start_run(port: int, log_dir: Path, *options: str) -> subprocess.Popen:
    log_dir.mkdir(parents=True, exist_ok=True)
    return subprocess.Popen(
        [sys.executable, "-m", "auxgps.cli", "run", "--connect", f"tcp:127.0.0.1:{port}", "--camera", f"sim:{WORLD}",
         "--log-dir", str(log_dir), *options],
        stdout=subprocess.DEVNULL, stderr=open(log_dir / "run.log", "w"), cwd=REPO,
    )


def wait_for(predicate, timeout_s: float, what: str) -> None:
    t_end = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > t_end:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.2)


def events_say(log_dir: Path, text: str) -> bool:
    path = log_dir / "events.csv"
    return path.exists() and text in path.read_text()


def fly_emulator(tmp_path: Path, emulator_args: list[str], run_args: list[str]) -> dict:
    """The emulator's flight with `auxgps run` beside it (logs in tmp_path/run); both stopped whatever happens.
    Returns the emulator's log."""
    port = free_port()
    emu = run = None
    try:
        emu = start_emulator(port, tmp_path / "emu.json", *emulator_args, world=WORLD)
        run = start_run(port, tmp_path / "run", *run_args)
        emu.wait(timeout=600)
    finally:
        for p in (emu, run):
            if p is not None and p.poll() is None:
                p.terminate()
        for p in (emu, run):
            if p is not None:
                p.wait(timeout=20)
    return json.loads((tmp_path / "emu.json").read_text())


def longest_without_gps2_fix_s(samples: list[dict], after_t_s: float) -> float:
    """The longest stretch after ``after_t_s`` in which GPS2 was unhealthy or had no 3D fix, emulated s."""
    longest, start = 0.0, None
    for s in samples:
        if s["t_s"] < after_t_s:
            continue
        good = s["gps2_healthy"] and s["gps2_fix"] >= 3
        if not good and start is None:
            start = s["t_s"]
        elif good and start is not None:
            longest, start = max(longest, s["t_s"] - start), None
    if start is not None:
        longest = max(longest, samples[-1]["t_s"] - start)
    return longest


@pytest.mark.flight
def test_kill_9_mid_flight_restarts_from_the_checkpoint_and_lands_home(tmp_path):
    """`kill -9` of auxgps 60 s into the GPS-denied part; restarted 1 s later with the checkpointed map and no
    GPS1: it acquires without a prior, GPS2 is back with a 3D fix before ArduPilot's timeout, and the vehicle lands
    home on it."""
    port = free_port()
    emu = start_emulator(port, tmp_path / "emu.json", "--survey-size", "12", "--fail-gps1-at", "20", "--max-seconds", "600", world=WORLD)
    ckpt = tmp_path / "map.npz"
    first = second = None
    try:
        first = start_run(port, tmp_path / "run1", "--save-map", str(ckpt), "--checkpoint", "5")
        wait_for(lambda: events_say(tmp_path / "run1", "GPS1 lost"), 180, "GPS1 lost in the first run's events")
        time.sleep(60.0)
        assert emu.poll() is None, "the flight ended before the kill: make the survey longer"
        first.kill()  # SIGKILL: no handler runs, nothing is saved at the end
        first.wait(timeout=10)
        t_killed = time.monotonic()
        lm, _ = load_map(ckpt)  # the last checkpoint, whole
        n_checkpointed = len(lm)
        time.sleep(max(0.0, 1.0 - (time.monotonic() - t_killed)))
        second = start_run(port, tmp_path / "run2", "--map", str(ckpt), "--save-map", str(ckpt), "--checkpoint", "5")
        emu.wait(timeout=600)
    finally:
        for p in (emu, first, second):
            if p is not None and p.poll() is None:
                p.terminate()
        for p in (emu, first, second):
            if p is not None:
                p.wait(timeout=20)
    log = json.loads((tmp_path / "emu.json").read_text())
    run2_log = (tmp_path / "run2" / "run.log").read_text()
    assert log["exit_reason"] == "landed", run2_log[-2000:]
    assert n_checkpointed > 50
    outage_s = longest_without_gps2_fix_s(log["samples"], log["failure_t_s"] + 1.0)
    print(f"checkpoint {n_checkpointed} landmarks; GPS2 without a healthy 3D fix for {outage_s:.1f} s at most after the "
          f"failure; landed {log['landing_error_m']:.2f} m from home")
    assert outage_s < GPS_TIMEOUT_S
    assert log["landing_error_m"] <= 1.0
    assert not any(e["event"] == "failsafe" for e in log["events"])
    with open(tmp_path / "run2" / "fixes.csv") as f:
        reasons = [row["reason"] for row in csv.DictReader(f)]
    assert any(r.startswith("acquired without a prior") for r in reasons), reasons[:20]
    assert "Traceback" not in run2_log


def test_each_injected_fault_is_named_once_and_never_becomes_a_confident_wrong_fix(tmp_path):
    """config/faults/all.yaml on a cube world at 2 frames a second. Frozen and blurred frames over featureless
    ground are alike anyway (nothing to judge them by, nothing to fix on): those two are shown on the textured
    world in docs/faults.md and by tests/test_frame_check.py and tests/test_estimator.py. A height stuck in level
    flight is a steady height (the autopilot's EKF holds one to the millimetre): survived, not named."""
    out = tmp_path / "faults.json"
    subprocess.run([sys.executable, "-m", "auxgps.cli", "eval", "--world", "cubes4_0.5m_different", "--altitude", "15",
                    "--faults", str(REPO / "config" / "faults" / "all.yaml"), "--quiet", "--json", str(out)],
                   cwd=REPO, check=True, capture_output=True, timeout=600)
    figures = json.loads(out.read_text())
    lines = [line for _, line in figures["notes"]]
    for starts in ("camera fault: image 50% black", "camera fault: image 50% saturated", "camera frame rate fell",
                   "attitude stream stopped", "duplicated telemetry",
                   "telemetry out of time order"):
        assert sum(line.startswith(starts) or f"; {starts}" in line for line in lines) == 1, (starts, lines)
    assert figures["gate"]["accepted_over_0_5m"] == 0
    assert figures["fused"]["within_3sigma"] >= 0.97


def test_a_slow_drag_found_late_is_undone_from_the_map(tmp_path):
    """GPS1 dragged at 0.2 m/s during the survey is found only once its drift from the older map reaches
    drag_m (0.5 m), seconds after it began; meanwhile it has refined landmarks already mapped and geotagged new ones.
    The map goes back to what it was at the last agreeing self-check (which allowed drag_m / 2): no landmark keeps
    more of the drag than that, beside its own error (at most 0.17 m on this world without a drag). Before the
    undo, landmarks were left 0.52 m off and a fix 0.68 m off was accepted."""
    faults = tmp_path / "drag.yaml"
    faults.write_text("faults:\n  - {kind: gps1_drag, flight: mapping, at_s: 30, for_s: 400, speed_m_s: 0.2, bearing_deg: 45}\n")
    out = tmp_path / "drag.json"
    subprocess.run([sys.executable, "-m", "auxgps.cli", "eval", "--world", "cubes4_0.5m_different", "--altitude", "15",
                    "--faults", str(faults), "--quiet", "--json", str(out)], cwd=REPO, check=True, capture_output=True, timeout=600)
    figures = json.loads(out.read_text())
    lines = [line for _, line in figures["notes"]]
    found = [line for line in lines if "GPS1 drifts" in line and "undone" in line]
    assert found and "put back" in found[0], lines
    drag_m = 0.5
    assert figures["landmarks"]["max_m"] <= drag_m / 2 + 0.2, figures["landmarks"]
    assert figures["gate"]["accepted_over_0_5m"] == 0
    assert figures["fused"]["within_3sigma"] >= 0.97


def gps2_error_m(samples: list[dict], after_t_s: float, lag_s: float = 0.1) -> np.ndarray:
    """GPS2's horizontal distance from the truth ``lag_s`` before (GPS_INPUT describes the vehicle 0.1 s ago), at
    each log sample after ``after_t_s`` with a GPS2 reading, m."""
    t = np.array([s["t_s"] for s in samples])
    truth = np.array([s["truth_ned_m"][:2] for s in samples])
    out = []
    for s in samples:
        if s["t_s"] >= after_t_s and s["gps2_ned_m"] is not None and s["gps2_fix"] >= 3:
            then = np.array([np.interp(s["t_s"] - lag_s, t, truth[:, i]) for i in (0, 1)])
            out.append(float(np.hypot(*(np.array(s["gps2_ned_m"][:2]) - then))))
    return np.array(out)


@pytest.mark.flight
@pytest.mark.parametrize("speed_m_s, take_primary", [(0.5, True), pytest.param(0.2, False, marks=pytest.mark.flight_extra),
                                                     pytest.param(0.5, False, marks=pytest.mark.flight_extra),
                                                     pytest.param(1.0, False, marks=pytest.mark.flight_extra)])
def test_a_gps1_dragged_while_mapping_is_found_mapping_stops_and_the_vehicle_lands_home(tmp_path, speed_m_s, take_primary):
    """The emulator drags GPS1 away at ``speed_m_s`` (bearing 45 deg) from 30 s after take-off for 10 s, then holds
    the offset. auxgps must find the drag within 10 s, map nothing after it (so no landmark has more drag in it than
    the filter had then), and position from the map: GPS2 as accurate as usual. The vehicle lands home on GPS2:
    after GPS1 fails at 60 s, or, with --take-primary-on-drift and GPS1 never failing, because auxgps makes GPS2
    the primary (by itself the autopilot would keep the dragged GPS1, which reports a 3D fix, and land where it
    says home is)."""
    faults = tmp_path / "drag.yaml"
    faults.write_text(f"faults:\n  - {{kind: gps1_drag, flight: mapping, at_s: 30, for_s: 10, speed_m_s: {speed_m_s}, bearing_deg: 45}}\n")
    failure = [] if take_primary else ["--fail-gps1-at", "60"]
    log = fly_emulator(tmp_path, ["--survey-size", "8", *failure, "--faults", str(faults), "--max-seconds", "600"],
                       ["--take-primary-on-drift"] if take_primary else [])
    run_log = (tmp_path / "run" / "run.log").read_text() if (tmp_path / "run" / "run.log").exists() else ""
    assert log["exit_reason"] == "landed", run_log[-2000:]
    takeoff_t_s = next(e["t_s"] for e in log["events"] if e["event"] == "takeoff")
    drag_t_s = takeoff_t_s + 30.0
    with open(tmp_path / "run" / "events.csv") as f:
        events = [(float(r["autopilot_boot_s"]), r["text"]) for r in csv.DictReader(f) if r["autopilot_boot_s"]]
    found = [t for t, text in events if text.startswith(("GPS1 drifts", "GPS1 off track"))]
    assert found, events
    detected_after_s = found[0] - drag_t_s
    mapping_after = [t for t, text in events if t > found[0] and "auxgps: mapping" in text]
    # Landmarks are geotagged at the filter's position, which GPS_INPUT reports: GPS2's error from the drag's start
    # to its finding is the most drag any landmark can have in it (mapping stops as it is found).
    in_map = gps2_error_m([s for s in log["samples"] if s["t_s"] <= found[0]], drag_t_s)
    # "From the map" ends with the last accepted visual fix: the last 3 to 4 s of the descent onto the pad are dead
    # reckoning (its shapes leave the view; without the pad, the last 9 to 12 s from 4.6 m: docs/faults.md). There
    # GPS2 must be as honest as everywhere: inside the accuracy it reports.
    last_fix_t_s = last_accepted_fix_t_s(tmp_path / "run", log)
    err = gps2_error_m([s for s in log["samples"] if s["t_s"] <= last_fix_t_s], found[0] + 2.0)
    out_err, out_acc = gps_input_errors_m(tmp_path / "run", log, after_t_s=found[0] + 2.0)
    inside = float(np.mean(out_err <= 3 * out_acc))
    print(f"drag {speed_m_s} m/s: found {detected_after_s:.1f} s after it began, GPS1 then {speed_m_s * detected_after_s:.2f} m "
          f"off, the filter that geotags landmarks at most {in_map.max():.2f} m; GPS2 after, to the last visual fix "
          f"{log['end_t_s'] - last_fix_t_s:.1f} s before the end: {len(err)} samples, RMS {np.sqrt(np.mean(err ** 2)):.3f} m, "
          f"max {err.max():.3f} m; GPS_INPUT after, to the end: max {out_err.max():.3f} m, inside 3 sigma {inside:.3f}; "
          f"landed {log['landing_error_m']:.2f} m from home")
    assert 0.0 < detected_after_s <= 10.0
    assert in_map.max() <= 1.0
    assert not mapping_after, mapping_after
    if take_primary:
        assert any(text.startswith("GPS1 dragged: GPS2 (auxgps) made primary") for _, text in events), events
        assert any(e["event"] == "primary_changed" and e["to"] == 1 for e in log["events"])
    assert np.sqrt(np.mean(err ** 2)) <= 0.3 and err.max() <= 1.0
    assert inside >= 0.97
    # Home, not where the dragged GPS1 puts it (10 s of drag away); within 1 m is the busy flight's and the kill
    # flight's test: here the survey was flown offset by the drag until it was found (0.22 to 0.43 m on the pad).
    assert log["landing_error_m"] <= max(1.0, 0.5 * 10.0 * speed_m_s)
    assert not any(e["event"] == "failsafe" for e in log["events"])


def test_gps1_faults_in_a_simulated_flight_inflate_and_drop_its_reports():
    from auxgps.core.events import Gps1
    from auxgps.sim.faults import Fault, FaultInjector, FaultPlan

    inj = FaultInjector(FaultPlan([Fault("gps1_inflated", at_s=1.0, for_s=1.0, h_acc_m=4.0),
                                   Fault("gps1_dropout", at_s=3.0, for_s=4.0, off_s=0.5, period_s=2.0)]))
    reports = {}
    for k in range(40):
        t = 0.2 * k
        out = inj.events(t, [Gps1(t, 6, 10, 47.0, 8.0, 500.0, 0.3)])
        reports[round(t, 1)] = out[0] if out else None
    inflated = [r for t, r in reports.items() if 1.0 <= t < 2.0]
    assert all(r.h_acc_m == 4.0 for r in inflated) and np.std([r.lat_deg for r in inflated]) * 111e3 > 1.0
    assert all(r is not None and r.h_acc_m == 0.3 and r.lat_deg == 47.0 for t, r in reports.items() if t < 1.0 or 2.0 <= t < 3.0)
    assert [t for t, r in reports.items() if r is None] == [3.0, 3.2, 3.4, 5.0, 5.2, 5.4]


def visual_fix_errors_m(run_dir: Path, log: dict) -> np.ndarray:
    """The horizontal error of each visual fix auxgps accepted, against the emulator's truth at its capture time
    (auxgps stamps on this machine's monotonic clock; the emulator logs that clock beside its own), m."""
    from auxgps.core.geometry import LocalFrame

    frame = LocalFrame(**log["origin"])
    pairs = np.array(log["monotonic_clock"])
    t = np.array([s["t_s"] for s in log["samples"]])
    truth = np.array([s["truth_ned_m"][:2] for s in log["samples"]])
    out = []
    with open(run_dir / "fixes.csv") as f:
        for row in csv.DictReader(f):
            if row["kind"] != "visual" or row["accepted"] != "True":
                continue
            t_emu = float(np.interp(float(row["t_s"]), pairs[:, 1], pairs[:, 0]))
            p = frame.to_ned(lat_deg=float(row["lat_deg"]), lon_deg=float(row["lon_deg"]), alt_amsl_m=frame.alt_amsl_m)
            out.append(float(np.hypot(p[0] - np.interp(t_emu, t, truth[:, 0]), p[1] - np.interp(t_emu, t, truth[:, 1]))))
    return np.array(out)


def last_accepted_fix_t_s(run_dir: Path, log: dict) -> float:
    """The capture time of the last visual fix auxgps accepted, emulated s."""
    pairs = np.array(log["monotonic_clock"])
    with open(run_dir / "fixes.csv") as f:
        t = [float(r["t_s"]) for r in csv.DictReader(f) if r["kind"] == "visual" and r["accepted"] == "True"]
    return float(np.interp(max(t), pairs[:, 1], pairs[:, 0]))


def gps2_unhealthy_s(samples: list[dict]) -> float:
    """How long GPS2 was unhealthy or without a 3D fix after it first became healthy, to the landing, emulated s."""
    first = next(k for k, s in enumerate(samples) if s["gps2_healthy"] and s["gps2_fix"] >= 3)
    flying = [s for s in samples[first:] if s["armed"]]
    return sum(0.1 for s in flying if not (s["gps2_healthy"] and s["gps2_fix"] >= 3))


@pytest.mark.flight
def test_beside_two_busy_processes_gps2_stays_healthy_and_the_vehicle_lands_home(tmp_path):
    """Two processes spinning at the same priority as auxgps for the whole flight (on two cores: auxgps, the
    emulator and the two share them): GPS_INPUT keeps ArduPilot's rate rule, no accepted fix is over 0.5 m, and the
    vehicle lands home on GPS2."""
    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(2)]
    port = free_port()
    emu = run = None
    try:
        emu = start_emulator(port, tmp_path / "emu.json", "--survey-size", "8", "--fail-gps1-at", "15", "--max-seconds", "600", world=WORLD)
        run = start_run(port, tmp_path / "run")
        emu.wait(timeout=600)
    finally:
        for p in (emu, run, *busy):
            if p is not None and p.poll() is None:
                p.terminate()
        for p in (emu, run, *busy):
            if p is not None:
                p.wait(timeout=20)
    log = json.loads((tmp_path / "emu.json").read_text())
    assert log["exit_reason"] == "landed", (tmp_path / "run" / "run.log").read_text()[-2000:]
    fixes = visual_fix_errors_m(tmp_path / "run", log)
    unhealthy_s = gps2_unhealthy_s(log["samples"])
    stats = log["gps_input"]
    print(f"beside two busy loops: GPS_INPUT {stats}; GPS2 unhealthy {unhealthy_s:.1f} s; {len(fixes)} accepted fixes, "
          f"RMS {np.sqrt(np.mean(fixes ** 2)):.3f} m, max {fixes.max():.3f} m; landed {log['landing_error_m']:.2f} m from home")
    assert unhealthy_s == 0.0
    assert len(fixes) > 100 and fixes.max() <= 0.5
    assert log["landing_error_m"] <= 1.0
    assert not any(e["event"] == "failsafe" for e in log["events"])


def gps_input_errors_m(run_dir: Path, log: dict, delay_s: float = 0.1,
                       after_t_s: float = -np.inf) -> tuple[np.ndarray, np.ndarray]:
    """The horizontal error of each GPS_INPUT with a 3D fix that auxgps sent (after ``after_t_s``, emulated s),
    against the emulator's truth ``delay_s`` (auxgps run's --gps-delay-ms) before it was sent, and the accuracy it
    reported, m."""
    from auxgps.core.geometry import LocalFrame

    frame = LocalFrame(**log["origin"])
    pairs = np.array(log["monotonic_clock"])
    t = np.array([s["t_s"] for s in log["samples"]])
    truth = np.array([s["truth_ned_m"][:2] for s in log["samples"]])
    err, acc = [], []
    with open(run_dir / "gps_input.csv") as f:
        for row in csv.DictReader(f):
            if row["fix_type"] != "3":
                continue
            t_emu = float(np.interp(float(row["t_s"]) - delay_s, pairs[:, 1], pairs[:, 0]))
            if t_emu > t[-1] or t_emu < after_t_s:
                continue
            p = frame.to_ned(lat_deg=float(row["lat_deg"]), lon_deg=float(row["lon_deg"]), alt_amsl_m=frame.alt_amsl_m)
            err.append(float(np.hypot(p[0] - np.interp(t_emu, t, truth[:, 0]), p[1] - np.interp(t_emu, t, truth[:, 1]))))
            acc.append(float(row["horiz_accuracy_m"]))
    return np.array(err), np.array(acc)


def assert_named_once_and_honest(run_dir: Path, log: dict, named: str, label: str) -> None:
    """An emulator flight with one fault injected: auxgps's events log names it once (a line containing ``named``),
    no accepted visual fix is over 0.5 m, its GPS_INPUT is inside 3 sigma for at least 97 % of the outputs, and the
    vehicle landed without a failsafe. Prints the figures under ``label``."""
    said = [r["text"] for r in csv.DictReader(open(run_dir / "events.csv")) if named in r["text"]]
    fixes = visual_fix_errors_m(run_dir, log)
    err, acc = gps_input_errors_m(run_dir, log)
    inside = float(np.mean(err <= 3 * acc))
    print(f"{label}: {said}; {len(fixes)} accepted fixes, max {fixes.max():.3f} m; GPS_INPUT 3D {len(err)}, "
          f"RMS {np.sqrt(np.mean(err ** 2)):.3f} m, max {err.max():.3f} m, inside 3 sigma {inside:.3f}; GPS2 unhealthy "
          f"{gps2_unhealthy_s(log['samples']):.1f} s; landed {log['landing_error_m']:.2f} m from home")
    assert len(said) == 1, said
    assert len(fixes) > 100 and fixes.max() <= 0.5
    assert inside >= 0.97
    assert not any(e["event"] == "failsafe" for e in log["events"])


@pytest.mark.flight
@pytest.mark.flight_extra
def test_an_autopilot_reboot_mid_flight_is_named_and_survived(tmp_path):
    """50 s after take-off, with GPS1 long lost, the emulated autopilot goes silent for 2 s and comes back with its
    boot clock from 0, streaming HEARTBEAT alone (a copter's rates after a restart). auxgps names it once, asks for
    its messages again, and its GPS_INPUT stays honest: no accepted fix over 0.5 m, inside 3 sigma for at least
    97 % of the outputs; the vehicle lands without a failsafe."""
    faults = tmp_path / "reboot.yaml"
    faults.write_text("faults:\n  - {kind: autopilot_reboot, at_s: 50, for_s: 2}\n")
    log = fly_emulator(tmp_path, ["--survey-size", "8", "--fail-gps1-at", "15", "--max-seconds", "600", "--faults",
                                  str(faults)], [])
    assert log["exit_reason"] == "landed", (tmp_path / "run" / "run.log").read_text()[-2000:]
    assert any(e["event"] == "rebooted" for e in log["events"])
    assert_named_once_and_honest(tmp_path / "run", log, "autopilot rebooted", "autopilot reboot")


@pytest.mark.flight
@pytest.mark.flight_extra
def test_a_height_stuck_in_the_descent_is_named_once_and_survived(tmp_path):
    """78 s after take-off, GPS1 long lost and the vehicle descending home at 0.5 m/s, the emulated autopilot's
    height above home holds one value for 6 s (in level flight a stuck height is a steady one: nothing to name).
    auxgps names it once and does not fuse it; its GPS_INPUT stays honest: no accepted fix over 0.5 m, inside 3
    sigma for at least 97 % of the outputs; the vehicle lands without a failsafe."""
    faults = tmp_path / "stuck.yaml"
    faults.write_text("faults:\n  - {kind: height_stuck, at_s: 78, for_s: 6}\n")
    log = fly_emulator(tmp_path, ["--survey-size", "8", "--fail-gps1-at", "15", "--max-seconds", "600", "--faults",
                                  str(faults)], [])
    assert log["exit_reason"] == "landed", (tmp_path / "run" / "run.log").read_text()[-2000:]
    began_t_s = next(e["t_s"] for e in log["events"] if e["event"] == "fault" and e["kind"] == "height_stuck")
    phase = next(s["phase"] for s in log["samples"] if s["t_s"] >= began_t_s)
    assert phase == "descend", f"the fault began in the {phase} phase, not the descent: move at_s"
    assert_named_once_and_honest(tmp_path / "run", log, "height above home stuck", "height stuck in the descent")
