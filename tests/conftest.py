import importlib.util
import socket
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from auxgps.config import PipelineConfig, parse_as
from auxgps.core.camera import PinholeCamera
from auxgps.sim.world import WorldSpec, world_from_spec

REPO = Path(__file__).resolve().parent.parent
WORLDS = REPO / "config" / "worlds"


def load_tool(name: str):
    """The script ``tools/<name>.py`` as a module (tools/ is not a package), registered in ``sys.modules`` so that
    its dataclasses can look their module up."""
    spec = importlib.util.spec_from_file_location(name, REPO / "tools" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


@pytest.fixture
def camera() -> PinholeCamera:
    return PinholeCamera.from_hfov(1280, 720, np.pi / 2)


@pytest.fixture
def pipeline() -> PipelineConfig:
    return PipelineConfig()


def make_world(cubes, ground=None):
    data = {"origin": {"lat_deg": 47.0, "lon_deg": 8.0, "alt_amsl_m": 400.0}, "cubes": cubes}
    if ground is not None:
        data["ground"] = ground
    return world_from_spec(parse_as(WorldSpec, data, "test"))


def free_port() -> int:
    """A TCP port on loopback that nothing listens on now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def when_listening(connect, timeout_s: float = 20.0):
    """``connect()`` retried until it stops raising OSError (a process just started, not listening yet)."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return connect()
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)
