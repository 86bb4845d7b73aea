"""The MAVLink link to the autopilot: one connection that reconnects when it drops.

Everything MAVLink is here: decoding the autopilot's messages into plain records (SI units, radians, one
clock), encoding GPS_INPUT and STATUSTEXT, the onboard-controller HEARTBEAT, stream requests. Messages from
other systems, and bytes that are not MAVLink, are ignored.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Callable

import numpy as np

os.environ.setdefault("MAVLINK20", "1")  # SIM_STATE's lat_int/lon_int are MAVLink 2 extension fields
from pymavlink import mavutil  # noqa: E402

from auxgps.core.events import Attitude, Gps1, Imu, Position  # noqa: E402  (re-exported: the link's records)
from auxgps.core.gps_output import GpsOutput  # noqa: E402
from auxgps.errors import LinkError  # noqa: E402

log = logging.getLogger(__name__)
mav = mavutil.mavlink
G_M_S2 = 9.80665

#: Streams auxgps asks for, message id -> rate (Hz).
STREAMS_HZ = {
    mav.MAVLINK_MSG_ID_ATTITUDE: 50.0,
    mav.MAVLINK_MSG_ID_SCALED_IMU: 50.0,
    mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 10.0,
    mav.MAVLINK_MSG_ID_GPS_RAW_INT: 5.0,
    mav.MAVLINK_MSG_ID_SYSTEM_TIME: 1.0,
    mav.MAVLINK_MSG_ID_HOME_POSITION: 0.5,
}
STREAMS_SILENT_S = 1.5  # no ATTITUDE for this long, the autopilot's HEARTBEAT coming: ask for the rates again
SIM_STREAMS_HZ = {mav.MAVLINK_MSG_ID_SIMSTATE: 20.0, mav.MAVLINK_MSG_ID_SIM_STATE: 20.0}  # raised to a simulated camera's rate


@dataclass(frozen=True)
class Truth:
    """A simulator's true pose (SIMSTATE / SIM_STATE). Only the simulated camera may use it."""

    t_s: float
    lat_deg: float
    lon_deg: float
    alt_amsl_m: float | None
    euler_rad: np.ndarray


class BootClock:
    """Maps the autopilot's boot-time stamps onto this process's monotonic clock.

    The offset is the smallest (arrival - stamp) seen over the last ``window_s`` of arrivals: the message that
    travelled fastest lately. A window, not all time: the autopilot's clock may run at another rate than ours
    (a simulator that falls behind real time does), and an offset fixed at the start would then drift away from
    the arrival times that frames and the GPS_INPUT timer live on.
    """

    def __init__(self, window_s: float = 2.0) -> None:
        self.window_s = window_s
        self._recent: deque = deque()  # (arrival_s, offset_s), offsets increasing from the left
        self._newest_boot_ms = -np.inf
        self.reboots = 0  # times the boot clock went back by more than a second: the autopilot restarted
        self.last_reboot_s: tuple[float, float] | None = None  # (boot time before, boot time after) the last one

    def to_local(self, time_boot_ms: int, arrival_s: float) -> float:
        if time_boot_ms < self._newest_boot_ms - 1000:
            # The autopilot rebooted: the old offset says nothing of the new boot clock (kept, it would stamp the
            # next window_s of messages its uptime in the past).
            self._recent.clear()
            self.reboots += 1
            self.last_reboot_s = (self._newest_boot_ms / 1000.0, time_boot_ms / 1000.0)
            log.warning("autopilot boot clock went back from %.1f to %.1f s: rebooted", self._newest_boot_ms / 1000, time_boot_ms / 1000)
            self._newest_boot_ms = -np.inf
        self._newest_boot_ms = max(self._newest_boot_ms, time_boot_ms)
        offset = arrival_s - time_boot_ms / 1000.0
        recent = self._recent
        while recent and recent[-1][1] >= offset:
            recent.pop()  # never the minimum again: a later arrival with a smaller offset
        recent.append((arrival_s, offset))
        while recent[0][0] < arrival_s - self.window_s:
            recent.popleft()
        return time_boot_ms / 1000.0 + recent[0][1]

    def boot_s(self, local_s: float) -> float | None:
        """A local time on the autopilot's boot clock, s (as its own log stamps it); None before the first message."""
        try:
            return local_s - self._recent[0][1]
        except IndexError:  # no arrival yet (or, read from another thread, just after a reboot cleared them)
            return None

    def unstamped(self, arrival_s: float, late_s: float = 0.025) -> float:
        """The local time of a message without a stamp of its own (SIM_STATE), sent in the stream of stamped ones:
        its arrival, unless that is more than ``late_s`` after the newest stamped message was sent (this process
        read late: a busy computer), then that send time plus ``late_s``. A frame rendered at such a message's pose
        keeps its moment as a camera's own timestamp would, not the moment a starved reader got to it."""
        if not self._recent or not np.isfinite(self._newest_boot_ms):
            return arrival_s
        sent_s = self._newest_boot_ms / 1000.0 + self._recent[0][1]
        return min(arrival_s, sent_s + late_s) if sent_s >= arrival_s - 1.0 else arrival_s

    def local(self, time_boot_ms: float) -> float | None:
        """An earlier boot-time stamp (a GPS fix's time) on the local clock, without taking it as an arrival;
        None before the first :meth:`to_local`."""
        return time_boot_ms / 1000.0 + self._recent[0][1] if self._recent else None


BOOT_TIME_MAX_US = 10 * 365 * 86400 * 1e6  # a time_usec below ten years is a boot time, above it UNIX time


def decode(msg, clock: BootClock, arrival_s: float):
    """One autopilot message -> a record, or None for messages auxgps does not use."""
    kind = msg.get_type()
    if kind == "ATTITUDE":
        return Attitude(clock.to_local(msg.time_boot_ms, arrival_s), np.array([msg.roll, msg.pitch, msg.yaw]),
                        np.array([msg.rollspeed, msg.pitchspeed, msg.yawspeed]))
    if kind == "SCALED_IMU":
        acc = np.array([msg.xacc, msg.yacc, msg.zacc], float) * G_M_S2 / 1000.0  # milli-g -> m/s^2
        return Imu(clock.to_local(msg.time_boot_ms, arrival_s), acc)
    if kind == "GPS_RAW_INT":
        h_acc = msg.h_acc / 1000.0 if getattr(msg, "h_acc", 0) else (msg.eph / 100.0 if msg.eph != 65535 else 99.0)
        # ArduPilot stamps the reading with the boot time of the fix (last_fix_time_ms), which may be up to one
        # GPS period before the message is sent; other autopilots send UNIX time, and then arrival must do.
        t_fix = clock.local(msg.time_usec / 1000.0) if 0 < msg.time_usec < BOOT_TIME_MAX_US else None
        t = min(t_fix, arrival_s) if t_fix is not None and t_fix >= arrival_s - 1.0 else arrival_s
        return Gps1(t, msg.fix_type, msg.satellites_visible, msg.lat / 1e7, msg.lon / 1e7, msg.alt / 1000.0, h_acc)
    if kind == "GLOBAL_POSITION_INT":
        t = clock.to_local(msg.time_boot_ms, arrival_s)
        return Position(t, msg.lat / 1e7, msg.lon / 1e7, msg.alt / 1000.0, msg.relative_alt / 1000.0)
    if kind == "SIM_STATE":
        lat = msg.lat_int / 1e7 if getattr(msg, "lat_int", 0) else msg.lat
        lon = msg.lon_int / 1e7 if getattr(msg, "lon_int", 0) else msg.lon
        return Truth(clock.unstamped(arrival_s), lat, lon, float(msg.alt), np.array([msg.roll, msg.pitch, msg.yaw]))
    if kind == "SIMSTATE":
        return Truth(clock.unstamped(arrival_s), msg.lat / 1e7, msg.lng / 1e7, None, np.array([msg.roll, msg.pitch, msg.yaw]))
    return None


class Decoder:
    """Turns the autopilot's messages into records, with the boot clock that stamps them on the local clock.

    Its state is the clock alone: a replay that hands it the same messages with the same arrival times gets the
    same records, to the bit.
    """

    def __init__(self) -> None:
        self.clock = BootClock()

    def __call__(self, msg, arrival_s: float):
        """A record, or None for a message auxgps does not use or cannot decode (logged)."""
        try:
            return decode(msg, self.clock, arrival_s)
        except (AttributeError, TypeError, ValueError) as err:
            log.warning("could not decode %s: %s", msg.get_type(), err)
            return None


@dataclass(frozen=True)
class LinkAddress:
    """Where the autopilot is: ``kind`` "tcp" (we connect), "tcpin", "udpin", "udpout" or "udp" with ``host`` and
    ``port``, or "serial" with ``device`` and ``baud``. ``url`` is what pymavlink opens."""

    kind: str
    url: str
    host: str = ""
    port: int = 0
    device: str = ""
    baud: int = 0


DEFAULT_BAUD = 57600  # ArduPilot's SERIALn_BAUD default for a telemetry port
_NET_KINDS = ("tcp", "tcpin", "udpin", "udpout", "udp")


def parse_link_url(url: str) -> LinkAddress:
    """``tcp:HOST:PORT``, ``tcpin:``, ``udpin:``, ``udpout:``, ``udp:`` likewise, or a serial device with an optional
    baud rate (``/dev/ttyAMA0,921600``, ``COM3,57600``). A malformed address is a :class:`LinkError` naming what is
    wrong."""
    url = url.strip()
    kind, sep, rest = url.partition(":")
    if sep and kind in _NET_KINDS:
        host, sep, port_text = rest.rpartition(":")
        if not sep or not host:
            raise LinkError(f"--connect {url!r}: expected {kind}:HOST:PORT")
        if not port_text.isdigit() or not 1 <= int(port_text) <= 65535:
            raise LinkError(f"--connect {url!r}: port {port_text!r} is not a number from 1 to 65535")
        return LinkAddress(kind, url, host=host, port=int(port_text))
    if url.startswith("/") or url.upper().startswith("COM"):
        device, sep, baud_text = url.partition(",")
        if sep and (not baud_text.isdigit() or int(baud_text) <= 0):
            raise LinkError(f"--connect {url!r}: baud rate {baud_text!r} is not a positive whole number")
        baud = int(baud_text) if sep else DEFAULT_BAUD
        return LinkAddress("serial", f"{device},{baud}", device=device, baud=baud)
    raise LinkError(f"--connect {url!r}: not an address auxgps knows: tcp:HOST:PORT, udpin:HOST:PORT, udpout:HOST:PORT, "
                    "or a serial device such as /dev/ttyAMA0,921600")


class MavLink:
    """A MAVLink connection (see :func:`parse_link_url` for the addresses).

    :meth:`open` makes the first connection in the caller's thread, so that a bad address, a missing device, no
    permission or a refused connection is a :class:`LinkError` at start. A reader thread then hands every message
    from the autopilot (the first system whose HEARTBEAT says ArduPilot) to ``on_message(msg, arrival_s)``, arrival
    on the monotonic clock rounded to the microsecond (what a tlog keeps). When the link fails (a device unplugged,
    TCP closed) or no HEARTBEAT comes from the autopilot for ``timeout_s``, it is logged and reconnected with
    back-off, and its return is logged. Bytes that are not MAVLink are counted (``n_bad_data``) and skipped. If
    the reader itself dies, ``failure`` holds why, and the companion stops. When the autopilot's HEARTBEAT comes
    but no ATTITUDE for ``STREAMS_SILENT_S``, the message rates are asked for again (``stream_requests``): an
    autopilot that restarted forgets them (a copter then streams nothing else), and another program on the link
    may have changed them.
    """

    def __init__(self, url: str, on_message: Callable[[object, float], None], *, sim: bool = False, timeout_s: float = 3.0,
                 source_system: int = 1, source_component: int = mav.MAV_COMP_ID_ONBOARD_COMPUTER, sim_hz: float = 20.0) -> None:
        self.address = parse_link_url(url)
        self.url = self.address.url
        self.on_message = on_message
        self.sim = sim
        self.sim_hz = sim_hz  # the simulator's truth (SIM_STATE), for a simulated camera: at least its frame rate
        self.timeout_s = timeout_s
        self.source_system, self.source_component = source_system, source_component
        self.target_system: int | None = None
        self.connected = threading.Event()
        self.reconnects = 0
        self.n_bad_data = 0
        self.failure: BaseException | None = None
        self._lost_at: float | None = None
        self._send_failing = False
        self._last_heartbeat = 0.0
        self._attitude_s = 0.0  # the newest ATTITUDE's arrival, monotonic s
        self._streams_asked_s = 0.0  # when the message rates were last asked for
        self._streams_silent_said = False
        self.stream_requests = 0
        self._conn = None
        self._send_lock = threading.Lock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []

    # -- lifecycle ------------------------------------------------------------------------------------------

    def open(self, timeout_s: float = 15.0) -> None:
        """Connect now, trying for up to ``timeout_s`` while the other end is not there yet (refused, or a device
        not yet present); a :class:`LinkError` naming the reason after that, or at once for no permission."""
        deadline = time.monotonic() + timeout_s
        while True:
            err = self._try_open()
            if err is None:
                return
            if isinstance(err, PermissionError):
                raise LinkError(f"--connect {self.url}: permission denied ({err.strerror or err}); on Linux add the user to "
                                "the dialout group, or run as a user that may open it")
            if time.monotonic() >= deadline:
                if self.address.kind == "serial" and not os.path.exists(self.address.device):
                    raise LinkError(f"--connect {self.url}: no such device {self.address.device}")
                reason = "connection refused" if isinstance(err, ConnectionRefusedError) else f"{type(err).__name__}: {err}"
                raise LinkError(f"--connect {self.url}: cannot connect for {timeout_s:g} s ({reason})")
            time.sleep(0.2)

    def start(self) -> None:
        for target in (self._read_loop, self._heartbeat_loop):
            th = threading.Thread(target=target, daemon=True, name=f"mavlink-{target.__name__}")
            th.start()
            self._threads.append(th)

    def stop(self) -> None:
        self._stop.set()
        self._close()
        for th in self._threads:
            th.join(timeout=2.0)

    def _try_open(self) -> BaseException | None:
        """Open the connection; None on success, else the error (the connection stays closed)."""
        import serial  # pyserial, which pymavlink opens serial devices with

        kwargs = dict(source_system=self.source_system, source_component=self.source_component, autoreconnect=False)
        if self.address.kind == "tcp":
            kwargs["retries"] = 0  # one attempt: the back-off is ours
        try:
            self._conn = mavutil.mavlink_connection(self.url, **kwargs)
        except (OSError, serial.SerialException) as err:
            self._conn = None
            cause = err
            if isinstance(err, serial.SerialException) and isinstance(err.__context__, OSError):
                cause = err.__context__
            if isinstance(cause, OSError) and cause.errno == 13:
                return PermissionError(cause.errno, cause.strerror)
            return cause
        self.target_system = None
        self._last_heartbeat = time.monotonic()
        return None

    def _open(self) -> bool:
        err = self._try_open()
        if err is not None:
            log.info("link %s not available (%s); retrying", self.url, err)
            return False
        return True

    def _close(self) -> None:
        conn, self._conn = self._conn, None
        self.connected.clear()
        if conn is not None:
            try:
                conn.close()
            except OSError:
                pass

    # -- reading --------------------------------------------------------------------------------------------

    def _read_loop(self) -> None:
        try:
            self._read_until_stopped()
        except BaseException as err:  # noqa: BLE001 - a reader that dies must say so, not leave the process deaf
            self.failure = err
            log.exception("the link's reader stopped")

    def _lost(self, why: str) -> None:
        log.warning("link %s %s; reconnecting", self.url, why)
        if self._lost_at is None:
            self._lost_at = time.monotonic()

    def _read_until_stopped(self) -> None:
        backoff = 0.2
        while not self._stop.is_set():
            if self._conn is None:
                if not self._open():
                    self._stop.wait(backoff)
                    backoff = min(backoff * 2, 0.5)  # a link back is in use again within half a second
                    continue
                backoff = 0.2
            while not self._stop.is_set() and self._conn is not None:
                try:
                    msg = self._conn.recv_match(blocking=True, timeout=0.2)
                except (OSError, ConnectionError) as err:
                    self._lost(f"failed: {err}")
                    break
                now = round(time.monotonic() * 1e6) / 1e6
                if now - self._last_heartbeat > self.timeout_s:
                    self._lost(f"without a HEARTBEAT from the autopilot for {now - self._last_heartbeat:.1f} s")
                    break
                if msg is None:
                    if self._closed_by_peer():
                        self._lost("closed by the other end")
                        break
                    continue
                try:
                    self._handle(msg, now)
                except Exception:  # noqa: BLE001 - one bad message or handler bug must not end the link
                    log.exception("handling %s failed; continuing", msg.get_type())
            self._close()
            if not self._stop.is_set():
                self.reconnects += 1

    def _handle(self, msg, now: float) -> None:
        kind = msg.get_type()
        if kind == "BAD_DATA":
            self.n_bad_data += 1
            if self.n_bad_data in (1, 10, 100) or self.n_bad_data % 1000 == 0:
                log.info("link %s: %d stretches of bytes that are not MAVLink skipped so far", self.url, self.n_bad_data)
            return
        src = msg.get_srcSystem()
        if kind == "HEARTBEAT" and self.target_system is None and msg.autopilot == mav.MAV_AUTOPILOT_ARDUPILOTMEGA:
            self.target_system = src
            self.connected.set()
            self.request_streams(now)
            log.info("autopilot is system %d on %s", src, self.url)
            if self._lost_at is not None:
                log.warning("link %s back after %.1f s", self.url, now - self._lost_at)
                self.send_statustext(f"auxgps: link back after {now - self._lost_at:.1f} s", mav.MAV_SEVERITY_WARNING)
                self._lost_at = None
        if src != self.target_system:
            return  # another system on the link
        if kind == "HEARTBEAT":
            self._last_heartbeat = now
            self._ask_again_if_silent(now)
        elif kind == "ATTITUDE":
            self._attitude_s = now
            self._streams_silent_said = False
        self.on_message(msg, now)

    def _ask_again_if_silent(self, now: float) -> None:
        silent_s = now - self._attitude_s
        if now - max(self._attitude_s, self._streams_asked_s) <= STREAMS_SILENT_S:
            return
        if not self._streams_silent_said:
            log.warning("link %s: no ATTITUDE for %.1f s while the autopilot's HEARTBEAT comes (restarted, or another "
                        "program changed its message rates): asking for them again", self.url, silent_s)
            self._streams_silent_said = True
        self.request_streams(now)

    # -- writing --------------------------------------------------------------------------------------------

    def _closed_by_peer(self) -> bool:
        """True when a TCP connection has been closed by the other end (pymavlink reads that as no data)."""
        import select
        import socket

        sock = getattr(self._conn, "port", None)
        if not isinstance(sock, socket.socket):
            return False
        try:
            readable, _, _ = select.select([sock], [], [], 0)
            return bool(readable) and sock.recv(1, socket.MSG_PEEK) == b""
        except (OSError, ValueError):
            return True

    def _send(self, build: Callable) -> bool:
        conn = self._conn
        if conn is None:
            return False
        try:
            with self._send_lock:
                conn.mav.send(build(conn.mav))
            self._send_failing = False
            return True
        except (OSError, ConnectionError) as err:
            if not self._send_failing:  # once per outage, not ten times a second
                log.warning("send on %s failed: %s", self.url, err)
            self._send_failing = True
            return False

    def _heartbeat_loop(self) -> None:
        while not self._stop.wait(1.0):
            self._send(lambda m: m.heartbeat_encode(mav.MAV_TYPE_ONBOARD_CONTROLLER, mav.MAV_AUTOPILOT_INVALID, 0, 0, mav.MAV_STATE_ACTIVE))

    def request_streams(self, now_s: float | None = None) -> None:
        """Ask for every message auxgps reads at its rate (SET_MESSAGE_INTERVAL); ``now_s`` on the monotonic clock."""
        self._streams_asked_s = time.monotonic() if now_s is None else now_s
        self.stream_requests += 1
        streams = {**STREAMS_HZ, **({i: max(hz, self.sim_hz) for i, hz in SIM_STREAMS_HZ.items()} if self.sim else {})}
        for msg_id, hz in streams.items():
            self._send(lambda m, i=msg_id, h=hz: m.command_long_encode(
                self.target_system or 1, 1, mav.MAV_CMD_SET_MESSAGE_INTERVAL, 0, i, 1e6 / h, 0, 0, 0, 0, 0))

    def send_gps_input(self, out: GpsOutput, time_usec: int) -> bool:
        ignore = 0  # every field is real; velocity included (ArduPilot issue 19633)
        return self._send(lambda m: m.gps_input_encode(
            time_usec, 1, ignore, out.time_week_ms, out.time_week, out.fix_type,
            int(round(out.lat_deg * 1e7)), int(round(out.lon_deg * 1e7)), float(out.alt_amsl_m),
            float(out.hdop), float(out.vdop), *(float(v) for v in out.vel_ned_m_s),
            float(out.speed_accuracy_m_s), float(out.horiz_accuracy_m), float(out.vert_accuracy_m), int(out.satellites), 0))

    def send_param_set(self, name: str, value: float) -> bool:
        """PARAM_SET of one of the autopilot's parameters (its PARAM_VALUE echo comes to ``on_message``)."""
        return self._send(lambda m: m.param_set_encode(self.target_system or 1, 1, name.encode(), float(value),
                                                        mav.MAV_PARAM_TYPE_REAL32))

    def send_param_request(self, name: str) -> bool:
        return self._send(lambda m: m.param_request_read_encode(self.target_system or 1, 1, name.encode(), -1))

    def send_statustext(self, text: str, severity: int = mav.MAV_SEVERITY_INFO) -> bool:
        return self._send(lambda m: m.statustext_encode(severity, text[:50].encode("ascii", "replace")))
