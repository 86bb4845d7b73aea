"""The MAVLink edge: decoding into SI records on one clock, and GPS_INPUT encoding as ArduPilot reads it."""

import os

import numpy as np
import pytest

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import ardupilotmega as mavlink  # noqa: E402

from auxgps.core.gps_output import GpsOutput  # noqa: E402
from auxgps.io.link import Attitude, BootClock, Gps1, Imu, Truth, decode  # noqa: E402

M = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)


def roundtrip(msg):
    """Encode and parse again, as the link would receive it."""
    buf = msg.pack(M)
    parser = mavlink.MAVLink(None)
    return parser.parse_char(buf)


def test_boot_clock_takes_the_fastest_message():
    clock = BootClock()
    assert clock.to_local(1000, 50.3) == pytest.approx(50.3)
    assert clock.to_local(2000, 51.1) == pytest.approx(51.1)  # faster: offset 49.1 from now on
    assert clock.to_local(3000, 52.5) == pytest.approx(52.1)  # a late arrival keeps its true time


def test_scaled_imu_is_specific_force_in_m_s2():
    rec = decode(roundtrip(M.scaled_imu_encode(1000, 10, -20, -1000, 0, 0, 0, 0, 0, 0, 0)), BootClock(), 10.0)
    assert isinstance(rec, Imu)
    assert np.allclose(rec.f_body_m_s2, [0.0980665, -0.196133, -9.80665])


def test_attitude_gps_and_sim_state():
    clock = BootClock()
    att = decode(roundtrip(M.attitude_encode(500, 0.1, -0.2, 3.0, 0, 0, 0)), clock, 5.0)
    assert isinstance(att, Attitude) and np.allclose(att.euler_rad, [0.1, -0.2, 3.0], atol=1e-6)
    gps = decode(roundtrip(M.gps_raw_int_encode(0, 3, 473977420, 85455940, 503000, 80, 100, 0, 0, 9)), clock, 6.0)
    assert isinstance(gps, Gps1) and gps.lat_deg == pytest.approx(47.397742) and gps.alt_amsl_m == pytest.approx(503.0)
    assert gps.satellites == 9 and gps.fix_type == 3
    sim = M.sim_state_encode(1, 0, 0, 0, 0.05, -0.02, 1.0, 0, 0, 0, 0, 0, 0, 4.7e8, 8.5e7, 503.5, 0, 0, 0, 0, 0, 473977420, 85455940)
    truth = decode(roundtrip(sim), clock, 7.0)
    assert isinstance(truth, Truth) and truth.lat_deg == pytest.approx(47.397742) and truth.alt_amsl_m == pytest.approx(503.5)


def test_gps1_is_stamped_with_its_fix_time_when_that_is_a_boot_time():
    clock = BootClock()
    decode(roundtrip(M.attitude_encode(10_000, 0, 0, 0, 0, 0, 0)), clock, 100.0)  # boot 10 s is local 100 s
    # ArduPilot sends the boot time of the last fix (here 150 ms before the attitude that went with it).
    late = decode(roundtrip(M.gps_raw_int_encode(9_850_000, 3, 473977420, 85455940, 503000, 80, 100, 0, 0, 9)), clock, 100.01)
    assert late.t_s == pytest.approx(99.85)
    # UNIX time (other autopilots), zero, or a stamp far older than the message: the arrival time.
    for time_usec in (1_795_000_000_000_000, 0, 5_000_000):
        gps = decode(roundtrip(M.gps_raw_int_encode(time_usec, 3, 473977420, 85455940, 503000, 80, 100, 0, 0, 9)), clock, 100.02)
        assert gps.t_s == pytest.approx(100.02)


def test_gps_input_fields_as_ardupilot_reads_them():
    from auxgps.io.link import MavLink

    sent = []

    class FakeConn:
        mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=191)

    link = MavLink("tcp:127.0.0.1:1", lambda r: None)
    link._conn = FakeConn()
    FakeConn.mav.send = lambda m: sent.append(m)
    out = GpsOutput(2446, 86418000, 3, 47.397742, 8.545594, 503.25, np.array([1.0, -0.5, 0.1]), 0.12, 0.2, 0.05, 0.5, 0.5, 6)
    assert link.send_gps_input(out, 1795392000000000)
    msg = roundtrip(sent[0])
    assert msg.get_type() == "GPS_INPUT" and msg.gps_id == 1 and msg.ignore_flags == 0
    assert (msg.lat, msg.lon) == (473977420, 85455940) and msg.alt == pytest.approx(503.25)
    assert (msg.time_week, msg.time_week_ms, msg.fix_type, msg.satellites_visible) == (2446, 86418000, 3, 6)
    assert (msg.vn, msg.ve) == pytest.approx((1.0, -0.5)) and msg.horiz_accuracy == pytest.approx(0.12)


def test_boot_clock_follows_an_autopilot_clock_that_runs_slow():
    """A simulator at 0.9 of real time: the mapped stamps stay within the window's drift of their arrivals."""
    clock = BootClock(window_s=2.0)
    arrivals = np.arange(0.0, 300.0, 0.02)
    mapped = [clock.to_local(int(round(t * 0.9 * 1000)), t) for t in arrivals]
    lag_s = arrivals - np.array(mapped)
    assert np.all(lag_s >= -1e-9) and lag_s.max() <= 0.1 * 2.0 + 0.02  # at most the drift over one window


def test_boot_clock_starts_afresh_when_the_autopilot_reboots():
    """300 s into the flight the autopilot restarts (its boot clock back to 0.5 s): the next messages are stamped
    at their arrival, not 300 s in the past for the window's length."""
    clock = BootClock(window_s=2.0)
    for t in np.arange(0.0, 300.0, 0.02):
        clock.to_local(int(round(t * 1000)) + 5000, t + 0.001)
    after = [clock.to_local(int(round(dt * 1000)) + 500, 300.0 + dt + 0.001) for dt in np.arange(0.0, 3.0, 0.02)]
    assert clock.reboots == 1
    np.testing.assert_allclose(after, 300.0 + np.arange(0.0, 3.0, 0.02) + 0.001, atol=0.002)


def test_a_message_without_a_stamp_read_late_keeps_the_time_it_was_sent():
    """SIM_STATE has no time of its own: read at once it is stamped on arrival; read 0.4 s late (a starved reader)
    it is stamped within 0.025 s of the stamped messages sent beside it (SCALED_IMU: 50 Hz), so a frame rendered at it
    is not 0.4 s late."""
    from auxgps.io.link import BootClock

    clock = BootClock()
    for k in range(50):
        clock.to_local(1000 * k // 50 + 10_000, 500.0 + k / 50)  # IMU at 50 Hz, on time
    sent_s = clock.local(10_000 + 980)
    assert clock.unstamped(sent_s + 0.003) == pytest.approx(sent_s + 0.003)
    clock.to_local(11_000, 501.0 + 0.4)  # the next IMU sample, read 0.4 s late
    assert clock.unstamped(501.0 + 0.41) == pytest.approx(501.0 + 0.025, abs=0.005)


def test_message_rates_are_asked_for_again_when_the_heartbeat_comes_without_attitude():
    """An autopilot that restarted forgets the rates it was asked for (a copter's SRn_ rates are all 0: HEARTBEAT
    alone). While ATTITUDE comes, the rates are asked for once; once it has been missing for over 1.5 s, at each
    HEARTBEAT over 1.5 s after the last asking, until it is back."""
    from auxgps.io.link import STREAMS_SILENT_S, MavLink

    sent = []

    class FakeConn:
        mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=191)

    link = MavLink("tcp:127.0.0.1:1", lambda msg, t: None)
    link._conn = FakeConn()
    FakeConn.mav.send = lambda m: sent.append(m)
    heartbeat = roundtrip(M.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 0))
    attitude = roundtrip(M.attitude_encode(0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))

    def asked(t0, t1):
        """The times in [t0, t1) at which the rates were asked for, fed a HEARTBEAT a second and ATTITUDE at 50 Hz
        while ``streaming`` says so."""
        times = []
        for t in np.arange(t0, t1, 0.02):
            n = link.stream_requests
            if abs(t - round(t)) < 1e-9:
                link._handle(heartbeat, float(t))
            if streaming(t):
                link._handle(attitude, float(t))
            if link.stream_requests > n:
                times.append(round(float(t), 2))
        return times

    def streaming(t):
        return t < 10.0 or t >= 14.0  # the autopilot restarts at 10 s; asked again, it streams from 14 s

    assert asked(0.0, 10.0) == [0.0]  # the first HEARTBEAT
    requests = [m for m in sent if m.get_type() == "COMMAND_LONG" and m.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL]
    assert {int(m.param1) for m in requests} >= {mavlink.MAVLINK_MSG_ID_ATTITUDE, mavlink.MAVLINK_MSG_ID_SCALED_IMU}
    assert STREAMS_SILENT_S == 1.5
    assert asked(10.0, 20.0) == [12.0, 14.0]  # 2 s after the last ATTITUDE; again 2 s later; then it is back
    assert link.stream_requests == 3
