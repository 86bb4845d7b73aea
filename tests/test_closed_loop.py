"""auxgps run against the vehicle emulator, as separate processes on loopback: a short closed-loop flight."""

import json
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import free_port, when_listening

pytestmark = pytest.mark.realtime  # flights in real time: never beside other tests

REPO = Path(__file__).resolve().parent.parent
WORLD = str(REPO / "config" / "worlds" / "cubes4_0.5m_different.yaml")


def start_emulator(port: int, log: Path, *options: str, world: str = WORLD) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "auxgps.sim.emulator", "--world", world, "--port", str(port), "--log", str(log), *options],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )


def start_run(port: int, log_dir: Path, *options: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "auxgps.cli", "run", "--connect", f"tcp:127.0.0.1:{port}", "--camera", f"sim:{WORLD}",
         "--log-dir", str(log_dir), *options],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=REPO,
    )


def stop(*procs: subprocess.Popen | None) -> None:
    """Terminate whatever is still running and reap it."""
    for p in procs:
        if p is not None and p.poll() is None:
            p.terminate()
    for p in procs:
        if p is not None:
            p.wait(timeout=20)


@pytest.fixture(scope="module")
def short_flight(tmp_path_factory):
    """A short survey on the emulator, GPS1 failing at 20 s, flown by `auxgps run --record` over a serial line: the
    emulator's TCP port bridged to a pseudo-terminal pair, auxgps on its slave end at 921600 baud, as on a vehicle's
    UART."""

    tmp_path = tmp_path_factory.mktemp("short_flight")
    port = free_port()
    emu = start_emulator(port, tmp_path / "emu.json", "--survey-size", "6", "--fail-gps1-at", "20", "--max-seconds", "150")
    bridge = run = None
    try:
        bridge = when_listening(lambda: SerialBridge(port))
        run = subprocess.Popen(
            [sys.executable, "-m", "auxgps.cli", "run", "--connect", f"{bridge.path},921600", "--camera", f"sim:{WORLD}",
             "--log-dir", str(tmp_path / "run"), "--duration", "150", "--save-map", str(tmp_path / "map.npz"),
             "--record", str(tmp_path / "rec")],
            stdout=subprocess.DEVNULL, stderr=open(tmp_path / "run.log", "w"), cwd=REPO,
        )
        emu.wait(timeout=170)
    finally:
        stop(emu, run)
        if bridge is not None:
            bridge.close()
    (tmp_path / "bridge.json").write_text(json.dumps({"bytes_up": bridge.bytes_up, "bytes_down": bridge.bytes_down}))
    return tmp_path


@pytest.mark.slow
def test_short_flight_over_a_serial_line_lands_home_on_gps2(short_flight):
    tmp_path = short_flight
    log = json.loads((tmp_path / "emu.json").read_text())
    assert log["exit_reason"] == "landed", (tmp_path / "run.log").read_text()[-2000:]
    assert log["switch_to_gps2_t_s"] - log["failure_t_s"] <= 1.0
    stats = log["gps_input"]
    # ArduPilot's health rule (AP_GPS): mean interval at most 215 ms and never two late (over 245 ms) in a row.
    # One late message is within the rule; a loaded CI machine once stalled the timer 350 ms.
    assert stats["mean_interval_ms"] <= 215 and stats["consecutive_gaps_over_245ms"] < 2
    # Under CPU load from other processes the landing error of a 6 m flight over TCP was once seen at 1.6 m; alone,
    # as make test runs it, this flight lands within a few decimetres.
    assert log["landing_error_m"] <= 1.0
    line = json.loads((tmp_path / "bridge.json").read_text())
    assert line["bytes_up"] > 10_000 and line["bytes_down"] > 100_000  # GPS_INPUT up, telemetry down, on the line
    assert "Traceback" not in (tmp_path / "run.log").read_text()
    assert not any(e["event"] == "failsafe" for e in log["events"])
    assert (tmp_path / "map.npz").exists()  # saved at the end of the flight, atomically
    events = (tmp_path / "run" / "events.csv").read_text()
    assert "GPS1 lost" in events and "positioning" in events
    # What the frame loop kept up with, said at the end of the flight
    frames = json.loads((tmp_path / "run" / "frames.json").read_text())
    assert frames["frames_processed"] > 100 and "frames: " in events
    assert 0.0 < frames["capture_to_gps_input_ms"]["median"] < 500.0, frames


def replay_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "auxgps.cli", "replay", *args], cwd=REPO, capture_output=True, text=True, timeout=600)


def gps_input_rows(path: Path) -> list[dict]:
    import csv

    return list(csv.DictReader(open(path)))


atol_replay_m = 1e-3  # 1 mm: the replay is the flight's own computation


@pytest.mark.slow
def test_replay_of_a_recorded_flight_reproduces_its_gps_input(short_flight):
    import numpy as np

    from auxgps.core.geometry import LocalFrame

    rec, out = short_flight / "rec", short_flight / "replay"
    proc = replay_cli(str(rec), "--out", str(out))
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    flown, replayed = gps_input_rows(short_flight / "run" / "gps_input.csv"), gps_input_rows(out / "gps_input.csv")
    assert len(flown) > 500 and len(replayed) == len(flown)
    assert [r["fix_type"] for r in replayed] == [r["fix_type"] for r in flown]
    assert {r["fix_type"] for r in flown} >= {"3"} and {r["mode"] for r in flown} >= {"mapping", "positioning"}
    lat = lambda rows: np.array([float(r["lat_deg"]) for r in rows])  # noqa: E731
    lon = lambda rows: np.array([float(r["lon_deg"]) for r in rows])  # noqa: E731
    frame = LocalFrame(float(flown[0]["lat_deg"]), float(flown[0]["lon_deg"]), 0.0)
    a = frame.to_ned(lat_deg=lat(flown), lon_deg=lon(flown), alt_amsl_m=np.zeros(len(flown)))
    b = frame.to_ned(lat_deg=lat(replayed), lon_deg=lon(replayed), alt_amsl_m=np.zeros(len(replayed)))
    assert np.max(np.linalg.norm(a[:, :2] - b[:, :2], axis=1)) <= atol_replay_m
    stats = json.loads((rec / "recording_stats.json").read_text())
    assert stats["frames"] > 100 and stats["frames_not_written"] == 0


@pytest.mark.slow
def test_replay_with_gps_denied_early_is_scored_against_the_hidden_gps1(short_flight, tmp_path):
    out = tmp_path / "denied"
    proc = replay_cli(str(short_flight / "rec"), "--deny-gps-after", "8", "--out", str(out), "--json", str(tmp_path / "f.json"),
                      "--report", str(tmp_path / "report.png"))
    assert proc.returncode == 0, proc.stderr
    fig = json.loads((tmp_path / "f.json").read_text())["score"]
    g = fig["gps1"]
    assert fig["scored"] and g["outputs_compared"] >= 50  # the hidden GPS1 covers the 8 s to the flight's own failure at 20 s
    assert g["rms_m"] < 0.5 and g["availability"] > 0.9  # the emulator's fixes are good to a decimetre; GPS1 to a few cm
    assert fig["truth"]["rms_m"] < 0.5
    for name in ("estimate.tum", "reference_gps1.tum", "tracks.geojson"):
        assert (out / name).stat().st_size > 0
    assert (tmp_path / "report.png").stat().st_size > 10_000
    assert "against the hidden GPS1" in proc.stdout


@pytest.mark.slow
def test_a_damaged_recording_is_replayed_as_far_as_it_goes(short_flight, tmp_path):
    import shutil

    rec = tmp_path / "rec"
    shutil.copytree(short_flight / "rec", rec)
    tlog = (rec / "flight.tlog").read_bytes()
    (rec / "flight.tlog").write_bytes(tlog[: len(tlog) // 2] + b"\x07" * 999)  # cut, with garbage after
    for k in (5, 6, 7):
        (rec / "frames" / f"{k:06d}.png").unlink()
    lines = (rec / "frames.csv").read_text().splitlines(keepends=True)
    lines[20], lines[21] = lines[21], lines[20]  # two frames out of time order
    (rec / "frames.csv").write_text("".join(lines) + "12")  # and a cut last line
    proc = replay_cli(str(rec), "--out", str(tmp_path / "out"))
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    problems = [line for line in proc.stderr.splitlines() if line.startswith("auxgps: replay:")]
    assert any("000005.png missing" in p for p in problems)
    assert any("out of time order" in p for p in problems)
    assert any("last line is cut" in p for p in problems)
    assert any("tlog is cut" in p for p in problems)
    assert len(gps_input_rows(tmp_path / "out" / "gps_input.csv")) > 100


@pytest.mark.slow
def test_run_reconnects_after_the_autopilot_restarts_and_ignores_noise(tmp_path):
    """The emulator is killed mid-flight and started again on the same port: auxgps reconnects and the new
    autopilot gets GPS_INPUT; garbage bytes and another system's messages on the link change nothing."""
    import time

    port = free_port()

    def emulator(name, seconds):
        return start_emulator(port, tmp_path / name, "--survey-size", "4", "--max-seconds", str(seconds))

    first = emulator("first.json", 60)
    run = start_run(port, tmp_path / "run", "--duration", "60")
    second = None
    try:
        # Until auxgps has sent the first autopilot 80 GPS_INPUT (one row each in its log), not a fixed time: on
        # a loaded machine its start-up alone has taken most of 12 s.
        sent = tmp_path / "run" / "gps_input.csv"
        deadline = time.monotonic() + 45
        while time.monotonic() < deadline and (not sent.exists() or len(sent.read_text().splitlines()) <= 80):
            time.sleep(0.5)
        first.send_signal(2)  # SIGINT: the emulator writes its log and exits; the link drops
        first.wait(timeout=10)
        second = emulator("second.json", 15)
        second.wait(timeout=40)
    finally:
        stop(first, second, run)
    one = json.loads((tmp_path / "first.json").read_text())
    two = json.loads((tmp_path / "second.json").read_text())
    assert len(one["gps_input_arrivals_t_s"]) > 50
    assert len(two["gps_input_arrivals_t_s"]) > 50  # reconnected and sending again
    assert two["gps_input"]["consecutive_gaps_over_245ms"] < 2  # ArduPilot's health rule, as above


def test_link_ignores_garbage_and_other_systems():
    """Decoding straight from bytes: noise between messages, and a second vehicle's messages, are dropped."""
    import os

    import numpy as np

    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    from auxgps.io.link import Attitude, Decoder, MavLink

    got = []
    decoder = Decoder()
    link = MavLink("tcp:127.0.0.1:1", lambda msg, arrival_s: got.append(decoder(msg, arrival_s)))
    ours, theirs = mavlink.MAVLink(None, srcSystem=1, srcComponent=1), mavlink.MAVLink(None, srcSystem=7, srcComponent=1)
    hb = ours.heartbeat_encode(2, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 0).pack(ours)
    att = ours.attitude_encode(100, 0.1, 0.2, 0.3, 0, 0, 0).pack(ours)
    other = theirs.attitude_encode(100, 1.0, 1.0, 1.0, 0, 0, 0).pack(theirs)
    noise = bytes(b for b in range(256) if b not in (0xFD, 0xFE))  # line noise without a frame start
    stream = noise + hb + noise + other + noise + att + noise
    parser = mavlink.MAVLink(None)
    parser.robust_parsing = True
    for i in range(len(stream)):
        msg = parser.parse_char(stream[i : i + 1])
        if msg is not None:
            link._handle(msg, 1.0)
    assert len(got) == 2 and got[0] is None  # the autopilot's HEARTBEAT, which decodes to no record
    got = got[1:]
    assert len(got) == 1 and isinstance(got[0], Attitude) and np.allclose(got[0].euler_rad, [0.1, 0.2, 0.3], atol=1e-6)


class SerialBridge:
    """A pseudo-terminal pair whose master end is bridged to the emulator's TCP port: the slave end is a serial line
    (auxgps opens it with a baud rate, as a flight controller's UART), the bytes cross unchanged."""

    def __init__(self, port: int) -> None:
        import os
        import pty
        import threading
        import tty

        self.master, slave = pty.openpty()
        tty.setraw(slave)
        self.path = os.ttyname(slave)
        self._slave = slave
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=10)
        self.sock.setblocking(False)
        self.bytes_up = self.bytes_down = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._pump, daemon=True)
        self._thread.start()

    def _pump(self) -> None:
        import os
        import select

        while not self._stop.is_set():
            ready, _, _ = select.select([self.master, self.sock], [], [], 0.1)
            try:
                if self.master in ready:
                    data = os.read(self.master, 65536)
                    self.sock.sendall(data)
                    self.bytes_up += len(data)
                if self.sock in ready:
                    data = self.sock.recv(65536)
                    if not data:
                        return
                    os.write(self.master, data)
                    self.bytes_down += len(data)
            except (BlockingIOError, InterruptedError):
                continue
            except OSError:
                return

    def close(self) -> None:
        import os

        self._stop.set()
        self._thread.join(timeout=2)
        self.sock.close()
        for fd in (self.master, self._slave):
            os.close(fd)


class LineProxy:
    """Between auxgps (which connects here) and the emulator: cuts auxgps's side of the link for a while (its TCP
    connection closed, new ones refused), injects bytes towards auxgps, and notes when each GPS_INPUT from auxgps
    went through (wall clock)."""

    def __init__(self, emulator_port: int) -> None:
        import os
        import threading

        os.environ.setdefault("MAVLINK20", "1")
        from pymavlink.dialects.v20 import ardupilotmega as mavlink

        self.up = socket.create_connection(("127.0.0.1", emulator_port), timeout=10)
        self.server = socket.socket()
        self.server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.server.bind(("127.0.0.1", 0))
        self.server.listen(4)
        self.port = self.server.getsockname()[1]
        self.down: socket.socket | None = None
        self.cut_until = 0.0
        self.gps_input_t: list[float] = []
        self.texts: list[str] = []  # STATUSTEXT from auxgps
        self._parser = mavlink.MAVLink(None)
        self._parser.robust_parsing = True
        self._lock = threading.Lock()
        self._stop = threading.Event()
        for target in (self._accept, self._pump_up, self._pump_down):
            threading.Thread(target=target, daemon=True).start()

    def _accept(self) -> None:
        import time

        self.server.settimeout(0.1)
        while not self._stop.is_set():
            try:
                conn, _ = self.server.accept()
            except OSError:
                continue
            if time.monotonic() < self.cut_until:
                conn.close()  # the line is down: refused
                continue
            with self._lock:
                self.down = conn

    def _pump_up(self) -> None:
        """Emulator -> auxgps (dropped while the line is down)."""
        while not self._stop.is_set():
            try:
                data = self.up.recv(65536)
            except OSError:
                return
            if not data:
                return
            with self._lock:
                down = self.down
            if down is not None:
                try:
                    down.sendall(data)
                except OSError:
                    pass

    def _pump_down(self) -> None:
        """auxgps -> emulator, noting GPS_INPUT."""
        import select
        import time

        while not self._stop.is_set():
            with self._lock:
                down = self.down
            if down is None:
                time.sleep(0.01)
                continue
            ready, _, _ = select.select([down], [], [], 0.1)
            if not ready:
                continue
            try:
                data = down.recv(65536)
            except OSError:
                data = b""
            if not data:
                with self._lock:
                    if self.down is down:
                        self.down = None
                continue
            now = time.monotonic()
            for msg in self._parser.parse_buffer(data) or []:
                if msg.get_type() == "GPS_INPUT":
                    self.gps_input_t.append(now)
                elif msg.get_type() == "STATUSTEXT":
                    self.texts.append(msg.text)
            try:
                self.up.sendall(data)
            except OSError:  # the emulator has ended its flight and closed its side
                return

    def cut(self, seconds: float) -> float:
        """Close auxgps's connection and refuse new ones for ``seconds``; returns when the line is back."""
        import time

        self.cut_until = time.monotonic() + seconds
        with self._lock:
            down, self.down = self.down, None
        if down is not None:
            down.close()
        time.sleep(seconds)
        return self.cut_until

    def inject(self, n_bytes: int, seed: int = 5) -> None:
        """Random bytes towards auxgps, in chunks between the real traffic."""
        import random
        import time

        rng = random.Random(seed)
        sent = 0
        while sent < n_bytes:
            chunk = bytes(rng.getrandbits(8) for _ in range(4096))
            with self._lock:
                down = self.down
            if down is not None:
                down.sendall(chunk)
                sent += len(chunk)
            time.sleep(0.002)

    def close(self) -> None:
        self._stop.set()
        for s in (self.up, self.server, self.down):
            if s is not None:
                s.close()


@pytest.mark.slow
def test_a_dropped_link_is_back_within_a_second_and_a_megabyte_of_noise_changes_nothing(tmp_path):
    """Mid-flight, 1 MB of random bytes on the line, then the line cut for 5 s and restored: auxgps reconnects,
    GPS_INPUT goes through again within 1 s of the line's return, and the vehicle finishes its flight."""
    import time

    port = free_port()
    emu = start_emulator(port, tmp_path / "emu.json", "--survey-size", "4", "--fail-gps1-at", "45", "--max-seconds", "150")
    proxy = run = None
    try:
        proxy = when_listening(lambda: LineProxy(port))
        run = subprocess.Popen(
            [sys.executable, "-m", "auxgps.cli", "run", "--connect", f"tcp:127.0.0.1:{proxy.port}", "--camera", f"sim:{WORLD}",
             "--log-dir", str(tmp_path / "run"), "--duration", "170"],
            stdout=subprocess.DEVNULL, stderr=open(tmp_path / "run.log", "w"), cwd=REPO,
        )
        deadline = time.monotonic() + 45
        while len(proxy.gps_input_t) < 50:
            assert time.monotonic() < deadline, (tmp_path / "run.log").read_text()[-2000:]
            time.sleep(0.2)
        proxy.inject(1 << 20)
        sent_before_cut = len(proxy.gps_input_t)
        back_at = proxy.cut(5.0)
        time.sleep(3.0)
        emu.wait(timeout=170)
    finally:
        stop(emu, run)
        if proxy is not None:
            proxy.close()
    after = [t for t in proxy.gps_input_t if t >= back_at]
    assert after and after[0] - back_at <= 1.0, f"GPS_INPUT back {after[0] - back_at if after else None} s after the line"
    assert sent_before_cut >= 50 and len(after) > 100
    log = json.loads((tmp_path / "emu.json").read_text())
    assert log["exit_reason"] == "landed" and not any(e["event"] == "failsafe" for e in log["events"])
    text = (tmp_path / "run.log").read_text()
    assert "back after" in text and "not MAVLink skipped" in text and "Traceback" not in text
    assert any(t.startswith("auxgps: link back after") for t in proxy.texts), proxy.texts  # told to the autopilot too
