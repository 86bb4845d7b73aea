"""Orthophoto worlds: a georeferenced GeoTIFF (any CRS) as the ground, optionally over a height model.

The rasters are made here, in tmp_path, from known fields of the local frame: each raster pixel's centre is taken
to NED (rasterio.warp.transform to WGS84, then pymap3d) and given the colour of a smooth pattern there (or the
height of a known surface). A rendered pixel must then show the pattern at the point the renderer says is behind
it, whatever the raster's CRS.
"""

from pathlib import Path

import numpy as np
import pytest
import rasterio
import rasterio.warp
import yaml
from rasterio.crs import CRS
from rasterio.transform import from_origin

from auxgps.core.camera import CameraPose, PinholeCamera
from auxgps.core.frame_check import FrameCheck
from auxgps.core.geometry import R_BODY_CAM_DOWN, LocalFrame, R_ned_body_from_euler
from auxgps.errors import ConfigError
from auxgps.sim.geoground import OFF_RASTER_BGR
from auxgps.sim.render import Renderer
from auxgps.sim.world import load_world

ORIGIN = {"lat_deg": 46.842371, "lon_deg": -91.993954, "alt_amsl_m": 158.5}
FRAME = LocalFrame(ORIGIN["lat_deg"], ORIGIN["lon_deg"], ORIGIN["alt_amsl_m"])
UTM = CRS.from_epsg(32615)  # UTM zone 15N, where the origin lies
MERCATOR = CRS.from_epsg(3857)

atol_grey = 4.0  # grey levels, per pixel: uint8 rounding and bilinear resampling of the 1.6 m pattern at 4-5 cm
atol_grey_mean = 1.5  # grey levels, mean over a frame: about 3 mm of misplacement on this pattern
atol_height_m = 0.005  # 5 mm: the DSM grid's bilinear surface and the refined ray crossing


def pattern_bgr(n_m, e_m):
    """A smooth colour field of the local frame, (...) north, east, m -> (..., 3) float in 30..225."""
    b = 127.5 + 95 * np.sin(2 * np.pi * n_m / 1.6)
    g = 127.5 + 95 * np.sin(2 * np.pi * e_m / 1.3 + 1.0)
    r = 127.5 + 95 * np.sin(2 * np.pi * (n_m + e_m) / 2.1 + 2.0)
    return np.stack([b, g, r], axis=-1)


def step_height_m(n_m, e_m):
    """A 3 m plateau north of 4 m, a gentle slope (5 %) east elsewhere: height above the origin, m."""
    return np.where(n_m > 4.0, 3.0, 0.05 * e_m)


def _pixel_centres_ned(crs, transform, width, height):
    cols, rows = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    x, y = transform @ (cols, rows)
    lon, lat = rasterio.warp.transform(crs, CRS.from_epsg(4326), x.ravel(), y.ravel())
    ned = FRAME.to_ned(lat_deg=np.array(lat), lon_deg=np.array(lon), alt_amsl_m=np.full(len(lat), FRAME.alt_amsl_m))
    return ned[:, 0].reshape(height, width), ned[:, 1].reshape(height, width)


def _grid_around_origin(crs, half_m, res_m):
    """A north-up transform in ``crs`` whose pixels are about ``res_m`` metres, covering +-half_m about the origin."""
    x0, y0 = rasterio.warp.transform(CRS.from_epsg(4326), crs, [FRAME.lon_deg], [FRAME.lat_deg])
    # metres per CRS unit at the origin, from a point 1 m north-east
    lat1, lon1, _ = FRAME.to_geodetic(np.array([1.0, 1.0, 0.0]))
    x1, y1 = rasterio.warp.transform(CRS.from_epsg(4326), crs, [float(lon1)], [float(lat1)])
    sx, sy = abs(x1[0] - x0[0]), abs(y1[0] - y0[0])  # CRS units per metre east, north
    width = height = int(round(2 * half_m / res_m))
    return from_origin(x0[0] - half_m * sx, y0[0] + half_m * sy, res_m * sx, res_m * sy), width, height


def write_ortho(path: Path, crs, half_m=12.0, res_m=0.04, overviews=(2, 4)) -> Path:
    transform, w, h = _grid_around_origin(crs, half_m, res_m)
    n, e = _pixel_centres_ned(crs, transform, w, h)
    bgr = np.clip(np.rint(pattern_bgr(n, e)), 0, 255).astype(np.uint8)
    with rasterio.open(path, "w", driver="GTiff", width=w, height=h, count=3, dtype="uint8", crs=crs, transform=transform,
                       tiled=True, blockxsize=256, blockysize=256, compress="deflate") as ds:
        ds.write(np.moveaxis(bgr[..., ::-1], -1, 0))  # RGB bands
        if overviews:
            ds.build_overviews(list(overviews), rasterio.enums.Resampling.average)
    return path


def write_dsm(path: Path, crs, height_fn, half_m=14.0, res_m=0.1) -> Path:
    transform, w, h = _grid_around_origin(crs, half_m, res_m)
    n, e = _pixel_centres_ned(crs, transform, w, h)
    z = (FRAME.alt_amsl_m + height_fn(n, e)).astype(np.float32)
    with rasterio.open(path, "w", driver="GTiff", width=w, height=h, count=1, dtype="float32", crs=crs, transform=transform) as ds:
        ds.write(z[None])
    return path


def write_world(tmp_path: Path, ground: dict, cubes=(), name="world.yaml") -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump({"origin": ORIGIN, "ground": ground, "cubes": list(cubes)}))
    return path


@pytest.fixture(scope="module")
def rasters(tmp_path_factory):
    d = tmp_path_factory.mktemp("rasters")
    return {
        "utm": write_ortho(d / "ortho_utm.tif", UTM),
        "mercator": write_ortho(d / "ortho_3857.tif", MERCATOR),
        "dsm_utm": write_dsm(d / "dsm_utm.tif", UTM, step_height_m),
        "dsm_4326": write_dsm(d / "dsm_4326.tif", CRS.from_epsg(4326), step_height_m),
        "dsm_flat": write_dsm(d / "dsm_flat.tif", UTM, lambda n, e: np.zeros_like(n)),
    }


@pytest.fixture(scope="module")
def cam():
    return PinholeCamera.from_hfov(640, 360, np.pi / 2)


POSES = [  # (north, east, down) m; roll, pitch, yaw rad
    ((0.0, 0.0, -8.0), (0.0, 0.0, 0.0)),
    ((1.5, -2.0, -6.0), (0.12, -0.08, 0.7)),
    ((-3.0, 2.5, -9.0), (-0.1, 0.15, 2.4)),
]


def _pose(p, a):
    return CameraPose(np.array(p, float), R_ned_body_from_euler(*a) @ R_BODY_CAM_DOWN)


def _interior(frame, margin_px=4, half_m=11.5):
    """Pixels away from the image border that show ground on the test rasters."""
    m = np.zeros(frame.depth_m.shape, bool)
    m[margin_px:-margin_px, margin_px:-margin_px] = True
    m &= np.isfinite(frame.depth_m)
    with np.errstate(invalid="ignore"):
        p = frame.points_ned()
    return m & (np.abs(p[..., 0]) < half_m) & (np.abs(p[..., 1]) < half_m)


def _pattern_error(frame):
    """Per-pixel |rendered colour - pattern at the true point behind the pixel|, grey levels, (N, 3)."""
    p = frame.points_ned()
    mask = _interior(frame)
    return np.abs(frame.image_bgr[mask].astype(float) - pattern_bgr(p[..., 0][mask], p[..., 1][mask]))


@pytest.mark.parametrize("crs_name", ["utm", "mercator"])
def test_a_pixel_shows_the_pattern_at_its_true_point(tmp_path, rasters, cam, crs_name):
    world = load_world(write_world(tmp_path, {"orthophoto": str(rasters[crs_name])}))
    renderer = Renderer(world, cam)
    for p, a in POSES:
        frame = renderer.render(_pose(p, a))
        err = _pattern_error(frame)
        assert err.mean() <= atol_grey_mean and np.percentile(err, 99) <= atol_grey, (p, err.mean(), np.percentile(err, 99))
        # flat ground: the truth is on the plane down = 0
        assert np.allclose(frame.points_ned()[..., 2][_interior(frame)], 0.0, atol=1e-4)


def test_ground_off_the_orthophoto_and_under_its_mask_is_featureless_grey(tmp_path, cam):
    """A camera sees ground beyond a survey, not a covered lens: off the raster and under its no-data mask the
    ground renders as OFF_RASTER_BGR (one flat colour, nothing to detect), the rest as the orthophoto, and the
    frame check does not call the frame black."""
    path = write_ortho(tmp_path / "masked.tif", UTM, overviews=())
    with rasterio.open(path, "r+") as ds:
        mask = np.full((ds.height, ds.width), 255, np.uint8)
        mask[: ds.height // 2] = 0  # the northern half: no data
        ds.write_mask(mask)
    frame = Renderer(load_world(write_world(tmp_path, {"orthophoto": str(path)})), cam).render(_pose((0.0, 0.0, -20.0), (0.0, 0.0, 0.0)))
    p = frame.points_ned()
    n, e = p[..., 0], p[..., 1]
    on_raster = (np.abs(n) < 11.5) & (np.abs(e) < 11.5)
    masked = on_raster & (n > 0.5)
    off = (np.abs(e) > 12.5) | (np.abs(n) > 12.5)
    shown = on_raster & (n < -0.5)
    assert masked.sum() > 1000 and off.sum() > 1000 and shown.sum() > 1000
    assert np.all(frame.image_bgr[masked | off] == OFF_RASTER_BGR)
    err = np.abs(frame.image_bgr[shown].astype(float) - pattern_bgr(n[shown], e[shown]))
    assert err.mean() <= atol_grey_mean and np.percentile(err, 99) <= atol_grey
    assert "black" not in (FrameCheck().check(0.0, frame.image_bgr, None) or "")


def test_a_raster_pixel_is_seen_where_geometry_puts_it(tmp_path, cam):
    """A single white pixel in a dark UTM raster, seen at 1:1 scale from straight above, lands within a pixel of
    where the camera projects its centre."""
    res_m, half_m = 0.05, 10.0
    transform, w, h = _grid_around_origin(UTM, half_m, res_m)
    img = np.full((3, h, w), 40, np.uint8)
    row, col = 150, 260
    img[:, row, col] = 250
    path = tmp_path / "dot.tif"
    with rasterio.open(path, "w", driver="GTiff", width=w, height=h, count=3, dtype="uint8", crs=UTM, transform=transform) as ds:
        ds.write(img)
    n, e = _pixel_centres_ned(UTM, transform, w, h)
    p_dot = np.array([n[row, col], e[row, col], 0.0])
    world = load_world(write_world(tmp_path, {"orthophoto": str(path)}))
    alt_m = res_m * cam.K[0, 0]  # one output pixel = one raster pixel
    pose = _pose((p_dot[0] + 0.3, p_dot[1] - 0.4, -alt_m), (0.0, 0.0, 0.4))
    frame = Renderer(world, cam).render(pose)
    uv, front = pose.project(cam, p_dot[None])
    grey = frame.image_bgr.astype(float).mean(axis=2)
    v, u = np.unravel_index(np.argmax(grey), grey.shape)
    # the bright blob's centroid
    win = grey[v - 3 : v + 4, u - 3 : u + 4] - 40.0
    vv, uu = np.mgrid[v - 3 : v + 4, u - 3 : u + 4]
    centroid = np.array([(uu * win).sum() / win.sum(), (vv * win).sum() / win.sum()])
    assert front[0] and np.linalg.norm(centroid - uv[0]) <= 0.5, (centroid, uv[0])


def test_the_same_world_in_two_crs_renders_the_same_image(tmp_path, rasters, cam):
    a = Renderer(load_world(write_world(tmp_path, {"orthophoto": str(rasters["utm"])}, name="a.yaml")), cam)
    b = Renderer(load_world(write_world(tmp_path, {"orthophoto": str(rasters["mercator"])}, name="b.yaml")), cam)
    for p, ang in POSES:
        fa, fb = a.render(_pose(p, ang)), b.render(_pose(p, ang))
        diff = np.abs(fa.image_bgr.astype(float) - fb.image_bgr.astype(float))[_interior(fa)]
        assert diff.mean() <= atol_grey_mean and np.percentile(diff, 99) <= atol_grey
        np.testing.assert_array_equal(fa.depth_m, fb.depth_m)


def test_overviews_and_the_block_cache(tmp_path, rasters, cam):
    world = load_world(write_world(tmp_path, {"orthophoto": str(rasters["utm"])}))
    renderer = Renderer(world, cam)
    high = _pose((0.0, 0.0, -30.0), (0.0, 0.0, 0.3))  # 15 cm per output pixel: the 4x overview (16 cm) is too coarse, 2x fits
    frame = renderer.render(high)
    reads = world.ground_orthophoto.reads
    again = renderer.render(high)
    assert world.ground_orthophoto.reads == reads  # the second frame came from the cache
    np.testing.assert_array_equal(frame.image_bgr, again.image_bgr)
    err = _pattern_error(frame)
    assert err.mean() <= 3 * atol_grey_mean  # the overview averages the pattern a little
    assert [lv.factor for lv in world.ground_orthophoto.levels] == [1.0, 2.0, 4.0]


def test_a_flat_dsm_renders_as_no_dsm(tmp_path, rasters, cam):
    flat = Renderer(load_world(write_world(tmp_path, {"orthophoto": str(rasters["utm"])}, name="a.yaml")), cam)
    relief = Renderer(load_world(write_world(tmp_path, {"orthophoto": str(rasters["utm"]), "dsm": str(rasters["dsm_flat"])}, name="b.yaml")), cam)
    for p, a in POSES:
        fa, fb = flat.render(_pose(p, a)), relief.render(_pose(p, a))
        m = _interior(fa)
        # within 15 m of the origin the ellipsoid is under 0.02 mm below the tangent plane
        np.testing.assert_allclose(fb.depth_m[m], fa.depth_m[m], rtol=2e-4)
        diff = np.abs(fa.image_bgr.astype(float) - fb.image_bgr.astype(float))[m]
        assert diff.mean() <= atol_grey_mean


@pytest.mark.parametrize("dsm", ["dsm_utm", "dsm_4326"])
def test_relief_truth_lies_on_the_dsm_and_shows_the_orthophoto(tmp_path, rasters, cam, dsm):
    world = load_world(write_world(tmp_path, {"orthophoto": str(rasters["utm"]), "dsm": str(rasters[dsm])}))
    renderer = Renderer(world, cam)
    for p, a in [((4.0, 0.0, -9.0), (0.0, 0.0, 0.0)), ((2.0, -1.0, -8.0), (0.1, -0.25, 0.5))]:
        frame = renderer.render(_pose(p, a))
        pts = frame.points_ned()
        m = _interior(frame)
        n, e, d = pts[..., 0][m], pts[..., 1][m], pts[..., 2][m]
        away = np.abs(n - 4.0) > 0.25  # off the step's edge (the DSM's 0.1 m cells blend it over one cell)
        assert away.mean() > 0.8 and (n > 4.5).any() and (n < 3.5).any()  # both levels in view
        np.testing.assert_allclose(-d[away], step_height_m(n[away], e[away]), atol=atol_height_m)
        err = np.abs(frame.image_bgr[m].astype(float) - pattern_bgr(n, e))
        assert err[away].mean() <= atol_grey_mean and np.percentile(err[away], 99) <= 2 * atol_grey


def test_the_plateau_hides_the_ground_behind_its_edge(tmp_path, rasters, cam):
    """Looking north at a slant from south of the 3 m step: rays that would reach the low ground just north of the
    edge meet the step's face or the plateau first."""
    world = load_world(write_world(tmp_path, {"orthophoto": str(rasters["utm"]), "dsm": str(rasters["dsm_utm"])}))
    pose = _pose((-2.0, 0.0, -7.0), (0.0, 0.6, 0.0))  # nose up 0.6 rad: the camera looks ahead, north
    frame = Renderer(world, cam).render(pose)
    pts = frame.points_ned()[_interior(frame)]
    # nothing low is seen beyond the edge (the DSM's 0.1 m cells, resampled, blend the step over about 0.25 m)
    assert not np.any((pts[:, 0] > 4.3) & (pts[:, 2] > -2.99))
    assert np.any(pts[:, 0] > 4.5)  # the plateau is seen


def test_cubes_stand_on_the_dsm_and_occlude(tmp_path, rasters, cam):
    cubes = [{"north_m": 6.0, "east_m": 0.0, "size_m": 1.0, "color": "red"}, {"north_m": 0.0, "east_m": -2.0, "size_m": 0.5, "color": "blue"}]
    world = load_world(write_world(tmp_path, {"orthophoto": str(rasters["utm"]), "dsm": str(rasters["dsm_utm"])}, cubes))
    on_plateau, on_slope = world.cubes
    assert on_plateau.vertices_ned()[:4, 2] == pytest.approx(-3.0, abs=1e-3)
    assert on_slope.vertices_ned()[:4, 2] == pytest.approx(-step_height_m(0.0, -2.0), abs=1e-3)
    pose = _pose((6.0, 0.0, -10.0), (0.0, 0.0, 0.0))
    frame = Renderer(world, cam).render(pose)
    c = np.array([cam.K[0, 2], cam.K[1, 2]])
    top = frame.true_points_at(c[None])[0]
    np.testing.assert_allclose(top, [6.0, 0.0, -4.0], atol=1e-3)  # the cube's top, 1 m above the plateau
    b, g, r = frame.image_bgr[int(c[1]), int(c[0])]
    assert r > 2 * max(b, g)


def test_a_flat_dsm_world_matches_flat_ground_without_curvature_error(tmp_path, rasters):
    world = load_world(write_world(tmp_path, {"orthophoto": str(rasters["utm"]), "dsm": str(rasters["dsm_flat"])}))
    assert world.ground_down_m(np.array([[0.0, 0.0], [10.0, -10.0]])) == pytest.approx([0.0, 0.0], abs=1e-4)


# -- errors: one clear line naming the key and the file -------------------------------------------------------


def _config_error(path) -> str:
    with pytest.raises(ConfigError) as err:
        load_world(path)
    text = str(err.value)
    assert "\n" not in text and str(path) in text
    return text


def test_missing_orthophoto(tmp_path):
    text = _config_error(write_world(tmp_path, {"orthophoto": "nowhere.tif"}))
    assert "ground.orthophoto" in text and "no such file" in text and "nowhere.tif" in text


def test_raster_without_crs(tmp_path):
    path = tmp_path / "plain.tif"
    with rasterio.open(path, "w", driver="GTiff", width=8, height=8, count=3, dtype="uint8") as ds:
        ds.write(np.zeros((3, 8, 8), np.uint8))
    assert "no CRS" in _config_error(write_world(tmp_path, {"orthophoto": "plain.tif"}))


def test_origin_outside_the_raster(tmp_path):
    transform, w, h = _grid_around_origin(UTM, 5.0, 0.1)
    path = tmp_path / "away.tif"
    far = transform @ rasterio.Affine.translation(2000, 0)  # 200 m east of the origin
    with rasterio.open(path, "w", driver="GTiff", width=w, height=h, count=3, dtype="uint8", crs=UTM, transform=far) as ds:
        ds.write(np.zeros((3, h, w), np.uint8))
    text = _config_error(write_world(tmp_path, {"orthophoto": "away.tif"}))
    assert "ground.orthophoto" in text and "outside" in text


def test_not_a_raster_and_bad_bands(tmp_path, rasters):
    (tmp_path / "junk.tif").write_text("not a tiff")
    assert "cannot read" in _config_error(write_world(tmp_path, {"orthophoto": "junk.tif"}))
    text = _config_error(write_world(tmp_path, {"orthophoto": str(rasters["dsm_utm"])}, name="bands.yaml"))
    assert "uint8" in text


def test_dsm_keys(tmp_path, rasters):
    assert "dsm goes with orthophoto" in _config_error(write_world(tmp_path, {"color": "grey", "dsm": str(rasters["dsm_utm"])}))
    text = _config_error(write_world(tmp_path, {"orthophoto": str(rasters["utm"]), "dsm": "missing_dsm.tif"}, name="b.yaml"))
    assert "ground.dsm" in text and "missing_dsm.tif" in text
    assert "exactly one" in _config_error(write_world(tmp_path, {"color": "grey", "orthophoto": str(rasters["utm"])}, name="c.yaml"))


def test_the_rendering_benchmark_runs_on_a_small_raster(tmp_path, cam):
    """`auxgps bench`'s orthophoto case, on a 60 m raster: it builds its GeoTIFFs once and reports finite
    figures (never timed here)."""
    from auxgps.evaluation.render_bench import RenderBenchConfig, render_bench_report, run_render_bench

    cfg = RenderBenchConfig(side_m=60.0, leg_m=20.0, frame_spacing_m=5.0, relief_frames=2)
    fig = run_render_bench(cam, tmp_path, cfg)
    assert fig["orthophoto"]["overview_factors"] == [2.0] and fig["build_s"] > 0
    for key in ("at_40m", "at_120m", "relief_at_60_to_90m_agl"):
        assert fig[key]["frames"] >= 1 and np.isfinite(fig[key]["median_ms"])
    assert run_render_bench(cam, tmp_path, cfg)["build_s"] < fig["build_s"]  # the second run finds them built
    assert "median" in render_bench_report(fig)
