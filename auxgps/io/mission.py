"""Mission files as ground stations write them: ArduPilot's ``.waypoints`` text (QGC WPL 110, read by pymavlink's
own loader) and QGroundControl's ``.plan`` JSON (simple items, and the items a survey or corridor scan expands to).

A :class:`Mission` keeps the items in file order with their sequence numbers (seq 0 is home in a ``.waypoints``
file; in a ``.plan`` the planned home comes separately and the items count from 1), so that "waypoint N" means
what the file and the ground station call it. Turning items into a path to fly is the simulator's
(:func:`auxgps.sim.flight.mission_waypoints_ned`).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

os.environ.setdefault("MAVLINK20", "1")  # as auxgps.io.link: one dialect in the process (mavwp asks the variable)
from pymavlink import mavutil, mavwp  # noqa: E402

from auxgps.errors import ConfigError  # noqa: E402

M = mavutil.mavlink
#: Frames whose altitude is above home (or the terrain, which the flat or gently rolling simulated ground equals
#: near enough for a flight path), and the one above mean sea level.
RELATIVE_FRAMES = {M.MAV_FRAME_GLOBAL_RELATIVE_ALT, M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, M.MAV_FRAME_GLOBAL_TERRAIN_ALT,
                   M.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT}
AMSL_FRAMES = {M.MAV_FRAME_GLOBAL, M.MAV_FRAME_GLOBAL_INT}
#: Commands that move the vehicle to a place (the rest, DO_ and CONDITION_ items, do not).
PLACE_COMMANDS = {M.MAV_CMD_NAV_WAYPOINT, M.MAV_CMD_NAV_SPLINE_WAYPOINT, M.MAV_CMD_NAV_LOITER_UNLIM, M.MAV_CMD_NAV_LOITER_TURNS,
                  M.MAV_CMD_NAV_LOITER_TIME, M.MAV_CMD_NAV_LOITER_TO_ALT, M.MAV_CMD_NAV_TAKEOFF, M.MAV_CMD_NAV_LAND,
                  M.MAV_CMD_NAV_RETURN_TO_LAUNCH}


@dataclass(frozen=True)
class MissionItem:
    """One mission item. ``alt_m`` is in ``frame`` (above home, or AMSL for the global frame); lat/lon 0 means
    "where the vehicle is" for the commands that allow it (take-off, land)."""

    seq: int
    command: int
    frame: int
    lat_deg: float
    lon_deg: float
    alt_m: float
    params: tuple[float, float, float, float]

    @property
    def name(self) -> str:
        entry = M.enums["MAV_CMD"].get(self.command)
        return entry.name.removeprefix("MAV_CMD_") if entry is not None else f"command {self.command}"

    @property
    def has_place(self) -> bool:
        return self.command in PLACE_COMMANDS


@dataclass(frozen=True)
class Mission:
    """A mission's items in file order, its home when the file gives one (lat, lon deg, alt AMSL m), and where it came from."""

    source: str
    items: tuple[MissionItem, ...]
    home: tuple[float, float, float] | None

    def item(self, seq: int) -> MissionItem:
        for it in self.items:
            if it.seq == seq:
                return it
        raise ConfigError(f"{self.source}: no mission item {seq} (items {self.items[0].seq} to {self.items[-1].seq})")


def load_mission(path: Path | str) -> Mission:
    """Read a ``.waypoints`` (QGC WPL 110) or ``.plan`` file. ConfigError, naming the file, on anything else."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"mission {path}: no such file")
    text = path.read_text(errors="replace")
    if text.lstrip().startswith("{"):
        mission = _read_plan(path, text)
    elif text.startswith("QGC WPL"):
        mission = _read_wpl(path)
    else:
        raise ConfigError(f"mission {path}: neither QGC WPL 110 text nor a QGroundControl .plan (JSON)")
    if not any(it.has_place for it in mission.items):
        raise ConfigError(f"mission {path}: no item that goes anywhere (waypoint, take-off, land, return)")
    for it in mission.items:
        if it.has_place and it.frame not in RELATIVE_FRAMES | AMSL_FRAMES:
            raise ConfigError(f"mission {path}: item {it.seq} ({it.name}) is in frame {it.frame}: only global frames "
                              "(relative, terrain or AMSL altitude) are flown")
        if it.has_place and not all(math.isfinite(v) for v in (it.lat_deg, it.lon_deg, it.alt_m)):
            raise ConfigError(f"mission {path}: item {it.seq} ({it.name}) has a coordinate that is not a number")
    return mission


def _read_wpl(path: Path) -> Mission:
    loader = mavwp.MAVWPLoader()
    try:
        loader.load(str(path))
    except (mavwp.MAVWPError, ValueError) as err:
        said = str(getattr(err, "message", err))
        hint = " (a QGC WPL 110 line has 12 values)" if "waypoint line" in said else ""
        raise ConfigError(f"mission {path}: {said}{hint}") from None
    items, home = [], None
    for k in range(loader.count()):
        w = loader.wp(k)
        if w.seq == 0 and k == 0:
            home = (float(w.x), float(w.y), float(w.z))  # Mission Planner's home item (AMSL)
            continue
        items.append(MissionItem(int(w.seq), int(w.command), int(w.frame), float(w.x), float(w.y), float(w.z),
                                 (float(w.param1), float(w.param2), float(w.param3), float(w.param4))))
    if not items:
        raise ConfigError(f"mission {path}: no items after home")
    return Mission(str(path), tuple(items), home if home and (home[0] or home[1]) else None)


def _plan_simple_items(items: list, path: Path) -> list[dict]:
    """SimpleItems in order, those inside complex items (survey, corridor scan, structure scan) expanded as QGC
    stores them."""
    out = []
    for it in items:
        kind = it.get("type")
        if kind == "SimpleItem":
            out.append(it)
        elif kind == "ComplexItem":
            inner = it.get("TransectStyleComplexItem", {}).get("Items") or it.get("Items")
            if not inner:
                raise ConfigError(f"mission {path}: complex item {it.get('complexItemType', '?')} has no stored items "
                                  "(save the plan from QGroundControl 4 or later)")
            out.extend(_plan_simple_items(inner, path))
        else:
            raise ConfigError(f"mission {path}: an item of unknown type {kind!r}")
    return out


def _read_plan(path: Path, text: str) -> Mission:
    try:
        plan = json.loads(text)
        mission = plan["mission"]
        raw = _plan_simple_items(mission["items"], path)
    except (json.JSONDecodeError, KeyError, TypeError) as err:
        raise ConfigError(f"mission {path}: not a QGroundControl plan ({type(err).__name__}: {err})") from None
    items = []
    for seq, it in enumerate(raw, start=1):
        p = [float("nan") if v is None else float(v) for v in (list(it.get("params", [])) + [0.0] * 7)[:7]]
        items.append(MissionItem(seq, int(it["command"]), int(it.get("frame", M.MAV_FRAME_GLOBAL_RELATIVE_ALT)),
                                 p[4], p[5], p[6], (p[0], p[1], p[2], p[3])))
    if not items:
        raise ConfigError(f"mission {path}: no items")
    home = mission.get("plannedHomePosition")
    return Mission(str(path), tuple(items), tuple(float(v) for v in home[:3]) if home else None)
