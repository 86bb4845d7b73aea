"""Faults a real flight brings: a fault campaign through `auxgps eval`, and the vehicle emulator flown with
`auxgps run` as a separate process (a minute to minutes each: marked ``flight``, run by .ci/run after make test)."""

import csv
import json
import subprocess
import sys
import time
from pathlib import Path

import pytest

from auxgps.io.map_file import load_map
from tests.conftest import free_port
from tests.test_closed_loop import start_emulator  # the same world, port and log options

REPO = Path(__file__).resolve().parent.parent
WORLD = str(REPO / "config" / "worlds" / "cubes4_0.5m_different.yaml")
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
    emu = start_emulator(port, tmp_path / "emu.json", "--survey-size", "12", "--fail-gps1-at", "20", "--max-seconds", "600")
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


@pytest.mark.flight
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
