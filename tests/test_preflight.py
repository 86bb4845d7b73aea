"""`auxgps check`: the rules against known answers, and the command against the vehicle emulator."""

import socket
import subprocess
import sys
from pathlib import Path

import pytest

from auxgps.core.autopilot_setup import Observed, check_setup, param_names, read_parm_file
from tests.conftest import free_port, when_listening

REPO = Path(__file__).resolve().parent.parent
WANTED = read_parm_file((REPO / "config" / "ardupilot" / "auxgps-gps2.parm").read_text())
GOOD_PARAMS = {"GPS2_TYPE": 14, "GPS_AUTO_SWITCH": 4, "GPS_PRIMARY": 0, "GPS2_DELAY_MS": 100, "EK3_SRC1_POSXY": 3, "EK3_SRC1_VELXY": 3}
GOOD_STREAMS = {"ATTITUDE": 50.0, "SCALED_IMU": 50.0, "GLOBAL_POSITION_INT": 10.0, "GPS_RAW_INT": 5.0}


def bad_keys(obs, delay_ms=100):
    return [f.key for f in check_setup(obs, WANTED, delay_ms) if not f.ok]


def test_the_project_parameter_file_on_a_healthy_autopilot_is_all_green():
    assert bad_keys(Observed((4, 7, 0), GOOD_PARAMS, GOOD_STREAMS, (6, 10))) == []


def test_each_fault_is_named():
    assert bad_keys(Observed((4, 7, 0), {**GOOD_PARAMS, "GPS2_TYPE": 0}, GOOD_STREAMS, (6, 10))) == ["GPS2_TYPE"]
    assert bad_keys(Observed((4, 7, 0), GOOD_PARAMS, GOOD_STREAMS, (6, 10)), delay_ms=150) == ["GPS2_DELAY_MS"]
    assert bad_keys(Observed((4, 7, 0), GOOD_PARAMS, {**GOOD_STREAMS, "ATTITUDE": 20.0}, (6, 10))) == ["ATTITUDE"]
    assert bad_keys(Observed((4, 7, 0), GOOD_PARAMS, GOOD_STREAMS, (1, 3))) == ["GPS1"]
    assert bad_keys(Observed(None, GOOD_PARAMS, GOOD_STREAMS, (6, 10))) == ["firmware"]
    missing = dict(GOOD_PARAMS)
    del missing["EK3_SRC1_VELXY"]
    findings = check_setup(Observed((4, 7, 0), missing, GOOD_STREAMS, (6, 10)), WANTED, 100)
    bad = [f for f in findings if not f.ok]
    assert [f.key for f in bad] == ["EK3_SRC1_VELXY"] and bad[0].set_params == {"EK3_SRC1_VELXY": 3.0}


def test_before_4_6_the_second_gps_has_its_old_names():
    assert param_names((4, 5, 7)) == {"GPS2_TYPE": "GPS_TYPE2", "GPS2_DELAY_MS": "GPS_DELAY_MS2"}
    old = {"GPS_TYPE2": 14, "GPS_AUTO_SWITCH": 4, "GPS_PRIMARY": 0, "GPS_DELAY_MS2": 100, "EK3_SRC1_POSXY": 3, "EK3_SRC1_VELXY": 3}
    assert bad_keys(Observed((4, 5, 7), old, GOOD_STREAMS, (6, 10))) == ["firmware"]  # works, but not what auxgps is tested on
    assert "GPS_TYPE2" in bad_keys(Observed((4, 5, 7), {**old, "GPS_TYPE2": 0}, GOOD_STREAMS, (6, 10)))


def test_a_bad_parameter_file_line_is_named():
    with pytest.raises(ValueError, match="line 2"):
        read_parm_file("GPS2_TYPE 14\nGPS_AUTO_SWITCH\n")


def check(port, *args):
    return subprocess.run([sys.executable, "-m", "auxgps.cli", "check", "--connect", f"tcp:127.0.0.1:{port}", *args],
                          cwd=REPO, capture_output=True, text=True, timeout=120)


@pytest.mark.slow
@pytest.mark.realtime
def test_check_and_fix_against_the_emulator():
    port = free_port()
    emu = subprocess.Popen([sys.executable, "-m", "auxgps.sim.emulator", "--world", "one_cube_1m",
                            "--port", str(port), "--gps2-type", "0", "--max-seconds", "120"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        when_listening(lambda: socket.create_connection(("127.0.0.1", port), timeout=0.2).close())
        first = check(port, "--gps-delay-ms", "120")
        assert first.returncode == 1, first.stdout + first.stderr
        bad = [line for line in first.stdout.splitlines() if line.strip().startswith("BAD")]
        assert any("GPS2_TYPE = 0, want 14" in line for line in bad) and any("GPS2_DELAY_MS = 100, want 120" in line for line in bad)
        assert any("ArduPilot 4.7.0" in line for line in first.stdout.splitlines())
        fixed = check(port, "--gps-delay-ms", "120", "--fix", "--yes")
        assert fixed.returncode == 0 and "reboot the autopilot for GPS2_TYPE, GPS2_DELAY_MS" in fixed.stdout, fixed.stdout
        again = check(port, "--gps-delay-ms", "120")
        assert again.returncode == 0 and "all green" in again.stdout, again.stdout
    finally:
        emu.kill()
        emu.wait(timeout=10)
