"""Landmark map files: a versioned, documented format, written atomically.

Format (version 4): a NumPy ``.npz`` archive (uncompressed) holding

======================  =================  ===============================================================
array                   shape, dtype       meaning
======================  =================  ===============================================================
``meta``                (), str (JSON)     ``{"format": "auxgps-map", "version": 3, "origin": {lat_deg,
                                           lon_deg, alt_amsl_m}, "count": N, "descriptor": "orb" | "sift",
                                           "sources": [{kind, name, georef_sigma_h_m}]}``: where the
                                           landmarks come from (kind "flight", "orthophoto" or
                                           "photos"; a flight map's source 0 is the flight);
                                           a map built from photos adds ``cameras`` (camera id ->
                                           ``{width_px, height_px, K, dist}``, refined intrinsics),
                                           ``georef_sigma_h_m`` (one-sigma error of the whole map's
                                           placement, m) and ``photos`` (``[{name, p_ned_m, R_ned_cam}]``)
``descriptors``         (N, D) uint8       ORB (D = 32) or SIFT (D = 128) descriptors
``p_ned_m``             (N, 3) float32     positions in the local NED frame of ``origin``, m
``info_packed``         (N, 6) float32     information matrix (inverse covariance), upper triangle
                                           xx xy xz yy yz zz, 1/m^2
``n_seen``              (N,) uint16        observations fused (photos: views of the point)
``n_visible``           (N,) uint16        frames that should have seen it
``view_cos``            (N,) float16       down-component of the view ray that gave the descriptor
``descriptor_range_m``  (N,) float16       range that view saw it from, over the frame's detection scale, m
                                           (NaN: unknown)
``chi2_mean``           (N,) float16       mean squared Mahalanobis innovation of its observations
``source``              (N,) uint8         its source, an index into ``sources``
======================  =================  ===============================================================

A map built from an orthophoto (``auxgps map build --orthophoto``) also holds ``prior`` in ``meta``: the
orthophoto, the build's ground sample distance, how heights were found, and the camera focal length its
descriptor ranges assume. A flight's map written while the heading solver runs holds ``heading`` in ``meta``:
the autopilot's heading error as solved then (``offset_rad``, ``sigma_rad``) and the wall time (``unix_s``), which
`auxgps run --map` starts its solver from, aged by the time since (:func:`saved_heading`).

Versions 1 to 3 are still read: version 3 is version 4 without ``source`` and ``sources`` (one source: the
flight, or for a photo map its photos), version 2 is version 3 without ``descriptor_range_m`` (read as unknown), and
version 1 is version 2 without ``descriptor`` in ``meta`` (always ORB). A file is written to a temporary
name in the same folder, flushed to disk and renamed over the target, so a crash leaves either the old map or
the new one, never half of one.
"""

from __future__ import annotations

import json
import os
import tempfile
import zipfile
from pathlib import Path

import numpy as np

from auxgps.core.camera import PinholeCamera
from auxgps.core.geometry import LocalFrame
from auxgps.core.landmarks import LandmarkMap, pack_sym, unpack_sym
from auxgps.core.prior_map import FLIGHT, MapSource
from auxgps.errors import MapError
from auxgps.photo.types import PhotoMap, SolvedPhoto

FORMAT = "auxgps-map"
VERSION = 5
READABLE_VERSIONS = (1, 2, 3, 4, 5)
DESCRIPTOR_BYTES = {"orb": 32, "sift": 128}
_COLUMNS = {
    "descriptors": (np.uint8, None),  # width set by the descriptor kind
    "p_ned_m": (np.float32, (3,)),
    "info_packed": (np.float32, (6,)),
    "n_seen": (np.uint16, ()),
    "n_visible": (np.uint16, ()),
    "view_cos": (np.float16, ()),
    "descriptor_range_m": (np.float16, ()),
    "chi2_mean": (np.float16, ()),
    "source": (np.uint8, ()),
    "ray_bias_sum": (np.float32, (3,)),
}


def _write(path: Path, meta: dict, arrays: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    # A process killed while writing leaves its temporary behind: the next write clears it.
    for stale in path.parent.glob(path.name + ".*.tmp"):
        stale.unlink(missing_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez(f, meta=np.array(json.dumps(meta)), **arrays)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    _fsync_dir(path.parent)  # the rename itself on disk: a power cut after this keeps the new map


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return  # a platform that cannot open folders (Windows): the rename is as durable as it makes it
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _origin(frame: LocalFrame) -> dict:
    return {"lat_deg": frame.lat_deg, "lon_deg": frame.lon_deg, "alt_amsl_m": frame.alt_amsl_m}


def save_map(path: Path | str, landmarks: LandmarkMap, frame: LocalFrame, prior: dict | None = None,
             heading: dict | None = None) -> None:
    """Write a flight map (ORB ``landmarks``, anchored at ``frame``) to ``path`` atomically; ``prior``: what a map
    built from an orthophoto says about its making (``meta["prior"]``); ``heading``: the autopilot's heading error
    as the flight had solved it when the map was written (``meta["heading"]``: ``offset_rad``, ``sigma_rad``,
    ``unix_s``), so that a restart after a crash need not learn it again."""
    n = len(landmarks)
    kind = "sift" if landmarks.descriptors.shape[1] == DESCRIPTOR_BYTES["sift"] else "orb"
    meta = {"format": FORMAT, "version": VERSION, "origin": _origin(frame), "count": n, "descriptor": kind,
            "sources": [s.to_json() for s in landmarks.sources]}
    if prior is not None:
        meta["prior"] = prior
    if heading is not None:
        meta["heading"] = heading
    _write(Path(path), meta, {name: getattr(landmarks, name)[:n] for name in _COLUMNS})


def saved_heading(path: Path | str) -> dict | None:
    """The heading error a flight map was written with (see :func:`save_map`), or None: a map without it, or one
    whose entry is malformed (the flight then learns the heading afresh)."""
    try:  # the meta entry alone: the map itself was read and checked by load_maps
        with np.load(path, allow_pickle=False) as data:
            h = json.loads(str(data["meta"])).get("heading")
    except (OSError, ValueError, KeyError, zipfile.BadZipFile, json.JSONDecodeError, AttributeError):
        return None
    try:
        out = {k: float(h[k]) for k in ("offset_rad", "sigma_rad", "unix_s")}
    except (TypeError, KeyError, ValueError):
        return None
    return out if all(np.isfinite(v) for v in out.values()) else None


def _read(path: Path) -> tuple[dict, dict, LocalFrame]:
    """Meta, columns and frame of a map file; every problem is one :class:`MapError`."""
    try:
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(str(data["meta"]))
            if not isinstance(meta, dict) or meta.get("format") != FORMAT:
                raise MapError(f"{path}: not an auxgps map (format {meta.get('format') if isinstance(meta, dict) else None!r})")
            if meta.get("version") not in READABLE_VERSIONS:
                raise MapError(f"{path}: map version {meta.get('version')} is not supported (this auxgps reads "
                               f"{', '.join(map(str, READABLE_VERSIONS))})")
            kind = meta.get("descriptor", "orb")
            if kind not in DESCRIPTOR_BYTES:
                raise MapError(f"{path}: unknown descriptor kind {kind!r}")
            n = int(meta["count"])
            o = meta["origin"]
            frame = LocalFrame(float(o["lat_deg"]), float(o["lon_deg"]), float(o["alt_amsl_m"]))
            columns = {}
            for name, (dtype, tail) in _COLUMNS.items():
                tail = (DESCRIPTOR_BYTES[kind],) if tail is None else tail
                if name == "descriptor_range_m" and meta["version"] < 3:
                    columns[name] = np.full(n, np.nan, dtype)
                    continue
                if name == "source" and meta["version"] < 4:
                    columns[name] = np.zeros(n, dtype)
                    continue
                if name == "ray_bias_sum" and meta["version"] < 5:  # no bias expected of its landmarks
                    columns[name] = np.zeros((n, 3), dtype)
                    continue
                a = data[name]
                if a.dtype != dtype or a.shape != (n, *tail):
                    raise MapError(f"{path}: array {name} has shape {a.shape} and type {a.dtype}, expected {(n, *tail)} {np.dtype(dtype)}")
                columns[name] = a
    except MapError:
        raise
    except FileNotFoundError:
        raise MapError(f"{path}: no such map file") from None
    except (OSError, ValueError, KeyError, TypeError, zipfile.BadZipFile, json.JSONDecodeError, EOFError) as err:
        raise MapError(f"{path}: unreadable or truncated map file ({type(err).__name__}: {err})") from None
    if not np.all(np.isfinite(columns["p_ned_m"])) or not np.all(np.isfinite(columns["info_packed"])):
        raise MapError(f"{path}: map holds non-finite positions or information")
    meta["descriptor"] = kind
    try:
        if meta["version"] < 4:
            old = ([MapSource("photos", path.name, float(meta.get("georef_sigma_h_m", 0.0)))] if kind == "sift" else [FLIGHT])
            meta["sources"] = old
        else:
            meta["sources"] = [MapSource.from_json(d) for d in meta["sources"]]
    except (KeyError, TypeError, ValueError) as err:
        raise MapError(f"{path}: bad map sources ({type(err).__name__}: {err})") from None
    if n and int(columns["source"].max()) >= len(meta["sources"]):
        raise MapError(f"{path}: a landmark names source {int(columns['source'].max())}, the map lists {len(meta['sources'])}")
    return meta, columns, frame


def load_map(path: Path | str) -> tuple[LandmarkMap, LocalFrame]:
    """Read a flight map (ORB descriptors). A photo map, or any problem with the file, is one :class:`MapError`."""
    path = Path(path)
    meta, columns, frame = _read(path)
    if meta["descriptor"] != "orb":
        raise MapError(f"{path}: a map of {meta['descriptor']} features (built from photos, for auxgps locate); "
                       "the flight pipeline needs a map it built itself (orb)")
    try:
        lm = LandmarkMap.from_columns(columns, sources=meta["sources"])
    except ValueError as err:
        raise MapError(f"{path}: {err}") from None
    return lm, frame


def load_maps(paths: list[Path | str], frame: LocalFrame | None = None) -> tuple[LandmarkMap, LocalFrame]:
    """Read one flight map or several (``auxgps run --map A --map B``) into one, in ``frame`` (default: the first
    map's): each landmark keeps its source (a prior map's name and placement error), moved into that frame
    through geodetic coordinates. Any problem with any file is one :class:`MapError` naming it."""
    if not paths:
        raise ValueError("no map to load")
    landmarks, first_frame = load_map(paths[0])
    if frame is not None and frame != first_frame:
        moved = LandmarkMap(descriptor_bytes=landmarks.descriptors.shape[1])
        _merge_into(moved, landmarks, first_frame, frame, paths[0])
        landmarks = moved
    frame = frame or first_frame
    for path in paths[1:]:
        other, other_frame = load_map(path)
        _merge_into(landmarks, other, other_frame, frame, path)
    landmarks.sync_index()
    return landmarks, frame


def _merge_into(landmarks: LandmarkMap, other: LandmarkMap, other_frame: LocalFrame, frame: LocalFrame, path) -> None:
    """Append ``other`` (in ``other_frame``) to ``landmarks`` (in ``frame``)."""
    lat, lon, alt = other_frame.to_geodetic(other.p_ned_m[: len(other)].astype(float))
    try:
        landmarks.merge(other, frame.to_ned(lat_deg=lat, lon_deg=lon, alt_amsl_m=alt))
    except ValueError as err:
        raise MapError(f"{path}: {err}") from None


def save_photo_map(path: Path | str, photo_map: PhotoMap, frame: LocalFrame, prior: dict | None = None) -> None:
    """Write a map built from photos (SIFT descriptors, refined cameras, solved photos), or from an orthophoto
    for ``auxgps locate`` (``prior``: how), atomically."""
    n = len(photo_map)
    meta = {
        "format": FORMAT,
        "version": VERSION,
        "origin": _origin(frame),
        "count": n,
        "descriptor": "sift",
        "sources": [s.to_json() for s in photo_map.sources] or [MapSource("photos", Path(path).name, photo_map.georef_sigma_h_m).to_json()],
        "cameras": {
            cid: {"width_px": c.width_px, "height_px": c.height_px, "K": c.K.tolist(), "dist": c.dist.tolist()}
            for cid, c in photo_map.cameras.items()
        },
        "georef_sigma_h_m": photo_map.georef_sigma_h_m,
        "photos": [{"name": p.name, "p_ned_m": p.p_cam_in_ned_m.tolist(), "R_ned_cam": p.R_ned_cam.tolist()} for p in photo_map.photos],
    }
    arrays = {
        "descriptors": photo_map.descriptors.astype(np.uint8),
        "p_ned_m": photo_map.p_ned_m.astype(np.float32),
        "info_packed": pack_sym(photo_map.info_ned).astype(np.float32),
        "n_seen": np.minimum(photo_map.n_views, np.iinfo(np.uint16).max).astype(np.uint16),
        "n_visible": np.minimum(photo_map.n_views, np.iinfo(np.uint16).max).astype(np.uint16),
        "view_cos": np.ones(n, np.float16),
        "descriptor_range_m": np.full(n, np.nan, np.float16),
        "chi2_mean": np.zeros(n, np.float16),
        "source": (photo_map.source if photo_map.source is not None else np.zeros(n)).astype(np.uint8),
        "ray_bias_sum": np.zeros((n, 3), np.float32),  # a photo block's bundle adjustment leaves none to expect
    }
    if prior is not None:
        meta["prior"] = prior
    _write(Path(path), meta, arrays)


def load_photo_map(path: Path | str) -> tuple[PhotoMap, LocalFrame]:
    """Read a map built from photos. A flight map, or any problem with the file, is one :class:`MapError`."""
    path = Path(path)
    meta, columns, frame = _read(path)
    if meta["descriptor"] != "sift" or "cameras" not in meta:
        raise MapError(f"{path}: a flight map ({meta['descriptor']} features), not one built from photos "
                       "(auxgps map build --images DIR)")
    try:
        cameras = {
            cid: PinholeCamera(int(c["width_px"]), int(c["height_px"]), np.array(c["K"], float), np.array(c["dist"], float))
            for cid, c in meta["cameras"].items()
        }
        photos = tuple(
            SolvedPhoto(str(p["name"]), np.array(p["p_ned_m"], float), np.array(p["R_ned_cam"], float), 0, None, None)
            for p in meta.get("photos", [])
        )
        georef = float(meta["georef_sigma_h_m"])
    except (KeyError, TypeError, ValueError) as err:
        raise MapError(f"{path}: bad photo-map metadata ({type(err).__name__}: {err})") from None
    except Exception as err:  # CameraError from a bad K
        raise MapError(f"{path}: bad camera in the map ({err})") from None
    pm = PhotoMap(
        p_ned_m=columns["p_ned_m"].astype(float),
        info_ned=unpack_sym(columns["info_packed"].astype(float)),
        descriptors=columns["descriptors"],
        n_views=columns["n_seen"].astype(int),
        cameras=cameras,
        georef_sigma_h_m=georef,
        photos=photos,
        source=columns["source"],
        sources=tuple(meta["sources"]),
    )
    return pm, frame


def load_photo_maps(paths: list[Path | str]) -> tuple[PhotoMap, LocalFrame]:
    """Read one photo map or several (``auxgps locate --map A --map B``: maps from photos or orthophotos) into
    one, in the frame of the first; each point keeps its source and that source's placement error."""
    maps = [load_photo_map(p) for p in paths]
    if len(maps) == 1:
        return maps[0]
    first, frame = maps[0]
    parts, src_idx, sources, cameras = [], [], [], {}
    for (pm, f), path in zip(maps, paths):
        p = pm.p_ned_m
        if f != frame:
            lat, lon, alt = f.to_geodetic(p)
            p = frame.to_ned(lat_deg=lat, lon_deg=lon, alt_amsl_m=alt)
        own = pm.sources or (MapSource("photos", Path(path).name, pm.georef_sigma_h_m),)
        own_idx = pm.source if pm.source is not None else np.zeros(len(pm), np.uint8)
        src_idx.append(own_idx.astype(int) + len(sources))
        sources.extend(own)
        parts.append((p, pm))
        for cid, cam in pm.cameras.items():
            cameras.setdefault(cid, cam)
    if len(sources) > 255:
        raise MapError(f"{len(sources)} map sources: 255 at most")
    merged = PhotoMap(
        p_ned_m=np.vstack([p for p, _ in parts]),
        info_ned=np.concatenate([pm.info_ned for _, pm in parts]),
        descriptors=np.vstack([pm.descriptors for _, pm in parts]),
        n_views=np.concatenate([pm.n_views for _, pm in parts]),
        cameras=cameras,
        georef_sigma_h_m=max(s.georef_sigma_h_m for s in sources),
        photos=first.photos,  # (the solved photos of the first map: the others are in their own frames)
        source=np.concatenate(src_idx).astype(np.uint8),
        sources=tuple(sources),
    )
    return merged, frame
