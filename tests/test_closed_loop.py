"""auxgps run against the vehicle emulator, as separate processes on loopback: a short closed-loop flight."""

import json
import socket
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
WORLD = str(REPO / "config" / "worlds" / "cubes4_0.5m_different.yaml")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_short_flight_lands_home_on_gps2(tmp_path):
    port = free_port()
    emu = subprocess.Popen(
        [sys.executable, str(REPO / "tools" / "vehicle_emulator.py"), "--world", WORLD, "--port", str(port),
         "--survey-size", "6", "--fail-gps1-at", "20", "--log", str(tmp_path / "emu.json"), "--max-seconds", "150"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )
    run = subprocess.Popen(
        [sys.executable, "-m", "auxgps.cli", "run", "--connect", f"tcp:127.0.0.1:{port}", "--camera", f"sim:{WORLD}",
         "--log-dir", str(tmp_path / "run"), "--duration", "150", "--save-map", str(tmp_path / "map.npz")],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=REPO,
    )
    try:
        emu.wait(timeout=170)
    finally:
        for p in (emu, run):
            if p.poll() is None:
                p.terminate()
        run.wait(timeout=20)
    log = json.loads((tmp_path / "emu.json").read_text())
    assert log["exit_reason"] == "landed"
    assert log["switch_to_gps2_t_s"] - log["failure_t_s"] <= 1.0
    stats = log["gps_input"]
    assert stats["mean_interval_ms"] <= 215 and stats["consecutive_gaps_over_245ms"] == 0
    assert log["landing_error_m"] <= 1.0
    assert (tmp_path / "map.npz").exists()  # saved at the end of the flight, atomically
    events = (tmp_path / "run" / "events.csv").read_text()
    assert "GPS1 lost" in events and "positioning" in events
