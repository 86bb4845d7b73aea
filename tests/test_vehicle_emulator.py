"""The vehicle emulator (auxgps.sim.emulator): its ArduPilot rules, then two flights over loopback TCP.

Unit tests drive the pure part with emulated times; the end-to-end tests start the emulator as a process,
talk MAVLink 2 to it with pymavlink and read its JSON log. Every process is killed at the end of its test.
"""

from __future__ import annotations

import json
import math
import os
import random
import socket
import subprocess
import sys
import time
import types
from pathlib import Path

import numpy as np
import pytest

os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil  # noqa: E402

from auxgps.core.geometry import LocalFrame  # noqa: E402
import auxgps.sim.emulator as emu  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
WORLD = REPO / "config" / "worlds" / "one_cube_1m.yaml"


MAV = emu.MAV
FRAME = LocalFrame(47.397742, 8.545594, 488.0)

atol_e7_m = 0.006  # half of 1e-7 degree of latitude (1.1 cm): the rounding of MAVLink's lat/lon
atol_t_s = 1e-9


def _reading(fix: int, sats: int, p_ned_m=(0.0, 0.0, 0.0)) -> "emu.GpsReading":
    return emu.GpsReading(fix, 0, 0, 488.0, np.asarray(p_ned_m, float), np.zeros(3), sats, 0.3)


def _feed(instance, times_s, fix=3, sats=10) -> None:
    for t in times_s:
        instance.on_message(float(t), _reading(fix, sats))


def _gps_input(p_ned_m, v_ned_m_s=(0.0, 0.0, 0.0), *, gps_id=1, fix=3, sats=8, ignore_flags=0):
    lat, lon, alt = FRAME.to_geodetic(np.asarray(p_ned_m, float))
    return types.SimpleNamespace(gps_id=gps_id, ignore_flags=ignore_flags, fix_type=fix, lat=emu._e7(lat),
                                 lon=emu._e7(lon), alt=float(alt), vn=v_ned_m_s[0], ve=v_ned_m_s[1],
                                 vd=v_ned_m_s[2], horiz_accuracy=0.3, satellites_visible=sats)


# ------------------------------------------------------------------------------------------------------------
# GPS_INPUT intake


def test_gps_input_with_another_gps_id_is_dropped():
    sim = emu.VehicleSim(FRAME, emu.EmulatorOptions())
    assert not sim.handle_gps_input(_gps_input((1.0, 2.0, -3.0), gps_id=0))
    assert not sim.handle_gps_input(_gps_input((1.0, 2.0, -3.0), gps_id=2))
    assert sim.gps[1].reading(sim.t_s) is None
    assert sim.gps_input_dropped == 2
    assert sim.handle_gps_input(_gps_input((1.0, 2.0, -3.0), gps_id=1))
    assert sim.gps_input_arrivals_t_s == [0.0]


def test_gps_input_is_dropped_when_gps2_is_not_a_mavlink_gps():
    sim = emu.VehicleSim(FRAME, emu.EmulatorOptions(gps2_type=0))
    assert not sim.handle_gps_input(_gps_input((1.0, 2.0, -3.0)))
    assert sim.gps[1].fix_type(sim.t_s) == emu.FIX_NO_GPS


def test_gps_input_position_round_trips_through_the_local_frame():
    p_ned_m = np.array([12.3, -45.6, -7.8])
    reading = emu.gps_input_to_reading(_gps_input(p_ned_m, (1.0, -2.0, 0.5)), FRAME, None)
    np.testing.assert_allclose(reading.p_ned_m, p_ned_m, atol=atol_e7_m)
    np.testing.assert_allclose(reading.v_ned_m_s, [1.0, -2.0, 0.5])
    assert (reading.fix_type, reading.satellites, reading.h_acc_m) == (3, 8, 0.3)


def test_gps_input_ignore_flags_as_ardupilot():
    previous = emu.gps_input_to_reading(_gps_input((0, 0, -5), (1.0, 1.0, 0.0)), FRAME, None)
    flags = emu.GPS_INPUT_IGNORE_ALT | emu.GPS_INPUT_IGNORE_VEL_HORIZ
    reading = emu.gps_input_to_reading(_gps_input((0, 0, -5), (9.0, 9.0, 9.0), ignore_flags=flags), FRAME, previous)
    assert reading.alt_amsl_m == 0.0  # ArduPilot zeroes an ignored altitude
    assert reading.p_ned_m[2] == pytest.approx(488.0, abs=0.01)
    np.testing.assert_allclose(reading.v_ned_m_s, [1.0, 1.0, 0.0])  # the previous velocity stays


# ------------------------------------------------------------------------------------------------------------
# Health and timeout


def test_steady_5hz_is_healthy_and_4hz_is_not():
    five_hz, four_hz = emu.GpsInstance(), emu.GpsInstance()
    _feed(five_hz, np.arange(0, 5, 0.2))
    _feed(four_hz, np.arange(0, 5, 0.25))
    assert five_hz.healthy(4.85)
    assert not four_hz.healthy(4.85)


def test_health_needs_three_messages():
    gps = emu.GpsInstance()
    _feed(gps, [0.0, 0.2])
    assert not gps.healthy(0.25)
    _feed(gps, [0.4])
    assert gps.healthy(0.45)


def test_one_late_message_is_tolerated_two_in_a_row_are_not():
    gps = emu.GpsInstance()
    _feed(gps, np.arange(0, 4.01, 0.2))
    _feed(gps, [4.3])  # one 300 ms gap: mean over the window 210 ms, one late in a row
    assert gps.healthy(4.3)
    _feed(gps, [4.6])  # a second in a row
    assert not gps.healthy(4.6)
    _feed(gps, [4.8])  # on time again, but the window's mean is still over 215 ms
    assert not gps.healthy(4.8)
    _feed(gps, np.arange(5.0, 7.01, 0.2))  # both late intervals have left the window
    assert gps.healthy(7.0)


def test_four_seconds_of_silence_mean_no_fix():
    gps = emu.GpsInstance()
    _feed(gps, np.arange(0, 2.01, 0.2), fix=3, sats=9)
    assert (gps.fix_type(5.9), gps.satellites(5.9), gps.healthy(5.9)) == (3, 9, True)
    assert (gps.fix_type(6.01), gps.satellites(6.01), gps.healthy(6.01)) == (emu.FIX_NONE, 0, False)
    assert gps.selection_fix(6.01) == emu.FIX_NONE
    _feed(gps, [6.5, 6.7])  # back, but the history starts again
    assert gps.fix_type(6.7) == 3 and not gps.healthy(6.7)


def test_an_unhealthy_instance_counts_as_no_fix_for_selection():
    gps = emu.GpsInstance()
    _feed(gps, np.arange(0, 3, 0.25), fix=3)
    assert gps.fix_type(2.8) == 3
    assert gps.selection_fix(2.8) == emu.FIX_NONE
    assert not gps.usable(2.8)


# ------------------------------------------------------------------------------------------------------------
# Primary selection (AP_GPS::update_primary)

BOTH = (True, True)


def test_use_best_keeps_rtk_gps1_over_a_3d_gps2_and_switches_at_once_when_it_fails():
    sel = emu.PrimarySelector()
    for t in np.arange(0, 60, 0.1):
        assert sel.update(t, (6, 3), (10, 6), BOTH, auto_switch=1, primary_param=0) == 0
    assert sel.update(60.0, (0, 3), (3, 6), BOTH, auto_switch=1, primary_param=0) == 1
    assert sel.last_swap_t_s == 60.0


def test_more_satellites_at_equal_fix_take_over_only_after_20_s_or_5_s():
    one_more, two_more = emu.PrimarySelector(), emu.PrimarySelector()
    for t in (0.0, 4.99, 19.99):
        assert one_more.update(t, (3, 3), (8, 9), BOTH, 1, 0) == 0
    assert one_more.update(20.0, (3, 3), (8, 9), BOTH, 1, 0) == 1
    assert two_more.update(4.99, (3, 3), (8, 10), BOTH, 1, 0) == 0
    assert two_more.update(5.0, (3, 3), (8, 10), BOTH, 1, 0) == 1
    # the clock restarts at each switch: GPS1 with 2 more satellites needs 5 s again
    assert two_more.update(9.99, (3, 3), (12, 10), BOTH, 1, 0) == 1
    assert two_more.update(10.0, (3, 3), (12, 10), BOTH, 1, 0) == 0


def test_blend_acts_as_use_best():
    sel = emu.PrimarySelector()
    assert sel.update(1.0, (1, 3), (10, 6), BOTH, auto_switch=2, primary_param=0) == 1


def test_use_primary_if_3d_holds_gps1_while_it_has_a_3d_fix():
    best, primary_if_3d = emu.PrimarySelector(), emu.PrimarySelector()
    assert best.update(30.0, (3, 6), (6, 20), BOTH, auto_switch=1, primary_param=0) == 1
    assert primary_if_3d.update(30.0, (3, 6), (6, 20), BOTH, auto_switch=4, primary_param=0) == 0
    assert primary_if_3d.update(31.0, (1, 3), (3, 8), BOTH, auto_switch=4, primary_param=0) == 1
    assert primary_if_3d.update(31.2, (3, 6), (6, 20), BOTH, auto_switch=4, primary_param=0) == 0


def test_use_primary_never_switches():
    sel = emu.PrimarySelector()
    assert sel.update(100.0, (0, 6), (0, 20), BOTH, auto_switch=0, primary_param=0) == 0
    assert sel.update(100.0, (6, 0), (20, 0), BOTH, auto_switch=0, primary_param=1) == 1
    assert sel.update(100.0, (6, 0), (20, 0), (True, False), auto_switch=0, primary_param=1) == 0


# ------------------------------------------------------------------------------------------------------------
# Estimate, dead reckoning and failsafe


def test_dead_reckoning_for_2_s_then_frozen_then_failsafe_at_8_s():
    nav = emu.NavEstimator()
    assert not nav.failsafe_due(100.0)  # never had a fix: nothing to lose
    nav.on_fix(10.0, np.array([1.0, 2.0]), np.array([1.0, -0.5]))
    p, v = nav.horizontal(11.5)
    np.testing.assert_allclose(p, [2.5, 1.25])
    np.testing.assert_allclose(v, [1.0, -0.5])
    assert nav.has_reference(12.0) and not nav.has_reference(12.01)
    for t in (12.01, 15.0, 17.99):
        p, v = nav.horizontal(t)
        np.testing.assert_allclose(p, [3.0, 1.0])
        np.testing.assert_allclose(v, [0.0, 0.0])
        assert not nav.failsafe_due(t)
    assert nav.failsafe_due(18.0)
    assert nav.state(11.0) == "dead_reckoning" and nav.state(13.0) == "frozen" and nav.state(10.2) == "gps"


def test_a_fix_before_the_failsafe_restores_normal_navigation():
    nav = emu.NavEstimator()
    nav.on_fix(0.0, np.zeros(2), np.zeros(2))
    nav.on_fix(7.9, np.array([5.0, 5.0]), np.array([0.2, 0.0]))
    assert not nav.failsafe_due(15.0)
    assert nav.state(7.95) == "gps"
    np.testing.assert_allclose(nav.horizontal(8.0)[0], [5.02, 5.0])


def test_failsafe_in_the_vehicle_when_gps1_fails_without_gps2():
    sim = emu.VehicleSim(FRAME, emu.EmulatorOptions(altitude_m=3, survey_size_m=2, gps2_type=0, fail_gps1_at_s=5))
    while not sim.failsafe and sim.t_s < 60:
        sim.step()
    failsafe_t_s = sim.t_s - sim.dt_s
    # 8 s after the last usable fix was measured: GPS1 (5 Hz) sent it up to 0.2 s before the failure, describing
    # the vehicle GPS1_LAG_S before it was sent
    assert 8.0 - 0.2 - emu.GPS1_LAG_S - atol_t_s <= failsafe_t_s - sim.failure_t_s < 8.0 - emu.GPS1_LAG_S + atol_t_s
    assert sim.mode is emu.CopterMode.LAND
    assert (MAV.MAV_SEVERITY_CRITICAL, "EKF Failsafe: changed to LAND Mode") in sim.outbox


# ------------------------------------------------------------------------------------------------------------
# Arming, streams, statistics


def test_prearm_reasons_in_ardupilots_order():
    gps1, gps2 = emu.GpsInstance(), emu.GpsInstance()
    _feed(gps1, np.arange(0, 2, 0.2), fix=6)
    assert emu.prearm_gps_failure((gps1, gps2), (True, True), 1.9) == "GPS 2: Bad fix"
    assert emu.prearm_gps_failure((gps1, gps2), (True, False), 1.9) is None
    for t in np.arange(0, 2, 0.2):
        gps2.on_message(float(t), _reading(3, 8, (30.0, 40.0, 0.0)))
    assert emu.prearm_gps_failure((gps1, gps2), (True, True), 1.9) == "GPS positions differ by 50.0m"
    slow = emu.GpsInstance()
    _feed(slow, np.arange(0, 2, 0.3))
    assert emu.prearm_gps_failure((gps1, slow), (True, True), 1.9) == "GPS 2: not healthy"


def test_stream_scheduler_rates_and_changes():
    sched = emu.StreamScheduler({"A": 10.0, "B": 1.0})
    sent = [name for t in np.arange(0, 1.0, 0.01) for name in sched.due(round(t, 2))]
    assert (sent.count("A"), sent.count("B")) == (10, 1)
    sched.set_interval("A", None, 1.0)
    sched.set_interval("B", 0.5, 1.0)
    sent = [name for t in np.arange(1.0, 2.0, 0.01) for name in sched.due(round(t, 2))]
    assert (sent.count("A"), sent.count("B")) == (0, 2)


def test_gps_input_stats_known_answer():
    stats = emu.gps_input_stats([0.0, 0.1, 0.2, 0.5, 0.8, 0.9, 1.2])
    assert stats["mean_interval_ms"] == pytest.approx(200.0)
    assert stats["max_interval_ms"] == pytest.approx(300.0)
    assert stats["consecutive_gaps_over_245ms"] == 2


def test_scaled_imu_reads_minus_one_g_on_the_ground():
    sim = emu.VehicleSim(FRAME, emu.EmulatorOptions())
    f_body = sim.specific_force_body_m_s2()
    np.testing.assert_allclose(f_body, [0.0, 0.0, -emu.GRAVITY_M_S2])


# ------------------------------------------------------------------------------------------------------------
# End to end, over loopback TCP

WALL_TIMEOUT_S = 45.0


def _port_is_free(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


class Emulator:
    """The emulator as a process on a free port; always killed on exit."""

    def __init__(self, tmp_path: Path, *args: str) -> None:
        self.log_path = tmp_path / "emulator.json"
        self.stderr_path = tmp_path / "emulator.stderr"
        self.args = args
        self.proc: subprocess.Popen | None = None
        self.port = 0

    def __enter__(self) -> "Emulator":
        rng = random.Random()
        for _ in range(8):
            port = rng.randint(20000, 60999)
            if _port_is_free(port) and self._start(port):
                return self
        raise RuntimeError(f"the emulator did not start; see {self.stderr_path}")

    def _start(self, port: int) -> bool:
        cmd = [sys.executable, "-m", "auxgps.sim.emulator", "--port", str(port), "--world", str(WORLD),
               "--log", str(self.log_path), *self.args]
        with open(self.stderr_path, "ab") as err:
            self.proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err, cwd=REPO)
        deadline = time.monotonic() + 20.0
        while time.monotonic() < deadline and self.proc.poll() is None:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=0.2).close()  # a first client, at once gone
                self.port = port
                return True
            except OSError:
                time.sleep(0.05)
        self._kill()
        return False

    def wait(self, timeout_s: float) -> int:
        return self.proc.wait(timeout=timeout_s)

    def read_log(self) -> dict:
        return json.loads(self.log_path.read_text())

    def _kill(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=10)

    def __exit__(self, *exc) -> None:
        self._kill()


def _connect(port: int):
    return mavutil.mavlink_connection(f"tcp:127.0.0.1:{port}", source_system=255, source_component=190,
                                      retries=3, reconnect_delay=0.2)


class GroundStation:
    """The test's side of the link: records what it sees and feeds GPS_INPUT from SIM_STATE's truth."""

    def __init__(self, conn) -> None:
        self.conn = conn
        self.t_s = 0.0  # emulated, from time_boot_ms
        self.seen: dict[str, list] = {}
        self.truth = None

    def pump(self, on_message=None, until=None, timeout_s: float = WALL_TIMEOUT_S, proc=None) -> None:
        """Read messages until ``until()`` holds, the process ends or ``timeout_s`` passes (which fails)."""
        deadline = time.monotonic() + timeout_s
        while until is None or not until():
            if proc is not None and proc.poll() is not None:
                return
            assert time.monotonic() < deadline, "timed out waiting for the emulator"
            try:
                msg = self.conn.recv_msg()
            except ConnectionResetError:
                # The emulator ended (its flight over) between the poll above and this read, with the test's own
                # GPS_INPUT unread in its socket: the end of the flight arrives as a reset, not as a closed link.
                if proc is None:
                    raise
                proc.wait(timeout=10)
                return
            if msg is None:
                time.sleep(0.0005)
                continue
            kind = msg.get_type()
            if hasattr(msg, "time_boot_ms"):
                self.t_s = msg.time_boot_ms * 1e-3
            if kind == "SIM_STATE":
                self.truth = msg
            self.seen.setdefault(kind, []).append((self.t_s, msg))
            if on_message is not None:
                on_message(msg)

    def last(self, kind: str):
        return self.seen[kind][-1][1] if self.seen.get(kind) else None

    def texts(self) -> list[str]:
        return [m.text for _, m in self.seen.get("STATUSTEXT", [])]

    def send_gps_input(self, gps_id: int = 1) -> None:
        s = self.truth
        self.conn.mav.gps_input_send(0, gps_id, 0, 0, 0, 3, s.lat_int, s.lon_int, s.alt, 0.8, 1.2,
                                     s.vn, s.ve, s.vd, 0.2, 0.3, 0.5, 8)


def _set_interval(gcs: GroundStation, name: str, interval_us: float) -> None:
    msg_id = getattr(MAV, f"MAVLINK_MSG_ID_{name}")
    gcs.conn.mav.command_long_send(1, 1, MAV.MAV_CMD_SET_MESSAGE_INTERVAL, 0, msg_id, interval_us, 0, 0, 0, 0, 0)


def _acks(gcs: GroundStation) -> list[int]:
    return [m.result for _, m in gcs.seen.get("COMMAND_ACK", []) if m.command == MAV.MAV_CMD_SET_MESSAGE_INTERVAL]


def _params(gcs: GroundStation) -> dict[str, float]:
    return {m.param_id: m.param_value for _, m in gcs.seen.get("PARAM_VALUE", [])}


@pytest.mark.realtime
def test_end_to_end_gps_input_carries_the_flight_home_after_gps1_fails(tmp_path):
    with Emulator(tmp_path, "--speedup", "10", "--altitude", "5", "--survey-size", "4", "--max-seconds", "200") as em:
        # a client that comes and goes: the emulator must take the next one
        first = _connect(em.port)
        GroundStation(first).pump(until=lambda: first.messages.get("HEARTBEAT") is not None, timeout_s=10)
        first.close()
        conn = _connect(em.port)
        gcs = GroundStation(conn)
        conn.write(bytes(range(256)) + b"\x00" * 300)  # garbage on the link
        conn.mav.heartbeat_send(MAV.MAV_TYPE_GCS, MAV.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        conn.mav.param_request_read_send(1, 1, b"GPS2_TYPE", -1)
        _set_interval(gcs, "ATTITUDE", 40_000)  # 25 Hz
        gcs.pump(until=lambda: all(gcs.last(k) is not None for k in ("SIM_STATE", "SIMSTATE", "SCALED_IMU")),
                 timeout_s=10)
        imu_on_ground, simstate, sim_state = gcs.last("SCALED_IMU"), gcs.last("SIMSTATE"), gcs.last("SIM_STATE")
        _set_interval(gcs, "SCALED_IMU", -1)
        _set_interval(gcs, "SIMSTATE", -1)  # the same truth as SIM_STATE: spare the test's parser
        t_imu_off_s = gcs.t_s
        for _ in range(5):
            gcs.send_gps_input(gps_id=0)  # the wrong instance: dropped

        flight = {"next_gps_t_s": gcs.t_s, "auto_since_s": None, "failed_at_s": None}

        def fly(msg) -> None:  # GPS_INPUT at 10 Hz of emulated time; GPS1 failed after 3 s of the survey
            if gcs.truth is not None and gcs.t_s >= flight["next_gps_t_s"]:
                gcs.send_gps_input()
                flight["next_gps_t_s"] = max(flight["next_gps_t_s"] + 0.1, gcs.t_s + 0.05)
            in_auto = msg.get_type() == "HEARTBEAT" and msg.custom_mode == emu.CopterMode.AUTO
            if in_auto and flight["auto_since_s"] is None:
                flight["auto_since_s"] = gcs.t_s
            auto_since_s = flight["auto_since_s"]
            if auto_since_s is not None and flight["failed_at_s"] is None and gcs.t_s > auto_since_s + 3:
                conn.mav.param_set_send(1, 1, b"SIM_GPS1_ENABLE", 0, MAV.MAV_PARAM_TYPE_INT8)
                flight["failed_at_s"] = gcs.t_s

        gcs.pump(fly, proc=em.proc)
        assert em.wait(timeout_s=10) == 0
        record = em.read_log()

    # the flight
    assert record["exit_reason"] == "landed"
    assert record["landing_error_m"] < 1.0
    events = [e["event"] for e in record["events"]]
    assert "gps1_failed" in events and "failsafe" not in events
    assert 0.0 <= record["switch_to_gps2_t_s"] - record["failure_t_s"] <= 0.25  # at once: GPS1's next message
    armed = [s for s in record["samples"] if s["armed"]]
    err_m = [math.dist(s["truth_ned_m"][:2], s["estimate_ned_m"][:2]) for s in armed]
    # a loaded test machine delays some GPS_INPUT, which the vehicle then reads late: judge the bulk
    assert np.percentile(err_m, 90) < 0.3
    assert {s["mode"] for s in armed} >= {"GUIDED", "AUTO", "RTL"}
    assert all(s["primary"] == 1 for s in armed if s["t_s"] > record["switch_to_gps2_t_s"])
    # GPS_INPUT as the emulator saw it
    assert record["gps_input_dropped"] == 5
    assert 80.0 < record["gps_input"]["mean_interval_ms"] < 130.0
    assert record["link"]["errors"] == 0 and record["link"]["connections"] >= 3
    # what the client saw
    heartbeat = gcs.last("HEARTBEAT")
    assert (heartbeat.type, heartbeat.autopilot) == (MAV.MAV_TYPE_QUADROTOR, MAV.MAV_AUTOPILOT_ARDUPILOTMEGA)
    assert not heartbeat.base_mode & MAV.MAV_MODE_FLAG_SAFETY_ARMED  # disarmed after landing
    assert _params(gcs)["GPS2_TYPE"] == 14 and _params(gcs)["SIM_GPS1_ENABLE"] == 0
    assert _acks(gcs)[:3] == [MAV.MAV_RESULT_ACCEPTED] * 3
    assert (simstate.lat, simstate.lng) == (sim_state.lat_int, sim_state.lon_int)  # on the ground, at home
    assert sim_state.lat == float(np.float32(sim_state.lat_int))  # SITL's quirk: the float holds deg * 1e7 too
    assert imu_on_ground.zacc == pytest.approx(-1000, abs=60)  # milli-g, FRD at rest
    assert not [t for t, _ in gcs.seen.get("SCALED_IMU", []) if t > t_imu_off_s + 1.0]
    attitude_t_s = [t for t, _ in gcs.seen["ATTITUDE"] if t_imu_off_s + 1.0 <= t < t_imu_off_s + 5.0]
    assert 80 <= len(attitude_t_s) <= 120  # 25 Hz for 4 s, not the default 50 Hz
    gps1_fixes = [(t, m.fix_type) for t, m in gcs.seen["GPS_RAW_INT"]]
    assert any(fix == 6 for t, fix in gps1_fixes if t < flight["failed_at_s"])
    assert any(fix == 0 for t, fix in gps1_fixes if t > flight["failed_at_s"] + 0.5)
    assert any(m.fix_type == 3 for _, m in gcs.seen["GPS2_RAW"])
    assert "EMU: GPS primary now GPS 2" in gcs.texts()


@pytest.mark.realtime
def test_end_to_end_without_gps_input_the_vehicle_fails_safe_and_lands_away_from_home(tmp_path):
    args = ("--speedup", "10", "--altitude", "5", "--survey-size", "4", "--gps2-type", "0", "--fail-gps1-at", "8",
            "--max-seconds", "200")
    with Emulator(tmp_path, *args) as em:
        conn = _connect(em.port)
        gcs = GroundStation(conn)
        gcs.pump(until=lambda: gcs.last("SYSTEM_TIME") is not None, timeout_s=10)
        conn.mav.request_data_stream_send(1, 1, MAV.MAV_DATA_STREAM_ALL, 0, 0)  # stop every stream...
        _set_interval(gcs, "SYSTEM_TIME", 0)  # ...but the clock, at its default 1 Hz
        t_stop_s = gcs.t_s
        armed = lambda: any(m.base_mode & MAV.MAV_MODE_FLAG_SAFETY_ARMED for _, m in gcs.seen.get("HEARTBEAT", []))
        gcs.pump(until=armed, timeout_s=10)
        conn.close()  # the client leaves mid-flight and another comes: the vehicle flies on
        gcs = GroundStation(_connect(em.port))
        gcs.pump(proc=em.proc)
        assert em.wait(timeout_s=10) == 0
        record = em.read_log()

    events = {e["event"]: e["t_s"] for e in record["events"]}
    assert 7.7 <= events["failsafe"] - record["failure_t_s"] <= 8.05  # 8 s after the last usable fix
    assert record["switch_to_gps2_t_s"] is None
    assert record["link"]["connections"] >= 3 and record["link"]["errors"] == 0
    assert record["landing_error_m"] > 2.0
    after = [s for s in record["samples"] if events["failsafe"] <= s["t_s"] <= events["landed"]]
    assert {s["mode"] for s in after} == {"LAND"}
    frozen = {tuple(s["estimate_ned_m"][:2]) for s in after}
    assert len(frozen) == 1  # the estimate does not move
    assert math.dist(after[-1]["truth_ned_m"][:2], after[-1]["estimate_ned_m"][:2]) > 1.0
    assert "EKF Failsafe: changed to LAND Mode" in gcs.texts()
    assert any(m.custom_mode == emu.CopterMode.LAND for _, m in gcs.seen["HEARTBEAT"])
    assert "GPS2_RAW" not in gcs.seen  # GPS2_TYPE 0: not sent, as ArduPilot
    late = {kind for kind, items in gcs.seen.items() for t, _ in items if t > t_stop_s + 1.0}
    assert late == {"HEARTBEAT", "SYSTEM_TIME"} | ({"STATUSTEXT"} & late), late


def test_injected_gps1_faults_count_from_take_off():
    """A drag moves GPS1 at its speed from at_s after take-off and then holds; a dropout silences GPS1 for the
    first off_s of each period; an inflated GPS1 reports its accuracy and is that noisy."""
    from auxgps.sim.faults import Fault

    faults = (Fault("gps1_drag", at_s=2.0, for_s=2.0, speed_m_s=1.0, bearing_deg=90.0),
              Fault("gps1_dropout", at_s=6.0, for_s=4.0, off_s=1.0, period_s=2.0),
              Fault("gps1_inflated", at_s=11.0, for_s=2.0, h_acc_m=4.0))
    sim = emu.VehicleSim(FRAME, emu.EmulatorOptions(altitude_m=3, survey_size_m=2, gps2_type=0, faults=faults))
    offsets, arrivals, h_acc = {}, [], {}
    while sim.t_s < 40.0:
        before = sim.gps[0].last_fix_t_s
        sim.step()
        if sim.takeoff_t_s is None:
            continue
        t = round(sim.t_s - sim.dt_s - sim.takeoff_t_s, 2)
        r = sim.gps[0].reading(sim.t_s)
        if sim.gps[0].last_fix_t_s != before:
            arrivals.append(t)
            p_then = sim._motion_history[0][0]
            offsets[t] = r.p_ned_m[1] - p_then[1]
            h_acc[t] = r.h_acc_m
        if t > 14.0:
            break
    assert sim.takeoff_t_s is not None
    east = lambda a, b: [offsets[t] for t in offsets if a <= t < b]  # noqa: E731
    assert max(abs(x) for x in east(0.0, 2.0)) < 0.3
    assert np.allclose(np.median(east(4.2, 6.0)), 2.0, atol=0.2)  # 1 m/s for 2 s, then held
    assert not [t for t in arrivals if 6.0 <= t < 7.0 or 8.0 <= t < 9.0]  # silent
    assert [t for t in arrivals if 7.0 <= t < 8.0]  # and back between
    assert all(h_acc[t] == 4.0 for t in h_acc if 11.0 <= t < 13.0) and all(h_acc[t] < 1.0 for t in h_acc if t < 11.0)


def test_a_mission_is_flown_at_its_own_heights_and_lands_where_it_ends():
    path = ((0.0, 0.0, 0.0), (0.0, 0.0, -3.0), (6.0, 0.0, -3.0), (6.0, 6.0, -5.0), (0.0, 0.0, -5.0), (0.0, 0.0, 0.0))
    sim = emu.VehicleSim(FRAME, emu.EmulatorOptions(mission_path_ned_m=path, mission_speed_m_s=3.0, gps2_type=0).validate())
    closest_m = np.full(len(path), np.inf)
    while sim.landed_t_s is None and sim.t_s < 120:
        sim.step()
        closest_m = np.minimum(closest_m, np.linalg.norm(np.array(path) - sim.craft.p_ned_m, axis=1))
    assert sim.landed_t_s is not None and sim.landing_error_m < 0.5 and sim.mode is emu.CopterMode.RTL
    assert np.all(closest_m[1:5] < 2 * emu.VehicleConfig().waypoint_radius_m)  # every place, at its height


def test_a_mission_loses_gps1_on_reaching_the_waypoint_asked():
    path = ((0.0, 0.0, 0.0), (0.0, 0.0, -3.0), (6.0, 0.0, -3.0), (6.0, 6.0, -3.0), (0.0, 0.0, -3.0), (0.0, 0.0, 0.0))
    sim = emu.VehicleSim(FRAME, emu.EmulatorOptions(mission_path_ned_m=path, mission_speed_m_s=3.0, fail_gps1_at_index=3,
                                                    gps2_type=0).validate())
    while sim.failure_t_s is None and sim.t_s < 60:
        sim.step()
    assert sim.failure_t_s is not None
    assert np.linalg.norm(sim.craft.p_ned_m - path[3]) < 2 * emu.VehicleConfig().waypoint_radius_m
    with pytest.raises(emu.EmulatorError, match="give one"):
        emu.EmulatorOptions(mission_path_ned_m=path, fail_gps1_at_index=3, fail_gps1_at_s=5.0).validate()
