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
    """A photo's metadata as priors in ``frame``; its GPS only when ``use_gps`` (never when locating it)."""
    gps = None
    if use_gps and meta.has_gps:
        gps = frame.to_ned(lat_deg=meta.lat_deg, lon_deg=meta.lon_deg, alt_amsl_m=frame.alt_amsl_m)[:2]
    R = R_ned_cam_from_gimbal(*meta.gimbal_rpy_rad) if meta.gimbal_rpy_rad is not None else None
    return PhotoPrior(gps_ne_m=gps, height_m=meta.rel_alt_m, R_ned_cam=R)


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
    return detect_sift(gray, scale, cfg.n_features)


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

    Returns ``{"images": [{file, located, lat_deg, lon_deg, accuracy_m, inliers, error_m, message, notes}],
    "summary": {total, located, median_error_m, max_error_m}}``. With ``use_metadata`` False the photos'
    attitude and height are ignored (as if stripped).
    """
    locator = PhotoLocator(photo_map, cfg.locate)
    rows = []
    for path in files:
        row = {"file": path.name, "located": False, "lat_deg": None, "lon_deg": None, "accuracy_m": None,
               "inliers": 0, "error_m": None, "message": "", "notes": []}
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
                       inliers=result.n_inliers, message="located")
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
