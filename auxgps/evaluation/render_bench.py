"""The orthophoto world's rendering benchmark: time per 1280x720 frame over a large, 5 cm GeoTIFF.

A synthetic orthophoto of ``side_m`` x ``side_m`` at ``m_per_px`` (UTM 18N, a little rotated from the local
north by the grid's convergence; tiled 256 x 256, JPEG-compressed, with average overviews down to under 1000
pixels) is built once from the seeded gravel texture (:func:`auxgps.sim.texture.gravel_texture`: randomly
placed, flipped and shaded crops of one patch of 4096 pixels) into a cache folder outside the repository, with a
smooth height model (1 m cells, hills of some 15 m) beside it. Frames are then rendered along an out-and-back
path at 40 m (the return 120 m to the side), a leg at 120 m (an overview level) and, over the height model, a
shorter leg at 60 m; each frame's :meth:`Renderer.render` is timed, the first one (an empty block cache)
reported apart.
"""

from __future__ import annotations

import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np

from auxgps.core.camera import CameraPose, PinholeCamera
from auxgps.core.geometry import LocalFrame, R_BODY_CAM_DOWN, R_ned_body_from_euler

#: The benchmark world's origin (near Seneca Falls, NY; UTM zone 18N) and the raster's CRS.
ORIGIN = LocalFrame(42.91, -76.80, 150.0)
EPSG = 32618


@dataclass(frozen=True)
class RenderBenchConfig:
    """``side_m`` the square orthophoto's side, m; ``m_per_px`` its ground sample distance; ``frame_spacing_m``
    between frames along the path; ``leg_m`` each leg's length; ``seed`` of the texture and the path's
    wobble; ``relief_frames`` frames over the height model."""

    side_m: float = 2000.0
    m_per_px: float = 0.05
    frame_spacing_m: float = 3.0
    leg_m: float = 1600.0
    seed: int = 1
    relief_frames: int = 60


def default_cache_dir() -> Path:
    """Where the benchmark's rasters are kept: ``$XDG_CACHE_HOME/auxgps/bench`` (``~/.cache/auxgps/bench``)."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "auxgps" / "bench"


def _world_transform(cfg: RenderBenchConfig):
    import rasterio.warp
    from rasterio.transform import from_origin

    x0, y0 = rasterio.warp.transform("EPSG:4326", f"EPSG:{EPSG}", [ORIGIN.lon_deg], [ORIGIN.lat_deg])
    h = cfg.side_m / 2.0
    return from_origin(x0[0] - h, y0[0] + h, cfg.m_per_px, cfg.m_per_px), int(round(cfg.side_m / cfg.m_per_px))


def build_orthophoto(path: Path, cfg: RenderBenchConfig, progress=None) -> Path:
    """Write the synthetic orthophoto to ``path`` (through a temporary name, so a half-written file is never
    taken for a built one)."""
    import rasterio
    from rasterio.enums import Resampling
    from rasterio.windows import Window

    from auxgps.sim.texture import gravel_texture

    transform, n_px = _world_transform(cfg)
    rng = np.random.default_rng(cfg.seed)
    base = gravel_texture(int(np.clip(n_px, 1024, 4096)), cfg.seed)
    tile = 512
    n_tiles = -(-n_px // tile)
    shade = cv2.resize(rng.uniform(0.75, 1.25, (n_tiles // 8 + 2, n_tiles // 8 + 2)).astype(np.float32), (n_tiles + 1, n_tiles + 1),
                       interpolation=cv2.INTER_CUBIC)
    tmp = path.with_suffix(".part.tif")
    profile = dict(driver="GTiff", width=n_px, height=n_px, count=3, dtype="uint8", crs=f"EPSG:{EPSG}", transform=transform,
                   tiled=True, blockxsize=256, blockysize=256, compress="jpeg", jpeg_quality=90, photometric="ycbcr", bigtiff="yes")
    with rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True, COMPRESS_OVERVIEW="JPEG", PHOTOMETRIC_OVERVIEW="YCBCR", INTERLEAVE_OVERVIEW="PIXEL",
                      JPEG_QUALITY_OVERVIEW=90):
        with rasterio.open(tmp, "w", **profile) as ds:
            for ti in range(n_tiles):
                rows = min(tile, n_px - ti * tile)
                strip = np.empty((rows, n_px, 3), np.uint8)
                for tj in range(n_tiles):
                    cols = min(tile, n_px - tj * tile)
                    oy, ox = rng.integers(0, base.shape[0] - tile, 2)
                    crop = base[oy : oy + tile, ox : ox + tile]
                    k = int(rng.integers(0, 8))
                    crop = np.rot90(crop, k % 4)
                    crop = crop[:, ::-1] if k >= 4 else crop
                    gain = shade[ti : ti + 2, tj : tj + 2]  # shading corners of this tile: bilinear across it
                    g = cv2.resize(gain, (tile, tile), interpolation=cv2.INTER_LINEAR)[..., None]
                    strip[:, tj * tile : tj * tile + cols] = np.clip(crop[:rows, :cols] * g[:rows, :cols], 0, 255).astype(np.uint8)
                ds.write(np.moveaxis(strip[..., ::-1], -1, 0), window=Window(0, ti * tile, n_px, rows))
                if progress:
                    progress(f"orthophoto strip {ti + 1} of {n_tiles}")
            factors, f = [], 2
            while n_px / f >= 512:
                factors.append(f)
                f *= 2
            if progress:
                progress(f"overviews {factors}")
            ds.build_overviews(factors, Resampling.average)
    tmp.replace(path)
    return path


def build_dsm(path: Path, cfg: RenderBenchConfig) -> Path:
    """A smooth height model under the orthophoto: 1 m cells, heights of 0 to about 30 m above the origin."""
    import rasterio
    from rasterio.transform import from_origin

    transform, _ = _world_transform(cfg)
    n = int(round(cfg.side_m))
    rng = np.random.default_rng(cfg.seed + 1)
    low = rng.uniform(0.0, 30.0, (n // 200 + 2, n // 200 + 2)).astype(np.float32)
    z = cv2.resize(low, (n, n), interpolation=cv2.INTER_CUBIC) + np.float32(ORIGIN.alt_amsl_m)
    t = from_origin(transform.c, transform.f, 1.0, 1.0)
    tmp = path.with_suffix(".part.tif")
    with rasterio.open(tmp, "w", driver="GTiff", width=n, height=n, count=1, dtype="float32", crs=f"EPSG:{EPSG}", transform=t,
                       tiled=True, blockxsize=256, blockysize=256, compress="deflate") as ds:
        ds.write(z[None])
    tmp.replace(path)
    return path


def bench_rasters(cache_dir: Path, cfg: RenderBenchConfig, progress=None) -> tuple[Path, Path, float]:
    """The orthophoto and height model for ``cfg`` in ``cache_dir``, built when missing; and the seconds spent
    building them (0 when they were there)."""
    cache_dir.mkdir(parents=True, exist_ok=True)
    stem = f"ortho_{cfg.side_m:.0f}m_{100 * cfg.m_per_px:g}cm_seed{cfg.seed}"
    ortho, dsm = cache_dir / f"{stem}.tif", cache_dir / f"dsm_{cfg.side_m:.0f}m_seed{cfg.seed}.tif"
    t0 = time.monotonic()
    if not ortho.is_file():
        build_orthophoto(ortho, cfg, progress)
    if not dsm.is_file():
        build_dsm(dsm, cfg)
    return ortho, dsm, time.monotonic() - t0


def _world(ortho: Path, dsm: Path | None):
    from auxgps.io.georaster import GeoRaster
    from auxgps.sim.world import World

    return World(ORIGIN, (), None, None, None, "render bench", "synthetic orthophoto",
                 ground_orthophoto=GeoRaster(ortho, "bench orthophoto", "orthophoto"),
                 ground_dsm=None if dsm is None else GeoRaster(dsm, "bench dsm", "dsm"))


def _poses(start_ne_m, end_ne_m, down_m: float, spacing_m: float, rng) -> list[CameraPose]:
    start, end = np.asarray(start_ne_m, float), np.asarray(end_ne_m, float)
    n = max(int(np.linalg.norm(end - start) // spacing_m), 1)
    yaw = float(np.arctan2(*(end - start)[::-1]))
    poses = []
    for k in range(n):
        p = start + (end - start) * k / n
        roll, pitch, dyaw = rng.normal(0.0, 0.03, 3)  # a flying vehicle's few degrees of wobble
        poses.append(CameraPose(np.array([p[0], p[1], down_m]), R_ned_body_from_euler(roll, pitch, yaw + dyaw) @ R_BODY_CAM_DOWN))
    return poses


def _stats(ms: list[float]) -> dict:
    x = np.asarray(ms, float)
    return {"frames": int(len(x)), "median_ms": float(np.median(x)), "p99_ms": float(np.percentile(x, 99)),
            "max_ms": float(x.max()), "min_ms": float(x.min())}


def _time_leg(renderer, poses) -> tuple[list[float], float]:
    ms, reads0 = [], renderer.world.ground_orthophoto.reads
    for pose in poses:
        t0 = time.perf_counter()
        renderer.render(pose)
        ms.append((time.perf_counter() - t0) * 1e3)
    return ms, (renderer.world.ground_orthophoto.reads - reads0) / max(len(poses), 1)


def run_render_bench(camera: PinholeCamera, cache_dir: Path | None = None, cfg: RenderBenchConfig = RenderBenchConfig(), progress=None) -> dict:
    """Build (once) and time; the figures as a dict (``ortho_render`` in the benchmark's JSON)."""
    from auxgps.sim.render import Renderer

    cache_dir = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    ortho, dsm, build_s = bench_rasters(cache_dir, cfg, progress)
    rng = np.random.default_rng(cfg.seed)
    half = cfg.leg_m / 2.0
    out_leg = _poses((-half, -60.0), (half, -60.0), -40.0, cfg.frame_spacing_m, rng)
    back_leg = _poses((half, 60.0), (-half, 60.0), -40.0, cfg.frame_spacing_m, rng)
    high_leg = _poses((-half, 300.0), (half, 300.0), -120.0, 4 * cfg.frame_spacing_m, rng)
    relief_leg = _poses((-300.0, -300.0), (-300.0 + cfg.relief_frames * cfg.frame_spacing_m, -300.0), -90.0, cfg.frame_spacing_m, rng)
    if progress:
        progress(f"rendering {len(out_leg) + len(back_leg) + len(high_leg)} frames over the orthophoto, {len(relief_leg)} over the height model")
    flat = Renderer(_world(ortho, None), camera)
    t0 = time.perf_counter()
    flat.render(out_leg[0])
    first_ms = (time.perf_counter() - t0) * 1e3
    low_ms, low_reads = _time_leg(flat, out_leg[1:] + back_leg)
    high_ms, high_reads = _time_leg(flat, high_leg)
    relief = Renderer(_world(ortho, dsm), camera)
    relief.render(relief_leg[0])
    relief_ms, relief_reads = _time_leg(relief, relief_leg[1:])
    ds = flat.world.ground_orthophoto
    return {
        "orthophoto": {"path": str(ortho), "side_m": cfg.side_m, "m_per_px": cfg.m_per_px, "width_px": ds.levels[0].width_px,
                       "overview_factors": [lv.factor for lv in ds.levels[1:]], "file_bytes": ortho.stat().st_size, "crs": f"EPSG:{EPSG}"},
        "build_s": build_s,
        "image_px": [camera.width_px, camera.height_px],
        "opencv_threads": cv2.getNumThreads(),
        "first_frame_ms": first_ms,
        "at_40m": {**_stats(low_ms), "blocks_read_per_frame": low_reads},
        "at_120m": {**_stats(high_ms), "blocks_read_per_frame": high_reads},
        "relief_at_60_to_90m_agl": {**_stats(relief_ms), "blocks_read_per_frame": relief_reads},
        "config": asdict(cfg),
    }


def render_bench_report(fig: dict) -> str:
    o = fig["orthophoto"]
    lines = [f"orthophoto render ({o['side_m'] / 1000:g} km square at {100 * o['m_per_px']:g} cm, {fig['image_px'][0]}x{fig['image_px'][1]}, "
             f"OpenCV threads {fig['opencv_threads']}; built in {fig['build_s']:.0f} s): first frame {fig['first_frame_ms']:.1f} ms"]
    for key, name in (("at_40m", "at 40 m"), ("at_120m", "at 120 m"), ("relief_at_60_to_90m_agl", "over the height model")):
        s = fig[key]
        lines.append(f"  {name}: {s['frames']} frames, median {s['median_ms']:.1f} ms, p99 {s['p99_ms']:.1f} ms, max {s['max_ms']:.1f} ms, "
                     f"{s['blocks_read_per_frame']:.1f} blocks read per frame")
    return "\n".join(lines)
