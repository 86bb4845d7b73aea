"""A user's mistake is one line naming what is wrong and exit code 2 (usage) or 1 (runtime); a bug is exit 3 with
the traceback kept in a file. Never a traceback on the screen."""

import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import free_port

REPO = Path(__file__).resolve().parent.parent
WORLD = str(REPO / "config" / "worlds" / "one_cube_1m.yaml")


def auxgps(*args: str, timeout_s: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "auxgps.cli", *args], cwd=REPO, capture_output=True, text=True, timeout=timeout_s)


@pytest.mark.parametrize(
    "args, code, names",
    [
        (["map", "build", "--images", ".", "--out", "x.npz", "--max-side", "-5"], 2, "--max-side"),
        (["bench", "--map-sizes", "10k"], 2, "--map-sizes"),
        (["run", "--connect", "tcp:host:abc", "--camera", "0"], 2, "port 'abc'"),
        (["run", "--connect", "serial0", "--camera", "0"], 2, "--connect"),
        (["run", "--connect", "/dev/ttyAMA0,fast", "--camera", "0"], 2, "baud rate"),
        (["eval", "--world", WORLD, "--altitude", "ten"], 2, "--altitude"),
        (["replay", "/no/such/recording"], 1, "not a recording"),
        (["run", "--connect", "/dev/ttyNOPE0,921600", "--camera", f"sim:{WORLD}", "--connect-timeout", "0.5", "--log-dir", "/tmp/auxgps-test-nodev"], 1, "no such device /dev/ttyNOPE0"),
    ],
)
def test_a_mistake_is_one_line_and_an_exit_code(args, code, names):
    proc = auxgps(*args)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == code, proc.stderr
    assert len(lines) == 1 and names in lines[0] and "Traceback" not in proc.stderr, proc.stderr


def test_a_refused_connection_at_start_is_one_line_and_exit_1(tmp_path):
    port = free_port()  # nothing listens there
    proc = auxgps("run", "--connect", f"tcp:127.0.0.1:{port}", "--camera", f"sim:{WORLD}", "--connect-timeout", "1",
                  "--log-dir", str(tmp_path))
    errors = [line for line in proc.stderr.splitlines() if "error" in line]
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    assert len(errors) == 1 and "connection refused" in errors[0] and f"127.0.0.1:{port}" in errors[0]


def test_a_bug_says_so_keeps_the_traceback_and_exits_3(monkeypatch, capsys):
    import auxgps.cli as cli

    def broken(args):
        raise ZeroDivisionError("a deliberate bug")

    monkeypatch.setattr(cli, "_eval", broken)
    assert cli.main(["eval", "--world", WORLD, "--altitude", "15"]) == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "a bug in auxgps" in err[0] and "ZeroDivisionError" in err[0]
    log = Path(err[0].split("the traceback is in ")[1].split(";")[0])
    assert "ZeroDivisionError: a deliberate bug" in log.read_text()


def test_nice_lowers_only_the_thread_that_asks():
    import os
    import threading

    from auxgps.companion import lower_this_thread

    main_nice = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    seen = {}

    def frames():
        seen["new"] = lower_this_thread(5)
        seen["read"] = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())

    t = threading.Thread(target=frames)
    t.start()
    t.join()
    assert seen["new"] == seen["read"] == min(main_nice + 5, 19)
    assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == main_nice


def test_take_primary_on_drift_sets_and_restores_the_autopilots_gps_choice():
    import types

    from auxgps.companion import PrimaryTakeover

    class Link:
        def __init__(self):
            self.sent = []

        def send_param_request(self, name):
            self.sent.append(("read", name))

        def send_param_set(self, name, value):
            self.sent.append((name, value))

    link, events = Link(), []
    p = PrimaryTakeover(link, lambda t, text: events.append(text))
    p.update(0.0, dragged=True, have_fix=True)  # the values to restore are not known yet: ask, do nothing else
    assert link.sent == [("read", "GPS_AUTO_SWITCH"), ("read", "GPS_PRIMARY")] and not p.taken
    for name, value in (("GPS_AUTO_SWITCH", 1.0), ("GPS_PRIMARY", 0.0)):
        p.on_param_value(types.SimpleNamespace(param_id=name, param_value=value))
    link.sent.clear()
    p.update(1.0, dragged=False, have_fix=True)
    assert link.sent == []
    p.update(2.0, dragged=True, have_fix=True)
    assert link.sent == [("GPS_AUTO_SWITCH", 0), ("GPS_PRIMARY", 1)] and events[-1].startswith("GPS1 dragged: GPS2")
    p.on_param_value(types.SimpleNamespace(param_id="GPS_PRIMARY", param_value=1.0))  # the echo: not what to restore
    link.sent.clear()
    p.update(3.0, dragged=True, have_fix=False)  # auxgps lost its fix: give the choice back
    assert link.sent == [("GPS_AUTO_SWITCH", 1.0), ("GPS_PRIMARY", 0.0)] and "auxgps has no fix" in events[-1]
    p.update(4.0, dragged=True, have_fix=True)
    link.sent.clear()
    p.restore(5.0, "auxgps stopping")
    assert link.sent == [("GPS_AUTO_SWITCH", 1.0), ("GPS_PRIMARY", 0.0)]
