"""auxgps as a package: the wheel ships everything its commands need, and works from outside the checkout."""

import os
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from tests.conftest import free_port

REPO = Path(__file__).resolve().parent.parent


def test_every_package_folder_is_in_the_wheel_list():
    listed = set(tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    folders = {".".join(p.parent.relative_to(REPO).parts) for p in (REPO / "auxgps").rglob("__init__.py")}
    assert listed == folders | {"auxgps.data"}


def test_worlds_are_found_by_name_and_a_wrong_name_lists_them():
    from auxgps.errors import ConfigError
    from auxgps.resources import world_path
    from auxgps.sim.world import load_world

    assert load_world("one_cube_1m").cubes and world_path("one_cube_1m.yaml").name == "one_cube_1m.yaml"
    with pytest.raises(ConfigError, match="one_cube_1m"):
        world_path("one_cube_7m")


@pytest.mark.slow
@pytest.mark.packaging
def test_the_wheel_installed_outside_the_checkout_runs_eval_and_a_flight(tmp_path):
    dist, venv, work = tmp_path / "dist", tmp_path / "venv", tmp_path / "work"
    work.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    subprocess.run([sys.executable, "-m", "pip", "wheel", str(REPO), "--no-deps", "-q", "-w", str(dist)], check=True, env=env,
                   capture_output=True, timeout=600)
    wheel = next(dist.glob("auxgps-*.whl"))
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=120)
    pip = subprocess.run([str(venv / "bin" / "python"), "-m", "pip", "install", "-q", str(wheel)], env=env, capture_output=True,
                         text=True, timeout=900)
    assert pip.returncode == 0, pip.stderr[-2000:]
    auxgps = str(venv / "bin" / "auxgps")

    def run(*args, timeout_s=600):
        return subprocess.run([auxgps, *args], cwd=work, env=env, capture_output=True, text=True, timeout=timeout_s)

    version = run("--version")
    assert version.returncode == 0 and version.stdout.startswith("auxgps "), version.stderr
    small = work / "small.yaml"  # a 6 m survey, GPS lost after 5 s: an eval of seconds
    small.write_text("mapping: {north_min_m: -3, north_max_m: 3, east_min_m: -3, east_max_m: 3, spacing_m: 3}\n"
                     "positioning: {north_min_m: -3, north_max_m: 3, east_min_m: -3, east_max_m: 3, spacing_m: 3, legs: ew}\n"
                     "denial: {gps_until_s: 5}\n")
    ev = run("eval", "--world", "one_cube_1m", "--altitude", "15", "--runs", "1", "--sim-config", str(small), "--quiet")
    assert ev.returncode == 0 and "per-frame fix horizontal error" in ev.stdout, ev.stderr[-2000:]
    port = free_port()
    emu = subprocess.Popen([str(venv / "bin" / "python"), "-m", "auxgps.sim.emulator", "--world", "one_cube_1m", "--port", str(port),
                            "--survey-size", "4", "--fail-gps1-at", "15", "--max-seconds", "90", "--log", str(work / "emu.json")],
                           cwd=work, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        flight = run("run", "--connect", f"tcp:127.0.0.1:{port}", "--camera", "sim:one_cube_1m", "--duration", "100",
                     "--log-dir", str(work / "run"), timeout_s=200)
        emu.wait(timeout=60)
    finally:
        if emu.poll() is None:
            emu.kill()
    import json

    log = json.loads((work / "emu.json").read_text())
    assert flight.returncode == 0, flight.stderr[-2000:]
    assert log["exit_reason"] == "landed" and log["landing_error_m"] <= 2.0
    assert log["gps_input"]["consecutive_gaps_over_245ms"] < 2
