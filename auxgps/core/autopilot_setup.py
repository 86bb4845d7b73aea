"""What auxgps needs of the autopilot's set-up, as rules over what the autopilot reported: pure, no link.

``auxgps check`` gathers the firmware version, the parameters, the rates its streams arrive at and GPS1's state
over MAVLink (:mod:`auxgps.preflight`), and these rules say, line by line, what is right and wrong for auxgps as
GPS2 (see ``config/ardupilot/auxgps-gps2.parm`` for why each value).
"""

from __future__ import annotations

from dataclasses import dataclass, field

#: Parameters that take effect only after a reboot (ArduPilot reads them when the GPS driver starts).
NEEDS_REBOOT = {"GPS2_TYPE", "GPS_TYPE2", "GPS2_DELAY_MS", "GPS_DELAY_MS2"}
#: ArduPilot 4.6 renamed the second GPS's parameters.
NAMES_BEFORE_4_6 = {"GPS2_TYPE": "GPS_TYPE2", "GPS2_DELAY_MS": "GPS_DELAY_MS2"}
#: The streams auxgps asks for, and the share of their rate that must arrive.
STREAMS_HZ = {"ATTITUDE": 50.0, "SCALED_IMU": 50.0, "GLOBAL_POSITION_INT": 10.0, "GPS_RAW_INT": 5.0}
MIN_RATE_SHARE = 0.7
MIN_FIRMWARE = (4, 6, 0)


@dataclass(frozen=True)
class Observed:
    """What the autopilot reported. ``version`` (major, minor, patch) or None; ``params`` name -> value;
    ``stream_hz`` message -> measured rate; ``gps1`` (fix type, satellites) or None when no GPS_RAW_INT came."""

    version: tuple[int, int, int] | None
    params: dict[str, float]
    stream_hz: dict[str, float]
    gps1: tuple[int, int] | None


@dataclass(frozen=True)
class Finding:
    """One line of the check: ``ok``, a short ``key``, the ``text``; ``set_params`` what ``--fix`` would write."""

    ok: bool
    key: str
    text: str
    set_params: dict[str, float] = field(default_factory=dict)


def param_names(version: tuple[int, int, int] | None) -> dict[str, str]:
    """The autopilot's name for each of auxgps's parameters (the 4.6 names, or the older ones before 4.6)."""
    old = version is not None and version < MIN_FIRMWARE
    return {new: (NAMES_BEFORE_4_6[new] if old else new) for new in NAMES_BEFORE_4_6}


def check_setup(obs: Observed, wanted: dict[str, float], gps_delay_ms: int) -> list[Finding]:
    """The findings, in the order they are printed. ``wanted``: the parameter file's values (4.6 names);
    ``gps_delay_ms``: auxgps run's --gps-delay-ms, which GPS2_DELAY_MS must equal."""
    out: list[Finding] = []
    if obs.version is None:
        out.append(Finding(False, "firmware", "firmware version not reported (no AUTOPILOT_VERSION): cannot tell 4.6+ parameter names"))
    else:
        v = ".".join(map(str, obs.version))
        ok = obs.version >= MIN_FIRMWARE
        out.append(Finding(ok, "firmware", f"ArduPilot {v}" + ("" if ok else " is older than 4.6: its GPS2 parameters are GPS_TYPE2 and "
                                                                "GPS_DELAY_MS2, checked under those names; 4.6 or later is what auxgps is tested on")))
    names = param_names(obs.version)
    want = dict(wanted)
    want["GPS2_DELAY_MS"] = float(gps_delay_ms)
    why = {
        "GPS2_TYPE": "GPS2 a MAVLink GPS, fed by auxgps's GPS_INPUT",
        "GPS_AUTO_SWITCH": "use the primary (GPS1) while it has a 3D fix, GPS2 otherwise",
        "GPS_PRIMARY": "GPS1, the real receiver, is the primary",
        "GPS2_DELAY_MS": f"equal to auxgps run's --gps-delay-ms ({gps_delay_ms} ms)",
        "EK3_SRC1_POSXY": "the EKF's horizontal position from GPS (whichever is primary)",
        "EK3_SRC1_VELXY": "the EKF's horizontal velocity from GPS",
    }
    for name, value in want.items():
        real = names.get(name, name)
        have = obs.params.get(real)
        reboot = " (takes effect after a reboot)" if real in NEEDS_REBOOT else ""
        if have is None:
            out.append(Finding(False, real, f"{real} not reported by the autopilot; want {value:g}: {why.get(name, '')}", {real: value}))
        elif abs(have - value) > 1e-6:
            out.append(Finding(False, real, f"{real} = {have:g}, want {value:g}: {why.get(name, '')}{reboot}", {real: value}))
        else:
            out.append(Finding(True, real, f"{real} = {have:g}: {why.get(name, '')}"))
    for msg, hz in STREAMS_HZ.items():
        got = obs.stream_hz.get(msg, 0.0)
        ok = got >= MIN_RATE_SHARE * hz
        out.append(Finding(ok, msg, f"{msg} arrives at {got:.1f} Hz" + ("" if ok else f", want {hz:g} Hz: check the link's baud rate "
                                                                               "and the SERIALn_ port's protocol (MAVLink 2)")))
    if obs.gps1 is None:
        out.append(Finding(False, "GPS1", "GPS1: no GPS_RAW_INT from the autopilot"))
    else:
        fix, sats = obs.gps1
        ok = fix >= 3 and sats >= 6
        out.append(Finding(ok, "GPS1", f"GPS1 fix type {fix}, {sats} satellites" + ("" if ok else ": not healthy now; auxgps maps only while "
                                                                                            "GPS1 has a 3D fix with 6 or more")))
    return out


def read_parm_file(text: str) -> dict[str, float]:
    """``NAME VALUE  # comment`` lines (ArduPilot's .parm format; commas also separate) -> name -> value."""
    out = {}
    for k, line in enumerate(text.splitlines(), start=1):
        line = line.split("#", 1)[0].replace(",", " ").strip()
        if not line:
            continue
        parts = line.split()
        if len(parts) != 2:
            raise ValueError(f"line {k}: expected NAME VALUE, got {line!r}")
        out[parts[0]] = float(parts[1])
    return out
