"""`auxgps check`: the pre-flight doctor. Connects to the autopilot, reads its firmware version and parameters,
measures the streams auxgps needs, and prints what is right and wrong for auxgps as GPS2; ``--fix`` writes the
parameter file's values.

The rules are :mod:`auxgps.core.autopilot_setup`'s; this module is the MAVLink around them (pymavlink, one thread,
a deadline on every wait).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402

from auxgps.core.autopilot_setup import NEEDS_REBOOT, STREAMS_HZ, Finding, Observed, param_names, read_parm_file  # noqa: E402
from auxgps.errors import ConfigError, LinkError  # noqa: E402
from auxgps.io.link import parse_link_url  # noqa: E402
from auxgps.resources import parm_file  # noqa: E402

mav = mavutil.mavlink
PARM_FILE = parm_file()


@dataclass
class Autopilot:
    """A synchronous MAVLink session with the autopilot, for the check (not for flying)."""

    conn: object
    system: int
    component: int

    def recv(self, types=None, timeout_s: float = 1.0):
        return self.conn.recv_match(type=types, blocking=True, timeout=timeout_s)

    def command(self, command: int, *params: float) -> None:
        p = list(params) + [0.0] * (7 - len(params))
        self.conn.mav.command_long_send(self.system, self.component, command, 0, *p)


def connect(url: str, timeout_s: float) -> Autopilot:
    """Connect and wait for the autopilot's HEARTBEAT; a :class:`LinkError` naming why not."""
    address = parse_link_url(url)
    deadline = time.monotonic() + timeout_s
    conn = None
    while conn is None:
        try:
            kwargs = {"retries": 0} if address.kind == "tcp" else {}
            conn = mavutil.mavlink_connection(address.url, source_system=1, source_component=mav.MAV_COMP_ID_ONBOARD_COMPUTER, **kwargs)
        except Exception as err:  # noqa: BLE001 - pyserial and sockets raise several kinds; each is one line
            if time.monotonic() > deadline:
                raise LinkError(f"--connect {address.url}: cannot connect ({type(err).__name__}: {err})") from None
            time.sleep(0.3)
    while True:
        left = deadline - time.monotonic()
        if left <= 0:
            raise LinkError(f"--connect {address.url}: no HEARTBEAT from an ArduPilot autopilot within {timeout_s:g} s")
        hb = conn.recv_match(type="HEARTBEAT", blocking=True, timeout=min(left, 1.0))
        if hb is not None and hb.autopilot == mav.MAV_AUTOPILOT_ARDUPILOTMEGA:
            return Autopilot(conn, hb.get_srcSystem(), hb.get_srcComponent())


def read_version(ap: Autopilot, timeout_s: float = 3.0) -> tuple[int, int, int] | None:
    """(major, minor, patch) from AUTOPILOT_VERSION, or None when the autopilot does not say."""
    ap.command(mav.MAV_CMD_REQUEST_MESSAGE, mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        msg = ap.recv("AUTOPILOT_VERSION", 0.5)
        if msg is not None and msg.get_srcSystem() == ap.system:
            v = int(msg.flight_sw_version)
            return (v >> 24) & 0xFF, (v >> 16) & 0xFF, (v >> 8) & 0xFF
    return None


def read_params(ap: Autopilot, names: list[str], timeout_s: float = 20.0) -> dict[str, float]:
    """Every parameter (PARAM_REQUEST_LIST until the count is reached or 2 s pass quiet), then ``names`` still
    missing asked for one by one."""
    params: dict[str, float] = {}
    ap.conn.mav.param_request_list_send(ap.system, ap.component)
    deadline, quiet_since, count = time.monotonic() + timeout_s, time.monotonic(), None
    while time.monotonic() < deadline and time.monotonic() - quiet_since < 2.0 and (count is None or len(params) < count):
        msg = ap.recv("PARAM_VALUE", 0.5)
        if msg is None or msg.get_srcSystem() != ap.system:
            continue
        params[_name(msg)] = float(msg.param_value)
        count, quiet_since = msg.param_count, time.monotonic()
    for name in names:
        if name not in params:
            value = read_param(ap, name)
            if value is not None:
                params[name] = value
    return params


def read_param(ap: Autopilot, name: str, timeout_s: float = 2.0) -> float | None:
    ap.conn.mav.param_request_read_send(ap.system, ap.component, name.encode(), -1)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        msg = ap.recv("PARAM_VALUE", 0.5)
        if msg is not None and _name(msg) == name:
            return float(msg.param_value)
    return None


def set_param(ap: Autopilot, name: str, value: float, timeout_s: float = 3.0) -> bool:
    """PARAM_SET, confirmed by the PARAM_VALUE the autopilot echoes."""
    ap.conn.mav.param_set_send(ap.system, ap.component, name.encode(), float(value), mav.MAV_PARAM_TYPE_REAL32)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        msg = ap.recv("PARAM_VALUE", 0.5)
        if msg is not None and _name(msg) == name:
            return abs(float(msg.param_value) - value) < 1e-6
    return False


def measure_streams(ap: Autopilot, listen_s: float) -> tuple[dict[str, float], tuple[int, int] | None]:
    """Ask for auxgps's streams at its rates, then count what arrives over ``listen_s``: rates (Hz) and GPS1's last
    (fix type, satellites)."""
    for name, hz in STREAMS_HZ.items():
        ap.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, getattr(mav, f"MAVLINK_MSG_ID_{name}"), 1e6 / hz)
    settle = time.monotonic() + 1.0
    while time.monotonic() < settle:
        ap.recv(None, 0.2)
    counts = dict.fromkeys(STREAMS_HZ, 0)
    gps1 = None
    t0 = time.monotonic()
    while time.monotonic() - t0 < listen_s:
        msg = ap.recv(list(STREAMS_HZ), 0.2)
        if msg is None or msg.get_srcSystem() != ap.system:
            continue
        counts[msg.get_type()] += 1
        if msg.get_type() == "GPS_RAW_INT":
            gps1 = (int(msg.fix_type), int(msg.satellites_visible))
    elapsed = time.monotonic() - t0
    return {k: n / elapsed for k, n in counts.items()}, gps1


def _name(msg) -> str:
    pid = msg.param_id
    return (pid.decode("ascii", "replace") if isinstance(pid, bytes) else str(pid)).rstrip("\x00")


def observe(ap: Autopilot, wanted: dict[str, float], listen_s: float) -> Observed:
    version = read_version(ap)

    names = [param_names(version).get(n, n) for n in wanted]
    params = read_params(ap, names)
    stream_hz, gps1 = measure_streams(ap, listen_s)
    return Observed(version, params, stream_hz, gps1)


def load_wanted(path: Path = PARM_FILE) -> dict[str, float]:
    try:
        return read_parm_file(path.read_text())
    except OSError as err:
        raise ConfigError(f"{path}: cannot read the parameter file ({err.strerror or err})") from None
    except ValueError as err:
        raise ConfigError(f"{path}: {err}") from None


def fix(ap: Autopilot, findings: list[Finding]) -> list[str]:
    """Write every wrong parameter; the lines to print (one per parameter, and which need a reboot)."""

    lines, reboot = [], []
    for f in findings:
        for name, value in f.set_params.items():
            ok = set_param(ap, name, value)
            lines.append(f"  set {name} = {value:g}: {'done' if ok else 'NOT confirmed by the autopilot'}")
            if ok and name in NEEDS_REBOOT:
                reboot.append(name)
    if reboot:
        lines.append(f"  reboot the autopilot for {', '.join(reboot)} to take effect (or run again with --reboot)")
    return lines


def reboot(ap: Autopilot) -> None:
    ap.command(mav.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 1)
