"""The photo workflow: build a map from a folder of geotagged photos; locate photos against it.

This module joins the edges (photo files, map files) to the pure core (:mod:`auxgps.photo`). Every
problem with one photo (unreadable, truncated, no GPS where GPS is needed, no intrinsics, not located) becomes
a message for that file; only a problem with the whole job (no map can be built, no photos at all) raises.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from auxgps.config import PhotoCameraConfig, PhotoConfig
from auxgps.core.camera import PinholeCamera
from auxgps.core.geometry import LocalFrame
from auxgps.errors import PhotoError
from auxgps.io.photos import PhotoMeta, load_gray, read_photo_meta
from auxgps.photo.build import build_photo_map
from auxgps.photo.features import detect_sift
from auxgps.photo.locate import PhotoLocator
from auxgps.photo.types import MapPhoto, PhotoFix, PhotoMap, PhotoPrior, R_ned_cam_from_gimbal

#: The diagonal of a 35 mm film frame, mm: EXIF's 35 mm-equivalent focal length is scaled to it.
_FILM_DIAGONAL_MM = math.hypot(36.0, 24.0)


def camera_for_photo(meta: PhotoMeta, cam_cfg: PhotoCameraConfig | None) -> tuple[PinholeCamera, str | None]:
    """Intrinsics for a photo: the camera file's ``K``, or its focal length (else EXIF's) over its sensor width.
    Without a camera file, EXIF's 35 mm-equivalent focal length gives an approximate camera (map building
    refines the focal length); the second value then says so. Raises :class:`PhotoError` when nothing fits."""
    w, h = meta.width_px, meta.height_px
    if cam_cfg is not None:
        if cam_cfg.width_px is not None and (cam_cfg.width_px, cam_cfg.height_px) != (w, h):
            raise PhotoError(f"{meta.path.name}: {w}x{h} px, but the camera file is for {cam_cfg.width_px}x{cam_cfg.height_px}")
        if cam_cfg.K is not None:
            return PinholeCamera(w, h, np.array(cam_cfg.K, float), np.array(cam_cfg.dist, float)), None
        focal_mm = cam_cfg.focal_mm or meta.focal_mm
        if focal_mm is None:
            raise PhotoError(f"{meta.path.name}: no focal length (neither in the camera file nor in EXIF)")
        f = focal_mm / cam_cfg.sensor_width_mm * w
        K = np.array([[f, 0.0, w / 2.0], [0.0, f, h / 2.0], [0.0, 0.0, 1.0]])
        return PinholeCamera(w, h, K, np.array(cam_cfg.dist, float)), None
    if meta.focal_35mm is not None:
        f = meta.focal_35mm / _FILM_DIAGONAL_MM * math.hypot(w, h)
        K = np.array([[f, 0.0, w / 2.0], [0.0, f, h / 2.0], [0.0, 0.0, 1.0]])
        return PinholeCamera(w, h, K), "intrinsics approximated from the EXIF 35 mm-equivalent focal length"
    raise PhotoError(f"{meta.path.name}: no intrinsics (give --camera with a camera file; EXIF has no 35 mm focal length)")


def photo_prior(meta: PhotoMeta, frame: LocalFrame, *, use_gps: bool) -> PhotoPrior:
    """A photo's metadata as priors in ``frame``; its GPS only when ``use_gps`` (never when locating it), its GPS
    altitude too when it has no height above take-off."""
    gps = gps_alt = None
    if use_gps and meta.has_gps:
        gps = frame.to_ned(lat_deg=meta.lat_deg, lon_deg=meta.lon_deg, alt_amsl_m=frame.alt_amsl_m)[:2]
        if meta.rel_alt_m is None and meta.alt_amsl_m is not None:
            gps_alt = meta.alt_amsl_m - frame.alt_amsl_m
    R = R_ned_cam_from_gimbal(*meta.gimbal_rpy_rad) if meta.gimbal_rpy_rad is not None else None
    return PhotoPrior(gps_ne_m=gps, height_m=meta.rel_alt_m, R_ned_cam=R, gps_alt_m=gps_alt)


def map_origin(metas: list[PhotoMeta]) -> LocalFrame:
    """The map's anchor: the mean GPS position, on the take-off point's level (GPS altitude minus the height
    above take-off; the median GPS altitude when no photo has both)."""
    lat = float(np.mean([m.lat_deg for m in metas]))
    lon = float(np.mean([m.lon_deg for m in metas]))
    both = [m.alt_amsl_m - m.rel_alt_m for m in metas if m.alt_amsl_m is not None and m.rel_alt_m is not None]
    alts = [m.alt_amsl_m for m in metas if m.alt_amsl_m is not None]
    alt = float(np.median(both)) if both else (float(np.median(alts)) if alts else 0.0)
    return LocalFrame(lat, lon, alt)


def _features(meta: PhotoMeta, cfg: PhotoConfig):
    gray, scale = load_gray(meta.path, cfg.max_side_px)
    return detect_sift(gray, scale, cfg.n_features, cfg.min_features)


@dataclass
class MapBuildReport:
    """What ``auxgps map build`` did: the map, its anchor, the photos used and one message per problem."""

    photo_map: PhotoMap
    frame: LocalFrame
    used: list[str]
    messages: list[str] = field(default_factory=list)


def read_map_photos(files: list[Path], cam_cfg: PhotoCameraConfig | None, cfg: PhotoConfig,
                    progress: Callable[[str], None] | None = None) -> tuple[list[PhotoMeta], LocalFrame, list[MapPhoto], list[str]]:
    """Read and detect ``files`` for a map: the metadata and :class:`MapPhoto` of each usable photo (in the same
    order), the map's anchor, and one message per photo left out or noted. Photos that cannot be used are
    reported, not fatal; fewer than 2 usable ones with GPS is a :class:`PhotoError`."""
    messages: list[str] = []
    metas: list[PhotoMeta] = []
    for path in files:
        try:
            meta = read_photo_meta(path)
        except PhotoError as err:
            messages.append(str(err))
            continue
        if not meta.has_gps:
            messages.append(f"{path.name}: no GPS position in its metadata: left out of the map")
            continue
        metas.append(meta)
    if len(metas) < 2:
        raise PhotoError(f"a map needs at least 2 readable photos with GPS; usable: {len(metas)} of {len(files)}"
                         + (" (" + "; ".join(messages) + ")" if messages else ""))
    frame = map_origin(metas)
    used, photos = [], []
    for meta in metas:
        try:
            camera, note = camera_for_photo(meta, cam_cfg)
            feats = _features(meta, cfg)
        except PhotoError as err:
            messages.append(str(err))
            continue
        if note:
            messages.append(f"{meta.path.name}: {note}")
        if progress is not None:
            progress(meta.path.name)
        used.append(meta)
        photos.append(MapPhoto(meta.path.name, feats, camera, meta.camera_id, photo_prior(meta, frame, use_gps=True)))
    return used, frame, photos, messages


def build_map_from_photos(files: list[Path], cam_cfg: PhotoCameraConfig | None, cfg: PhotoConfig,
                          progress: Callable[[str], None] | None = None) -> MapBuildReport:
    """Read, detect and map ``files``. Photos that cannot be used are reported, not fatal."""
    _, frame, photos, messages = read_map_photos(files, cam_cfg, cfg, progress)
    photo_map = build_photo_map(photos, cfg.map)
    messages.extend(photo_map.messages)
    return MapBuildReport(photo_map, frame, [p.name for p in photo_map.photos], messages)


def strip_attitude_and_height(meta: PhotoMeta) -> PhotoMeta:
    """The same photo as if its metadata held no attitude and no height (GPS kept, for scoring only)."""
    from dataclasses import replace

    return replace(meta, gimbal_rpy_rad=None, flight_rpy_rad=None, rel_alt_m=None, alt_amsl_m=None)


def locate_photos(files: list[Path], photo_map: PhotoMap, frame: LocalFrame, cam_cfg: PhotoCameraConfig | None,
                  cfg: PhotoConfig, *, use_metadata: bool = True,
                  progress: Callable[[dict], None] | None = None) -> dict:
    """Locate each photo from the map alone; its GPS is read only to score the answer.

    Returns ``{"images": [{file, located, lat_deg, lon_deg, accuracy_m, inliers, error_m, message, notes, map}],
    "summary": {total, located, median_error_m, max_error_m}}``. With ``use_metadata`` False the photos'
    attitude and height are ignored (as if stripped).
    """
    locator = PhotoLocator(photo_map, cfg.locate)
    rows = []
    for path in files:
        row = {"file": path.name, "located": False, "lat_deg": None, "lon_deg": None, "accuracy_m": None,
               "inliers": 0, "error_m": None, "message": "", "notes": [], "map": ""}
        try:
            meta = read_photo_meta(path)
            if not use_metadata:
                meta = strip_attitude_and_height(meta)
            camera = photo_map.cameras.get(meta.camera_id)
            if camera is None:
                camera, note = camera_for_photo(meta, cam_cfg)
                if note:
                    row["notes"].append(note)
            feats = _features(meta, cfg)
        except PhotoError as err:
            row["message"] = str(err)
            rows.append(row)
            if progress is not None:
                progress(row)
            continue
        result = locator.locate(feats, camera, photo_prior(meta, frame, use_gps=False))
        if isinstance(result, PhotoFix):
            lat, lon, _ = frame.to_geodetic(result.p_cam_in_ned_m)
            row.update(located=True, lat_deg=float(lat), lon_deg=float(lon), accuracy_m=result.accuracy_m,
                       inliers=result.n_inliers, message="located", map=result.map_source)
            row["notes"].extend(result.notes)
            if meta.has_gps:  # scoring only: the photo's own GPS never reaches the locator
                gps_ne = frame.to_ned(lat_deg=meta.lat_deg, lon_deg=meta.lon_deg, alt_amsl_m=frame.alt_amsl_m)[:2]
                row["error_m"] = float(np.hypot(*(result.p_cam_in_ned_m[:2] - gps_ne)))
            else:
                row["notes"].append("no GPS in the photo to score against")
        else:
            row.update(inliers=result.n_inliers, message=f"not located: {result.reason}")
        rows.append(row)
        if progress is not None:
            progress(row)
    errors = [r["error_m"] for r in rows if r["error_m"] is not None]
    summary = {
        "total": len(rows),
        "located": sum(r["located"] for r in rows),
        "median_error_m": float(np.median(errors)) if errors else None,
        "max_error_m": float(np.max(errors)) if errors else None,
    }
    return {"images": rows, "summary": summary}


@dataclass
class OrthoReport:
    """What ``auxgps ortho build`` did: where the orthophoto is, its grid, the ground plane it lies on, the seam
    offsets between neighbouring photos (m) and one message per problem."""

    path: Path
    crs: str
    gsd_m: float
    width_px: int
    height_px: int
    plane: object
    used: list[str]
    seams: list
    messages: list[str] = field(default_factory=list)

    def seam_summary(self) -> dict:
        """Seam offsets over neighbouring pairs: count, median, 95th percentile and max, m."""
        off = np.array([s.offset_m for s in self.seams])
        if not len(off):
            return {"pairs": 0, "median_m": None, "p95_m": None, "max_m": None}
        return {"pairs": int(len(off)), "median_m": float(np.median(off)), "p95_m": float(np.percentile(off, 95)),
                "max_m": float(off.max())}

    def to_json(self) -> dict:
        p = self.plane
        return {
            "orthophoto": str(self.path), "crs": self.crs, "gsd_m": self.gsd_m, "width_px": self.width_px,
            "height_px": self.height_px, "photos": self.used,
            "ground_plane": {"down_m": f"{p.a:.6f} * north_m + {p.b:.6f} * east_m + {p.c:.3f}", "rms_m": p.rms_m,
                             "points": p.n_points},
            "seams": self.seam_summary(),
            "seam_pairs": [{"a": s.a, "b": s.b, "offset_m": s.offset_m, "offset_xy_m": [float(v) for v in s.offset_xy_m],
                            "response": s.response} for s in self.seams],
            "messages": self.messages,
        }


def build_orthophoto(files: list[Path], cam_cfg: PhotoCameraConfig | None, cfg: PhotoConfig, out: Path | str,
                     gsd_m: float | None = None, tile_px: int = 1024,
                     progress: Callable[[str], None] | None = None) -> OrthoReport:
    """An orthophoto GeoTIFF at ``out`` from geotagged photos: the photo block's poses (as ``auxgps map build``
    solves them), each photo projected onto the ground plane fitted to the block's points and blended
    (:mod:`auxgps.photo.ortho`), in the UTM zone of the block, at ``gsd_m`` metres a pixel (default: the photos'
    median ground sample distance). Also writes ``OUT.json``, the report."""
    import json
    from functools import lru_cache

    import rasterio
    import rasterio.warp

    from auxgps.core.camera import CameraPose
    from auxgps.io.geotiff import utm_crs, write_rgb_geotiff
    from auxgps.io.orthophoto import TAG_GEOREF_SIGMA, TAG_GROUND_ALT, TAG_GROUND_SLOPE
    from auxgps.io.photos import load_rgb
    from auxgps.photo.ortho import Mosaic, OrthoPhoto, fit_ground_plane, footprint_ne

    out = Path(out)
    metas, frame, photos, messages = read_map_photos(files, cam_cfg, cfg, progress)
    photo_map = build_photo_map(photos, cfg.map)
    messages.extend(photo_map.messages)
    plane = fit_ground_plane(photo_map.p_ned_m)
    camera_id = {m.path.name: m.camera_id for m in metas}
    path_of = {m.path.name: m.path for m in metas}
    ortho_photos = [OrthoPhoto(sp.name, photo_map.cameras[camera_id[sp.name]], CameraPose(sp.p_cam_in_ned_m, sp.R_ned_cam))
                    for sp in photo_map.photos]
    if gsd_m is None:
        gsd = [(plane.down_m(*p.pose.p_cam_in_ned_m[:2]) - p.pose.p_cam_in_ned_m[2]) / p.camera.focal_px for p in ortho_photos]
        gsd_m = float(np.median(gsd))
    if not (gsd_m > 0 and np.isfinite(gsd_m)):
        raise PhotoError(f"ground sample distance {gsd_m} m: the photos are not above the ground plane")

    wgs84 = rasterio.crs.CRS.from_epsg(4326)
    crs = utm_crs(frame.lat_deg, frame.lon_deg)

    def xy_of_ne(n, e):
        shape = np.shape(n)
        lat, lon, _ = frame.to_geodetic(np.stack([np.ravel(n), np.ravel(e), np.zeros(np.size(n))], axis=-1))
        x, y = rasterio.warp.transform(wgs84, crs, np.ravel(lon), np.ravel(lat))
        return np.reshape(x, shape), np.reshape(y, shape)

    def ne_of_xy(x, y):
        shape = np.shape(x)
        lon, lat = rasterio.warp.transform(crs, wgs84, np.ravel(x), np.ravel(y))
        p = frame.to_ned(lat_deg=np.asarray(lat), lon_deg=np.asarray(lon), alt_amsl_m=np.full(np.size(x), frame.alt_amsl_m))
        return p[:, 0].reshape(shape), p[:, 1].reshape(shape)

    # The grid: north up, over every photo's footprint, its corners on whole multiples of the pixel size.
    corners = [fp for p in ortho_photos if (fp := footprint_ne(p, plane)) is not None]
    if not corners:
        raise PhotoError("no photo looks at the ground (every footprint reaches the horizon)")
    x, y = xy_of_ne(*np.vstack(corners).T)
    x0, x1 = np.floor(x.min() / gsd_m) * gsd_m, np.ceil(x.max() / gsd_m) * gsd_m
    y0, y1 = np.floor(y.min() / gsd_m) * gsd_m, np.ceil(y.max() / gsd_m) * gsd_m
    width, height = int(round((x1 - x0) / gsd_m)), int(round((y1 - y0) / gsd_m))
    transform = rasterio.Affine(gsd_m, 0.0, x0, 0.0, -gsd_m, y1)
    inv = ~transform

    def affine(t, a, b):
        a, b = np.asarray(a, float), np.asarray(b, float)
        return t.a * a + t.b * b + t.c, t.d * a + t.e * b + t.f

    def ne_of_colrow(col, row):
        return ne_of_xy(*affine(transform, col, row))

    def colrow_of_ne(n, e):
        return affine(inv, *xy_of_ne(n, e))

    @lru_cache(maxsize=64)
    def image(name: str) -> np.ndarray:
        return load_rgb(path_of[name])[0]

    mosaic = Mosaic(ortho_photos, image, plane, ne_of_colrow, colrow_of_ne)
    messages.extend(f"{name}: left out of the orthophoto (its view reaches the horizon)" for name in mosaic.left_out)

    def tiles():
        for row0 in range(0, height, tile_px):
            for col0 in range(0, width, tile_px):
                h, w = min(tile_px, height - row0), min(tile_px, width - col0)
                rgb, seen = mosaic.tile(row0, col0, h, w)
                if progress is not None:
                    progress(f"tile rows {row0}-{row0 + h}, cols {col0}-{col0 + w}")
                yield row0, col0, rgb, seen

    # What a prior map built from this orthophoto needs to know of it (auxgps/io/orthophoto.py reads them back):
    # its placement error, the ground plane's height under its centre and its slope. The placement error is the
    # photo block's on its GPS and, in quadrature, the 95th percentile of the seams between neighbouring photos:
    # how far the mosaic disagrees with itself is how far it may be off in places (two Seneca mosaics of the
    # same field, 20 minutes apart, differ by a 2 % scale as well as a shift: docs/prior_maps.md).
    seams = mosaic.seam_offsets(gsd_m)
    seam_p95_m = float(np.percentile([sm.offset_m for sm in seams], 95)) if seams else 0.0
    n_c, e_c = ne_of_colrow(np.array(width / 2), np.array(height / 2))
    tags = {TAG_GEOREF_SIGMA: f"{float(np.hypot(photo_map.georef_sigma_h_m, seam_p95_m)):.3f}",
            TAG_GROUND_ALT: f"{frame.alt_amsl_m - float(plane.down_m(n_c, e_c)):.2f}",
            TAG_GROUND_SLOPE: f"{-plane.a:.6f} {-plane.b:.6f}"}
    write_rgb_geotiff(out, crs, transform, width, height, tiles(), tags=tags)
    report = OrthoReport(out, crs.to_string(), gsd_m, width, height, plane, [p.name for p in ortho_photos if p.name not in mosaic.left_out],
                         seams, messages)
    out.with_suffix(".json").write_text(json.dumps(report.to_json(), indent=1) + "\n")
    return report
