"""Where auxgps's own data is: the worlds, cameras, ArduPilot parameter file and simulation settings.

In an installed wheel they are package data, ``auxgps/data/``; in a source checkout (an editable install, or the
tests) they are ``config/`` beside the package. ``pyproject.toml`` ships ``config/`` as ``auxgps.data``.
"""

from __future__ import annotations

from pathlib import Path

from auxgps.errors import ConfigError

_PACKAGE = Path(__file__).resolve().parent


def data_dir() -> Path:
    """The folder holding ``worlds/``, ``cameras/``, ``ardupilot/``, ``sim/``."""
    for candidate in (_PACKAGE / "data", _PACKAGE.parent / "config"):
        if (candidate / "worlds").is_dir():
            return candidate
    raise ConfigError(f"auxgps's data (worlds, cameras, the ArduPilot parameter file) is neither in {_PACKAGE / 'data'} "
                      f"nor in {_PACKAGE.parent / 'config'}: reinstall auxgps")


def world_names() -> list[str]:
    return sorted(p.stem for p in (data_dir() / "worlds").glob("*.yaml"))


def world_path(name_or_path: str | Path) -> Path:
    """A world file: a path as given when it exists, else one of auxgps's worlds by name (``one_cube_1m``, with or
    without ``.yaml``); a :class:`ConfigError` listing the names otherwise."""
    path = Path(name_or_path)
    if path.exists():
        return path
    stem = path.name.removesuffix(".yaml")
    if path.parent == Path(".") or path.parent.name == "worlds":
        named = data_dir() / "worlds" / f"{stem}.yaml"
        if named.exists():
            return named
    raise ConfigError(f"world {str(name_or_path)!r}: no such file, and not one of auxgps's worlds ({', '.join(world_names())})")


def parm_file() -> Path:
    """``auxgps-gps2.parm``: the ArduPilot parameters for auxgps as GPS2."""
    return data_dir() / "ardupilot" / "auxgps-gps2.parm"
