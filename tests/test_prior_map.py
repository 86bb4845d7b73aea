"""Prior maps from an orthophoto (``auxgps map build --orthophoto``): landmarks where the ground shows them, in any CRS.

The orthophotos are made here from a known field of the local frame: squares of known corners (north/east, m),
each raster pixel coloured by whether its centre (taken to NED through rasterio.warp and pymap3d) lies in one. A
landmark of the map must then lie on a square's corner, whatever the raster's CRS; its height must be the height
model's; and the file must say where its landmarks come from.
"""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import rasterio
import rasterio.warp
from rasterio.crs import CRS
from rasterio.transform import from_origin

from auxgps.config import PipelineConfig
from auxgps.core.camera import camera_from_config
from auxgps.core.geometry import LocalFrame
from auxgps.core.prior_map import PRIOR_SEEN
from auxgps.errors import MapError
from auxgps.io.map_file import load_map, load_maps, load_photo_map, load_photo_maps
from auxgps.ortho_map import DEFAULT_GEOREF_SIGMA_M, build_prior_map

FRAME = LocalFrame(41.0356504, -83.3053108, 213.0)
UTM = CRS.from_epsg(32617)
MERCATOR = CRS.from_epsg(3857)
WGS84 = CRS.from_epsg(4326)
HALF_M, RES_M = 30.0, 0.1
FOCAL_PX = camera_from_config(PipelineConfig().camera).focal_px


def _squares(seed=3, n=70):
    rng = np.random.default_rng(seed)
    c = rng.uniform(-HALF_M + 4, HALF_M - 4, (n, 2))
    side = rng.uniform(1.2, 2.6, n)
    grey = rng.choice([30, 60, 200, 230], n)
    return c, side, grey


def _corners_ne(squares):
    c, side, _ = squares
    h = side[:, None] / 2
    return np.vstack([c + np.hstack([sn * h, se * h]) for sn in (-1, 1) for se in (-1, 1)])


def _grid(crs, half_m, res_m):
    x0, y0 = rasterio.warp.transform(WGS84, crs, [FRAME.lon_deg], [FRAME.lat_deg])
    # CRS units per ground metre along x and along y (one metre east, one north; conformal: either way for UTM)
    lat1, lon1, _ = FRAME.to_geodetic(np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]))
    x1, y1 = rasterio.warp.transform(WGS84, crs, list(lon1), list(lat1))
    sx = float(np.hypot(x1[0] - x0[0], y1[0] - y0[0]))
    sy = float(np.hypot(x1[1] - x0[0], y1[1] - y0[0]))
    w = h = int(round(2 * half_m / res_m))
    return from_origin(x0[0] - half_m * sx, y0[0] + half_m * sy, res_m * sx, res_m * sy), w, h


def _centres_ne(crs, transform, w, h):
    cols, rows = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    x, y = transform @ (cols, rows)
    lon, lat = rasterio.warp.transform(crs, WGS84, x.ravel(), y.ravel())
    ned = FRAME.to_ned(lat_deg=np.array(lat), lon_deg=np.array(lon), alt_amsl_m=np.full(len(lat), FRAME.alt_amsl_m))
    return ned[:, 0].reshape(h, w), ned[:, 1].reshape(h, w)


def write_ortho(path: Path, crs, squares, tags=None, with_crs=True) -> Path:
    transform, w, h = _grid(crs, HALF_M, RES_M)
    n, e = _centres_ne(crs, transform, w, h)
    grey = np.full((h, w), 128, np.uint8)
    for (cn, ce), s, g in zip(*squares):
        grey[(np.abs(n - cn) <= s / 2) & (np.abs(e - ce) <= s / 2)] = g
    profile = dict(driver="GTiff", width=w, height=h, count=3, dtype="uint8", transform=transform)
    if with_crs:
        profile["crs"] = crs
    with rasterio.open(path, "w", **profile) as ds:
        ds.write(np.repeat(grey[None], 3, axis=0))
        if tags:
            ds.update_tags(**tags)
    return path


def write_dsm(path: Path, crs, height_fn) -> Path:
    transform, w, h = _grid(crs, HALF_M + 2, 0.5)
    n, e = _centres_ne(crs, transform, w, h)
    with rasterio.open(path, "w", driver="GTiff", width=w, height=h, count=1, dtype="float32", crs=crs, transform=transform) as ds:
        ds.write((FRAME.alt_amsl_m + height_fn(n, e)).astype(np.float32)[None])
    return path


@pytest.fixture(scope="module")
def squares():
    return _squares()


def _landmarks_ne(report):
    p = report.columns["p_ned_m"].astype(float)
    lat, lon, alt = report.frame.to_geodetic(p)
    return FRAME.to_ned(lat_deg=lat, lon_deg=lon, alt_amsl_m=alt)


def _corner_offsets_m(report, squares):
    """(N, 2) north/east of each landmark from its nearest square corner, m."""
    p = _landmarks_ne(report)[:, :2]
    d = p[:, None, :] - _corners_ne(squares)[None]
    return d[np.arange(len(p)), np.argmin(np.linalg.norm(d, axis=2), axis=1)]


def _corner_distance_m(report, squares):
    return np.linalg.norm(_corner_offsets_m(report, squares), axis=1)


@pytest.mark.parametrize("crs", [UTM, MERCATOR, WGS84], ids=["utm", "web-mercator", "wgs84-degrees"])
def test_landmarks_lie_on_the_corners_the_orthophoto_shows(tmp_path, squares, crs):
    ortho = write_ortho(tmp_path / "o.tif", crs, squares)
    report = build_prior_map(ortho, pipeline=PipelineConfig(), ground_alt_amsl_m=FRAME.alt_amsl_m)
    assert report.count > 100
    assert report.gsd_m == pytest.approx(RES_M, rel=0.02)
    off = _corner_offsets_m(report, squares)
    d = np.linalg.norm(off, axis=1)
    # A corner drawn on whole pixels, found by FAST and refined: within about a pixel, and no offset common to
    # all of them (a half-pixel convention or a CRS mistake would be one).
    assert np.median(d) < 0.8 * RES_M
    assert np.mean(d < 3 * RES_M) > 0.9
    assert np.all(np.abs(np.mean(off[d < 1.5 * RES_M], axis=0)) < 0.2 * RES_M)
    # Flat ground at the stated height: the origin's, so every landmark is at down 0.
    assert np.allclose(report.columns["p_ned_m"][:, 2], 0.0, atol=0.02)
    # Usable for positioning from the start, never counted against by the flight.
    assert np.all(report.columns["n_seen"] == PRIOR_SEEN)
    # The range from which the flight's camera sees the ground at the map's scale.
    assert np.allclose(report.columns["descriptor_range_m"].astype(float), RES_M * FOCAL_PX, rtol=0.01)


def test_a_coarser_build_keeps_the_places_and_scales_the_descriptor_range(tmp_path, squares):
    ortho = write_ortho(tmp_path / "o.tif", UTM, squares)
    report = build_prior_map(ortho, pipeline=PipelineConfig(), gsd_m=0.3, ground_alt_amsl_m=FRAME.alt_amsl_m)
    assert report.gsd_m == 0.3
    d = _corner_distance_m(report, squares)
    assert np.median(d) < 0.8 * 0.3
    r = report.columns["descriptor_range_m"].astype(float)
    assert np.allclose(r, 0.3 * FOCAL_PX, rtol=0.01)
    with pytest.raises(MapError, match="finer than the orthophoto"):
        build_prior_map(ortho, pipeline=PipelineConfig(), gsd_m=0.05)


def test_heights_come_from_the_height_model(tmp_path, squares):
    ortho = write_ortho(tmp_path / "o.tif", UTM, squares)
    dsm = write_dsm(tmp_path / "dsm.tif", MERCATOR, lambda n, e: 0.1 * e + 2.0)
    report = build_prior_map(ortho, pipeline=PipelineConfig(), dsm_path=dsm)
    assert report.heights == "dsm"
    p = _landmarks_ne(report)
    # Up is -down, about the test's frame: the DSM's 0.1 * east + 2 (bilinear on a plane is exact).
    assert np.allclose(-p[:, 2], 0.1 * p[:, 1] + 2.0, atol=0.03)


def test_the_placement_error_is_the_sources_not_each_landmarks(tmp_path, squares):
    ortho = write_ortho(tmp_path / "o.tif", UTM, squares)
    report = build_prior_map(ortho, pipeline=PipelineConfig())
    assert report.source.georef_sigma_h_m == DEFAULT_GEOREF_SIGMA_M
    assert any("placement error" in m for m in report.messages)
    assert report.heights == "datum 0 m" and report.frame.alt_amsl_m == 0.0
    # Per landmark: a fraction of a pixel and the orthophoto's own distortion, not the 2 m.
    info = report.columns["info_packed"].astype(float)
    assert np.all(1.0 / np.sqrt(info[:, 0]) < 0.3)
    tagged = write_ortho(tmp_path / "t.tif", UTM, squares, tags={"AUXGPS_GEOREF_SIGMA_H_M": "0.7", "AUXGPS_GROUND_ALT_AMSL_M": "213"})
    r2 = build_prior_map(tagged, pipeline=PipelineConfig())
    assert r2.source.georef_sigma_h_m == 0.7 and r2.frame.alt_amsl_m == 213.0
    assert build_prior_map(tagged, pipeline=PipelineConfig(), georef_sigma_m=0.2).source.georef_sigma_h_m == 0.2
    # The ground plane auxgps ortho build fitted, with its slope: heights rise with it from the centre.
    sloped = write_ortho(tmp_path / "s.tif", UTM, squares, tags={"AUXGPS_GROUND_ALT_AMSL_M": "213", "AUXGPS_GROUND_SLOPE": "0.02 -0.05"})
    r3 = build_prior_map(sloped, pipeline=PipelineConfig())
    p = r3.columns["p_ned_m"].astype(float)
    assert np.allclose(-p[:, 2], 0.02 * p[:, 0] - 0.05 * p[:, 1], atol=0.01)
    bad = write_ortho(tmp_path / "b.tif", UTM, squares, tags={"AUXGPS_GROUND_ALT_AMSL_M": "213", "AUXGPS_GROUND_SLOPE": "0.02"})
    with pytest.raises(MapError, match="AUXGPS_GROUND_SLOPE"):
        build_prior_map(bad, pipeline=PipelineConfig())


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "auxgps.cli", *map(str, args)], capture_output=True, text=True)


def test_the_command_writes_maps_that_keep_their_source(tmp_path, squares):
    ortho = write_ortho(tmp_path / "o.tif", UTM, squares)
    out = _cli("map", "build", "--orthophoto", ortho, "--ground-alt-m", 213, "--georef-sigma-m", 0.5, "--out", tmp_path / "prior.npz", "--quiet")
    assert out.returncode == 0, out.stderr
    assert "landmarks" in out.stdout and "for auxgps run" in out.stdout
    lm, frame = load_map(tmp_path / "prior.npz")
    assert [s.kind for s in lm.sources] == ["flight", "orthophoto"] and lm.sources[1].georef_sigma_h_m == 0.5
    assert np.all(lm.source[: len(lm)] == 1)
    out = _cli("map", "build", "--orthophoto", ortho, "--descriptor", "sift", "--out", tmp_path / "prior_sift.npz", "--quiet")
    assert out.returncode == 0, out.stderr
    pm, _ = load_photo_map(tmp_path / "prior_sift.npz")
    assert len(pm) > 100 and pm.georef_sigma_h_m == DEFAULT_GEOREF_SIGMA_M


def test_maps_merge_into_one_frame_each_landmark_keeping_its_source(tmp_path, squares):
    a = write_ortho(tmp_path / "a.tif", UTM, squares)
    b = write_ortho(tmp_path / "b.tif", MERCATOR, _squares(seed=9))
    for name, path, sigma in (("a", a, "0.5"), ("b", b, "1.5")):
        assert _cli("map", "build", "--orthophoto", path, "--ground-alt-m", 213, "--georef-sigma-m", sigma,
                    "--out", tmp_path / f"{name}.npz", "--quiet").returncode == 0
    lm_a, fa = load_map(tmp_path / "a.npz")
    lm_b, fb = load_map(tmp_path / "b.npz")
    merged, frame = load_maps([tmp_path / "a.npz", tmp_path / "b.npz"])
    assert frame == fa and len(merged) == len(lm_a) + len(lm_b)
    assert [s.name for s in merged.sources] == ["", "a.tif", "b.tif"]
    ids_b = np.arange(len(lm_a), len(merged))
    assert np.all(merged.source[ids_b] == 2) and merged.shared_sigma_h_m(ids_b) == 1.5
    assert merged.source_name(ids_b) == "b.tif"
    # b's landmarks, moved into a's frame, are where they were on Earth.
    lat, lon, alt = frame.to_geodetic(merged.p_ned_m[ids_b].astype(float))
    back = fb.to_ned(lat_deg=lat, lon_deg=lon, alt_amsl_m=alt)
    assert np.allclose(back, lm_b.p_ned_m[: len(lm_b)], atol=0.01)
    mixed = np.array([0, 1, len(lm_a), len(lm_a) + 1])
    assert merged.shared_sigma_h_m(mixed) == pytest.approx(np.sqrt((0.5**2 + 1.5**2) / 2))
    for name, path in (("a", a), ("b", b)):
        assert _cli("map", "build", "--orthophoto", path, "--descriptor", "sift", "--out", tmp_path / f"{name}_s.npz", "--quiet").returncode == 0
    pm, _ = load_photo_maps([tmp_path / "a_s.npz", tmp_path / "b_s.npz"])
    assert [s.name for s in pm.sources] == ["a.tif", "b.tif"]


def test_an_orthophoto_without_a_crs_is_refused_in_one_line(tmp_path, squares):
    ortho = write_ortho(tmp_path / "nocrs.tif", UTM, squares, with_crs=False)
    out = _cli("map", "build", "--orthophoto", ortho, "--out", tmp_path / "m.npz")
    assert out.returncode == 1
    assert out.stderr.strip().count("\n") == 0 and "no CRS" in out.stderr
    assert not (tmp_path / "m.npz").exists()
    out = _cli("map", "build", "--orthophoto", tmp_path / "absent.tif", "--out", tmp_path / "m.npz")
    assert out.returncode == 1 and "no such file" in out.stderr


# -- positioning on a prior map alone ---------------------------------------------------------------------------


def write_texture_ortho(path: Path, seed: int, half_m=90.0, res_m=0.1) -> Path:
    """A natural-looking ground (smooth noise at several scales, as fields and tracks give) in UTM."""
    import cv2

    transform, w, h = _grid(UTM, half_m, res_m)
    rng = np.random.default_rng(seed)
    grey = np.zeros((h, w))
    for cell_px, weight in ((160, 1.0), (40, 0.7), (10, 0.5), (3, 0.3)):
        small = rng.normal(size=(h // cell_px + 2, w // cell_px + 2))
        grey += weight * cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)
    grey = np.clip(128 + 40 * grey, 0, 255).astype(np.uint8)
    with rasterio.open(path, "w", driver="GTiff", width=w, height=h, count=3, dtype="uint8", crs=UTM, transform=transform,
                       tiled=True, blockxsize=256, blockysize=256) as ds:
        ds.write(np.repeat(grey[None], 3, axis=0))
        ds.build_overviews([2, 4, 8], rasterio.enums.Resampling.average)
    return path


def _locate_on(map_report, world_ortho: Path, tmp_path: Path, p_true, euler_deg, prior_offset_m=(1.0, -0.8)):
    """A frame of ``world_ortho`` rendered from the true pose, located on the prior map alone, as positioning does."""
    import yaml

    from auxgps.core.features import FeatureDetector
    from auxgps.core.geometry import R_body_cam_from_mount, R_ned_body_from_euler
    from auxgps.core.camera import CameraPose
    from auxgps.core.landmarks import LandmarkMap
    from auxgps.core.localise import Localiser, PositionPrior
    from auxgps.core.prior_map import FLIGHT
    from auxgps.sim.render import Renderer
    from auxgps.sim.world import load_world

    cfg = PipelineConfig()
    camera = camera_from_config(cfg.camera)
    world_yaml = tmp_path / "world.yaml"
    world_yaml.write_text(yaml.safe_dump({"origin": {"lat_deg": FRAME.lat_deg, "lon_deg": FRAME.lon_deg, "alt_amsl_m": FRAME.alt_amsl_m},
                                          "ground": {"orthophoto": str(world_ortho)}}))
    R_body_cam = R_body_cam_from_mount()
    R_ned_body = R_ned_body_from_euler(*np.deg2rad(euler_deg))
    image = Renderer(load_world(world_yaml), camera).render(CameraPose(np.asarray(p_true, float), R_ned_body @ R_body_cam)).image_bgr
    c = map_report.columns
    lm = LandmarkMap.from_columns({**c, "source": np.ones(map_report.count, np.uint8)}, sources=[FLIGHT, map_report.source])
    # The map's frame is the orthophoto's centre, here the test's origin (both at the same ground height).
    assert np.hypot(*FRAME.to_ned(lat_deg=map_report.frame.lat_deg, lon_deg=map_report.frame.lon_deg, alt_amsl_m=FRAME.alt_amsl_m)[:2]) < 0.2
    loc = Localiser(cfg, camera, R_body_cam, lm)
    alt = -float(p_true[2])
    prior = PositionPrior(np.array([p_true[0] + prior_offset_m[0], p_true[1] + prior_offset_m[1], p_true[2]]), 2.0)
    scale = loc.detection_scale(alt, prior)
    feats = FeatureDetector(cfg.detector).detect(image, R_ned_body @ R_body_cam, scale)
    return loc.locate(feats, 0.0, R_ned_body, alt, prior), scale


@pytest.fixture(scope="module")
def textured(tmp_path_factory):
    d = tmp_path_factory.mktemp("textured")
    world = write_texture_ortho(d / "ground.tif", seed=1)
    other = write_texture_ortho(d / "elsewhere.tif", seed=2)
    report = build_prior_map(world, pipeline=PipelineConfig(), gsd_m=0.3, ground_alt_amsl_m=FRAME.alt_amsl_m, georef_sigma_m=1.0)
    return world, other, report


@pytest.mark.parametrize("p_true, euler_deg", [((12.0, -20.0, -60.0), (2.0, -3.0, 30.0)), ((-30.0, 25.0, -45.0), (-4.0, 1.0, -100.0))])
def test_a_frame_is_located_on_a_coarser_prior_map_alone(tmp_path, textured, p_true, euler_deg):
    from auxgps.core.localise import Fix

    world, _, report = textured
    fix, scale = _locate_on(report, world, tmp_path, p_true, euler_deg)
    # Seen from 45 to 60 m, the frame (about 0.07 to 0.09 m a pixel at nadir) is detected shrunk toward the
    # map's 0.3 m (to the median range of the landmarks in reach, which reach beyond the view).
    assert scale < 0.6
    assert isinstance(fix, Fix), fix
    err = float(np.hypot(*(fix.p_ned_m[:2] - np.asarray(p_true[:2]))))
    assert err < 0.6, err  # two pixels of the prior map
    assert fix.map_source == "ground.tif" and fix.prior_share == 1.0
    # Its covariance is the fit's; the orthophoto's placement error is the filter's to carry, not in here.
    assert fix.sigma_h_rms_m < 1.0


def test_a_prior_map_that_matches_nothing_gives_no_fix(tmp_path, textured):
    from auxgps.core.localise import NoFix

    world, other, report = textured
    fix, _ = _locate_on(report, other, tmp_path, (12.0, -20.0, -60.0), (2.0, -3.0, 30.0))
    assert isinstance(fix, NoFix), fix
