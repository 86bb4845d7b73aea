"""Config and world files: typos and bad values are one clear line naming the key and the file."""

import subprocess
import sys

import pytest

from auxgps.config import load_pipeline_config
from auxgps.errors import ConfigError
from auxgps.sim.world import load_world
from tests.conftest import WORLDS

ORIGIN = "origin: {lat_deg: 47.0, lon_deg: 8.0, alt_amsl_m: 400.0}\n"


def write(tmp_path, text, name="w.yaml"):
    p = tmp_path / name
    p.write_text(text)
    return p


@pytest.mark.parametrize(
    "text,key",
    [
        (ORIGIN + "cubes: [{east_m: 0, north_m: 0, size_m: 1, colour: red}]\n", "cubes.0.colour: unknown key"),
        (ORIGIN + "cubes: [{east_m: 0, north_m: 0, size_m: -1}]\n", "cubes.0.size_m"),
        ("cubes: []\n", "origin: Field required"),
        (ORIGIN + "ground: {color: [1, 2]}\n", "ground.color"),
        (ORIGIN + "cubes: [{east_m: 0, north_m: 0, size_m: 1, color: mauve}]\n", "unknown colour name"),
        (ORIGIN + "wind: 3\n", "wind: unknown key"),
    ],
)
def test_bad_world_names_file_and_key(tmp_path, text, key):
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as err:
        load_world(path)
    assert str(path) in str(err.value) and key in str(err.value)


def test_bad_yaml_and_missing_file(tmp_path):
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_world(write(tmp_path, "origin: [\n"))
    with pytest.raises(ConfigError, match="absent.yaml.: no such file"):
        load_world(tmp_path / "absent.yaml")


def test_pipeline_config_rejects_out_of_range(tmp_path):
    with pytest.raises(ConfigError, match="detector.n_features"):
        load_pipeline_config(write(tmp_path, "detector: {n_features: 0}\n"))
    with pytest.raises(ConfigError, match="mapping.min_sen: unknown key"):
        load_pipeline_config(write(tmp_path, "mapping: {min_sen: 3}\n"))


def test_every_shipped_world_loads_with_cubes_inside_the_survey():
    files = sorted(WORLDS.glob("*.yaml"))
    assert len(files) >= 16
    for f in files:
        try:
            world = load_world(f)
        except ConfigError as err:
            # A world over data that is not in the repository (a survey's photo, an orthophoto to build first): on a
            # clean checkout it is refused with a line naming the file it lacks.
            assert ("no such file" in str(err) or "cannot read" in str(err)) and ("shared/data" in str(err) or "out/ortho" in str(err)), err
            continue
        for cube in world.cubes:
            assert all(abs(v) <= 10.0 - cube.size_m / 2 for v in cube.center_ne_m), f


def test_cli_prints_one_line_and_exits_1(tmp_path):
    path = write(tmp_path, ORIGIN + "cubes: [{east_m: 0, north_m: 0, size_m: -2}]\n")
    proc = subprocess.run(
        [sys.executable, "-m", "auxgps.cli", "eval", "--world", str(path), "--altitude", "15"],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 1
    assert proc.stderr.strip().count("\n") == 0 and "size_m" in proc.stderr and "Traceback" not in proc.stderr


def test_every_shipped_sim_config_loads_and_changes_only_what_it_says():
    from auxgps.sim.flight import SimConfig, load_sim_config

    sim_dir = WORLDS.parent / "sim"
    loaded = {f.name: load_sim_config(f) for f in sorted(sim_dir.glob("*.yaml"))}
    assert {"blackout.yaml", "quiet_accelerometer.yaml"} <= set(loaded)
    quiet, default = loaded["quiet_accelerometer.yaml"], SimConfig()
    assert quiet.noise.accel_noise_m_s2 == 0.0
    assert quiet.noise.accel_bias_m_s2 == default.noise.accel_bias_m_s2 and quiet.denial == default.denial
