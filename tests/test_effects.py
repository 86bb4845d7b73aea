"""The simulated camera's appearance effects (exposure and white balance shift, sun glare, motion blur, sensor
noise): each does what it says on a synthetic image, the defaults change nothing, the configuration refuses
nonsense, and the evaluation switches to the way back's effects when GPS1 is lost."""

import dataclasses
from pathlib import Path

import cv2
import numpy as np
import pytest

from auxgps.config import parse_as
from auxgps.core.camera import CameraPose
from auxgps.core.geometry import R_BODY_CAM_DOWN, R_ned_body_from_euler
from auxgps.errors import ConfigError
from auxgps.evaluation import scenario
from auxgps.sim.flight import SimConfig, load_sim_config
from auxgps.sim.render import (
    ImageEffects,
    Renderer,
    apply_effects,
    ground_motion_px,
    line_kernel,
    sun_dir_ned,
    sun_glint_px,
)
from tests.conftest import make_world

REPO = Path(__file__).resolve().parent.parent
EFFECTS_ALL = REPO / "config" / "sim" / "effects_all.yaml"

atol_px = 0.5  # half a pixel
atol_grey = 0.6  # grey levels: rounding to uint8, and a little
atol_deg = 1.0


def nadir_pose(height_m=15.0, yaw_rad=0.0):
    return CameraPose(np.array([0.0, 0.0, -height_m]), R_ned_body_from_euler(0.0, 0.0, yaw_rad) @ R_BODY_CAM_DOWN)


def textured(h=180, w=320, seed=0):
    """A colour texture between 50 and 150 grey levels: no effect below saturates it."""
    return np.random.default_rng(seed).integers(50, 151, (h, w, 3)).astype(np.uint8)


def principal_axes(img):
    """The intensity-weighted centroid, the major axis' angle (rad, image x right, y down) and the variances along
    the major and minor axes of a single-channel image."""
    w = img.astype(float)
    y, x = np.mgrid[: img.shape[0], : img.shape[1]]
    m = w.sum()
    cx, cy = (w * x).sum() / m, (w * y).sum() / m
    cov = np.cov(np.vstack([x.ravel() - cx, y.ravel() - cy]), aweights=w.ravel(), bias=True)
    evals, evecs = np.linalg.eigh(cov)
    major = evecs[:, 1]
    return (cx, cy), float(np.arctan2(major[1], major[0])), float(evals[1]), float(evals[0])


# -- the defaults are the identity ------------------------------------------------------------------------------


def test_default_effects_return_the_image_itself_before_and_after_gps_loss():
    img = textured()
    for after in (False, True):
        effects = SimConfig().image_effects(after_gps_loss=after)
        assert effects.is_identity
        assert apply_effects(img, effects, np.random.default_rng(0), motion_px=np.array([3.0, 4.0]),
                             glint_px=np.array([10.0, 10.0])) is img


def test_a_default_render_is_bit_identical_with_a_velocity_given(camera):
    world = make_world([{"east_m": 1.0, "north_m": 2.0, "size_m": 2.0, "color": "white"}])
    renderer = Renderer(world, camera)
    pose = nadir_pose(yaw_rad=0.3)
    plain = renderer.render(pose).image_bgr
    moving = renderer.render(pose, SimConfig().image_effects(True), np.random.default_rng(0), v_ned_m_s=np.array([8.0, 3.0, 0.0]))
    assert np.array_equal(plain, moving.image_bgr)


def test_the_whole_run_effects_are_those_of_before():
    """Equivalence with the effects as they were (gain, Gaussian blur, white noise, in that order), draw for draw."""
    img = textured()
    effects = ImageEffects(noise_sigma=3.0, blur_sigma_px=1.2, exposure_gain=1.1)
    ref = img.astype(np.float32) * 1.1
    ref = cv2.GaussianBlur(ref, (0, 0), 1.2)
    ref += np.random.default_rng(5).normal(0.0, 3.0, ref.shape).astype(np.float32)
    ref = np.clip(np.rint(ref), 0, 255).astype(np.uint8)
    assert np.array_equal(apply_effects(img, effects, np.random.default_rng(5)), ref)


# -- exposure and white balance shift ----------------------------------------------------------------------------


def test_a_white_balance_shift_scales_each_channel_mean_by_its_gain():
    img = textured()
    effects = ImageEffects(shift_gain=1.2, shift_gain_bgr=(0.9, 1.0, 1.1))
    out = apply_effects(img, effects, None)
    ratio = out.reshape(-1, 3).mean(0) / img.reshape(-1, 3).mean(0)
    assert np.allclose(ratio, [1.2 * 0.9, 1.2, 1.2 * 1.1], atol=0.005)


def test_gamma_acts_on_the_unit_image():
    img = np.full((4, 4, 3), 64, np.uint8)
    out = apply_effects(img, ImageEffects(shift_gamma=2.0), None)
    assert np.all(np.abs(out.astype(float) - 255.0 * (64 / 255.0) ** 2) <= atol_grey)
    assert np.array_equal(apply_effects(np.full((2, 2, 3), 255, np.uint8), ImageEffects(shift_gamma=2.0), None), np.full((2, 2, 3), 255))


def test_the_shift_applies_only_after_gps_loss():
    sim = parse_as(SimConfig, {"effects": {"exposure_shift": {"gain": 0.8, "gain_bgr": [1.1, 1.0, 0.9], "gamma": 1.2}}}, "x.yaml")
    assert sim.image_effects(after_gps_loss=False).is_identity
    back = sim.image_effects(after_gps_loss=True)
    assert (back.shift_gain, back.shift_gain_bgr, back.shift_gamma) == (0.8, (1.1, 1.0, 0.9), 1.2)


# -- sun glare -----------------------------------------------------------------------------------------------------


def test_glare_saturates_a_disc_of_the_configured_radius_and_fades_beyond():
    h, w = 360, 640
    img = np.full((h, w, 3), 100, np.uint8)
    centre = np.array([300.0, 200.0])
    effects = ImageEffects(glare_strength=1.0, glare_core_frac=0.05, glare_falloff_frac=0.05)
    out = apply_effects(img, effects, None, glint_px=centre)
    radius_px = 0.05 * w
    y, x = np.mgrid[:h, :w]
    r = np.hypot(x - centre[0], y - centre[1])
    saturated = (out == 255).all(axis=2)
    assert saturated[r <= radius_px].all()
    # 100 grey levels of ground need 155 of glare to saturate: 0.76 sigma of fall-off beyond the core.
    edge_px = radius_px + np.sqrt(-2 * np.log(155 / 255)) * 0.05 * w
    assert not saturated[r > edge_px + 1.0].any()
    assert abs(np.sqrt(saturated.sum() / np.pi) - edge_px) <= 1.0
    assert np.array_equal(out[r > edge_px + 6 * 0.05 * w], img[r > edge_px + 6 * 0.05 * w])  # far away, untouched


def test_haze_blends_every_pixel_towards_white():
    img = textured()
    out = apply_effects(img, ImageEffects(glare_haze=0.2), None)
    assert np.all(np.abs(out.astype(float) - (img * 0.8 + 0.2 * 255)) <= atol_grey)


def test_the_glint_is_the_suns_mirror_and_turns_in_the_image_with_the_vehicle(camera):
    # A sun overhead glints at the principal point.
    uv = sun_glint_px(camera, nadir_pose(), sun_dir_ned(0.0, 90.0))
    assert np.allclose(uv, camera.K[:2, 2], atol=1e-6)
    # A sun in the south-east at 55 deg: seen from above, the glint is south-east of the camera, 35 deg off nadir.
    sun = sun_dir_ned(135.0, 55.0)
    f = camera.focal_px
    off = f * np.tan(np.deg2rad(35.0)) / np.sqrt(2)
    uv_north = sun_glint_px(camera, nadir_pose(yaw_rad=0.0), sun)  # heading north: east is right, south is down
    assert np.allclose(uv_north - camera.K[:2, 2], [off, off], atol=1e-6)
    uv_east = sun_glint_px(camera, nadir_pose(yaw_rad=np.pi / 2), sun)  # heading east: south is right, east is up
    assert np.allclose(uv_east - camera.K[:2, 2], [off, -off], atol=1e-6)
    # A sun on the horizon glints on the horizon, far outside a downward camera's view: no glare in the frame.
    uv_low = sun_glint_px(camera, nadir_pose(), sun_dir_ned(0.0, 0.001))
    assert uv_low is None or not camera.in_image(uv_low)[0]


def test_the_renderer_draws_the_glare_where_the_sun_glints(camera):
    world = make_world([])
    renderer = Renderer(world, camera)
    effects = ImageEffects(glare_strength=1.0, glare_core_frac=0.03)
    pose = nadir_pose(yaw_rad=0.4)
    out = renderer.render(pose, effects)
    uv = sun_glint_px(camera, pose, np.asarray(effects.sun_dir_ned))
    assert camera.in_image(uv)[0]
    (cx, cy), *_ = principal_axes((out.image_bgr == 255).all(axis=2).astype(np.uint8))
    assert np.hypot(cx - uv[0], cy - uv[1]) <= atol_px + 1.0


# -- motion blur ---------------------------------------------------------------------------------------------------


def test_the_ground_motion_is_speed_times_exposure_over_the_ground_sample_distance(camera):
    height_m, v, exposure_s = 15.0, 8.0, 0.01
    gsd_m = height_m / camera.focal_px
    # Heading north and flying north, the ground runs down the image.
    d = ground_motion_px(camera, nadir_pose(height_m), np.array([v, 0.0, 0.0]), height_m, exposure_s)
    assert np.allclose(d, [0.0, v * exposure_s / gsd_m], atol=1e-9)
    # Heading north and flying east: the ground runs left. Heading east, flying east: down again.
    d = ground_motion_px(camera, nadir_pose(height_m), np.array([0.0, v, 0.0]), height_m, exposure_s)
    assert np.allclose(d, [-v * exposure_s / gsd_m, 0.0], atol=1e-9)
    d = ground_motion_px(camera, nadir_pose(height_m, np.pi / 2), np.array([0.0, v, 0.0]), height_m, exposure_s)
    assert np.allclose(d, [0.0, v * exposure_s / gsd_m], atol=1e-9)


@pytest.mark.parametrize("motion_px", [(17.0, 0.0), (0.0, -9.0), (12.0, 9.0), (-6.0, 14.0)])
def test_a_point_blurs_into_a_line_of_the_motions_length_and_direction(motion_px):
    img = np.zeros((81, 81, 3), np.uint8)
    img[40, 40] = 255
    # Exposure time set so that the geometry does not clip: only ``motion_px`` matters to apply_effects.
    out = apply_effects(img, ImageEffects(exposure_time_s=0.002), None, motion_px=np.array(motion_px))
    (cx, cy), angle, var_major, var_minor = principal_axes(out[..., 1])
    length = np.hypot(*motion_px)
    assert np.hypot(cx - 40, cy - 40) <= 0.1
    assert abs(np.sqrt(12 * var_major) - length) <= atol_px  # a uniform segment of length L: variance L^2 / 12
    assert var_minor <= 0.25
    expected = np.arctan2(motion_px[1], motion_px[0])
    assert np.rad2deg(abs(np.angle(np.exp(2j * (angle - expected))))) / 2 <= atol_deg  # an axis: modulo 180 deg


def test_the_line_kernel_sums_to_one_and_a_still_camera_is_not_blurred(camera):
    assert line_kernel(np.array([5.3, -2.1])).sum() == pytest.approx(1.0, abs=1e-6)
    world = make_world([{"east_m": 0.0, "north_m": 0.0, "size_m": 2.0, "color": "white"}])
    renderer = Renderer(world, camera)
    pose = nadir_pose()
    effects = ImageEffects(exposure_time_s=0.05)
    still = renderer.render(pose, effects, v_ned_m_s=np.zeros(3)).image_bgr
    assert np.array_equal(still, renderer.render(pose).image_bgr)
    # Flying north at 8 m/s for 50 ms at 15 m: 17 px of blur down the image, none across it.
    moving = renderer.render(pose, effects, v_ned_m_s=np.array([8.0, 0.0, 0.0])).image_bgr.astype(float)
    sharp = still.astype(float)
    grad = lambda im, axis: (np.diff(im, axis=axis) ** 2).sum()  # noqa: E731  (energy: a ramp keeps a step's total variation)
    assert grad(moving, 0) < 0.3 * grad(sharp, 0)  # edges across the motion smeared
    assert grad(moving, 1) > 0.6 * grad(sharp, 1)  # edges along it kept


# -- sensor noise --------------------------------------------------------------------------------------------------


def test_shot_noise_variance_grows_with_the_signal_over_the_read_noise():
    shot, read = 0.2, 1.5
    effects = ImageEffects(shot_noise_dn=shot, read_noise_dn=read)
    for level in (20, 80, 200):
        img = np.full((200, 200, 3), level, np.uint8)
        out = apply_effects(img, effects, np.random.default_rng(1)).astype(float)
        expected = shot * level + read**2
        assert out.var() == pytest.approx(expected + 1 / 12, rel=0.05)  # + rounding to whole grey levels
        assert out.mean() == pytest.approx(level, abs=0.05)


def test_noise_is_the_same_for_the_same_seed_and_differs_for_another():
    img = textured()
    effects = ImageEffects(shot_noise_dn=0.1, read_noise_dn=1.0)
    a = apply_effects(img, effects, np.random.default_rng(3))
    assert np.array_equal(a, apply_effects(img, effects, np.random.default_rng(3)))
    assert not np.array_equal(a, apply_effects(img, effects, np.random.default_rng(4)))


# -- configuration -------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "effects, key",
    [
        ({"glare": {"strength": -1.0}}, "effects.glare.strength"),
        ({"glare": {"haze": 1.0}}, "effects.glare.haze"),
        ({"motion_blur": {"exposure_time_s": -0.002}}, "effects.motion_blur.exposure_time_s"),
        ({"sensor_noise": {"shot_dn": -0.1}}, "effects.sensor_noise.shot_dn"),
        ({"sensor_noise": {"read_sigma_dn": -1}}, "effects.sensor_noise.read_sigma_dn"),
        ({"exposure_shift": {"gain": 0.0}}, "effects.exposure_shift.gain"),
        ({"exposure_shift": {"gain_bgr": [1.0, -1.0, 1.0]}}, "effects.exposure_shift.gain_bgr.1"),
        ({"exposure_shift": {"gain_bgr": [1.0, 1.0]}}, "effects.exposure_shift.gain_bgr"),
        ({"exposure_shift": {"gamma": -2}}, "effects.exposure_shift.gamma"),
        ({"glare": {"strenght": 1.0}}, "effects.glare.strenght: unknown key"),
    ],
)
def test_the_config_refuses_nonsense_naming_the_file_and_key(tmp_path, effects, key):
    import yaml

    path = tmp_path / "fx.yaml"
    path.write_text(yaml.safe_dump({"effects": effects}))
    with pytest.raises(ConfigError) as err:
        load_sim_config(path)
    assert str(path) in str(err.value) and key in str(err.value)


def test_effects_all_turns_every_effect_on_and_only_effects():
    sim = load_sim_config(EFFECTS_ALL)
    assert dataclasses.replace(sim, effects=SimConfig().effects) == SimConfig()
    out, back = sim.image_effects(after_gps_loss=False), sim.image_effects(after_gps_loss=True)
    assert back.has_shift and back.glare_strength > 0 and back.glare_haze > 0
    assert back.exposure_time_s > 0 and back.shot_noise_dn > 0 and back.read_noise_dn > 0
    # The map is made with the camera as it was; blur and noise are the camera's own, both ways.
    assert not out.has_shift and not out.has_glare and out.exposure_time_s == back.exposure_time_s


# -- the evaluation switches effects when GPS1 is lost --------------------------------------------------------------


class _Stop(Exception):
    pass


def test_a_mission_switches_to_the_way_backs_effects_when_gps1_is_lost(monkeypatch):
    from auxgps.config import PipelineConfig
    from auxgps.io.mission import load_mission
    from auxgps.sim.world import load_world

    seen = {}

    def fake_fly(est, su, traj, sensors, fps, **kw):
        seen["effects_after_s"], seen["denied_from_s"] = kw["effects_after_s"], sensors.gps_denied_from_s
        raise _Stop

    monkeypatch.setattr(scenario, "_fly", fake_fly)
    with pytest.raises(_Stop):
        scenario.run_mission(load_world(REPO / "config" / "worlds" / "cubes4_0.5m_different.yaml"),
                             load_mission(REPO / "config" / "missions" / "cubes_out_and_back.waypoints"), 15.0, 2.0, 3, 2.0, 1,
                             PipelineConfig(), load_sim_config(EFFECTS_ALL))
    assert 0 < seen["effects_after_s"] < np.inf and seen["effects_after_s"] == seen["denied_from_s"]


def test_the_positioning_flight_has_the_way_backs_effects_and_the_survey_not(monkeypatch):
    from auxgps.config import PipelineConfig
    from auxgps.sim.world import load_world

    calls = []

    def fake_fly(est, su, traj, sensors, fps, **kw):
        calls.append(kw.get("effects_after_s", np.inf))
        if len(calls) == 2:
            raise _Stop

    monkeypatch.setattr(scenario, "_fly", fake_fly)
    with pytest.raises(_Stop):
        scenario.run_once(load_world(REPO / "config" / "worlds" / "cubes4_0.5m_different.yaml"), 15.0, 2.0, 1,
                          PipelineConfig(), load_sim_config(EFFECTS_ALL))
    assert calls == [np.inf, -np.inf]


def test_the_setup_renders_with_the_way_back_only_when_told(camera):
    from auxgps.config import PipelineConfig
    from auxgps.sim.flight import fly
    from auxgps.sim.world import load_world

    sim = parse_as(SimConfig, {"effects": {"exposure_shift": {"gain": 0.5}}}, "x.yaml")
    su = scenario._Setup(load_world(REPO / "config" / "worlds" / "cubes4_0.5m_different.yaml"), PipelineConfig(), sim, 1)
    traj = fly(np.array([[0.0, 0.0, -15.0], [5.0, 0.0, -15.0]]), 2.0, sim.vehicle, np.random.default_rng(0), sim.dt_s)
    out = su.render(traj, 50).image_bgr.astype(float)
    back = su.render(traj, 50, after_gps_loss=True).image_bgr.astype(float)
    assert back.mean() == pytest.approx(0.5 * out.mean(), abs=atol_grey)


@pytest.mark.parametrize("name, section", [("shift", "exposure_shift"), ("glare", "glare"), ("blur", "motion_blur"),
                                           ("noise", "sensor_noise")])
def test_each_single_effect_file_is_that_effect_of_effects_all_alone(name, section):
    alone, every = load_sim_config(REPO / "config" / "sim" / f"effects_{name}.yaml"), load_sim_config(EFFECTS_ALL)
    assert alone.effects == dataclasses.replace(SimConfig().effects, **{section: getattr(every.effects, section)})
