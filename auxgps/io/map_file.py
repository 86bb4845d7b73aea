"""Landmark map files: a versioned, documented format, written atomically.

Format (version 1): a NumPy ``.npz`` archive (uncompressed) holding

======================  =================  ===============================================================
array                   shape, dtype       meaning
======================  =================  ===============================================================
``meta``                (), str (JSON)     ``{"format": "auxgps-map", "version": 1, "origin": {lat_deg,
                                           lon_deg, alt_amsl_m}, "count": N}``
``descriptors``         (N, 32) uint8      ORB descriptors
``p_ned_m``             (N, 3) float32     positions in the local NED frame of ``origin``, m
``info_packed``         (N, 6) float32     information matrix (inverse covariance), upper triangle
                                           xx xy xz yy yz zz, 1/m^2
``n_seen``              (N,) uint16        observations fused
``n_visible``           (N,) uint16        frames that should have seen it
``view_cos``            (N,) float16       down-component of the view ray that gave the descriptor
``chi2_mean``           (N,) float16       mean squared Mahalanobis innovation of its observations
======================  =================  ===============================================================

A file is written to a temporary name in the same folder, flushed to disk and renamed over the target, so a
crash leaves either the old map or the new one, never half of one.
"""

from __future__ import annotations

import json
import os
import tempfile
import zipfile
from pathlib import Path

import numpy as np

from auxgps.core.geometry import LocalFrame
from auxgps.core.landmarks import LandmarkMap
from auxgps.errors import MapError

FORMAT = "auxgps-map"
VERSION = 1
_COLUMNS = {
    "descriptors": (np.uint8, (32,)),
    "p_ned_m": (np.float32, (3,)),
    "info_packed": (np.float32, (6,)),
    "n_seen": (np.uint16, ()),
    "n_visible": (np.uint16, ()),
    "view_cos": (np.float16, ()),
    "chi2_mean": (np.float16, ()),
}


def save_map(path: Path | str, landmarks: LandmarkMap, frame: LocalFrame) -> None:
    """Write ``landmarks`` (anchored at ``frame``) to ``path`` atomically."""
    path = Path(path)
    n = len(landmarks)
    meta = {
        "format": FORMAT,
        "version": VERSION,
        "origin": {"lat_deg": frame.lat_deg, "lon_deg": frame.lon_deg, "alt_amsl_m": frame.alt_amsl_m},
        "count": n,
    }
    arrays = {name: getattr(landmarks, name)[:n] for name in _COLUMNS}
    path.parent.mkdir(parents=True, exist_ok=True)
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


def load_map(path: Path | str) -> tuple[LandmarkMap, LocalFrame]:
    """Read a map file. Any problem (missing, truncated, wrong version, bad arrays) is one :class:`MapError`."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(str(data["meta"]))
            if meta.get("format") != FORMAT:
                raise MapError(f"{path}: not an auxgps map (format {meta.get('format')!r})")
            if meta.get("version") != VERSION:
                raise MapError(f"{path}: map version {meta.get('version')} is not supported (this auxgps reads {VERSION})")
            n = int(meta["count"])
            o = meta["origin"]
            frame = LocalFrame(float(o["lat_deg"]), float(o["lon_deg"]), float(o["alt_amsl_m"]))
            columns = {}
            for name, (dtype, tail) in _COLUMNS.items():
                a = data[name]
                if a.dtype != dtype or a.shape != (n, *tail):
                    raise MapError(f"{path}: array {name} has shape {a.shape} and type {a.dtype}, expected {(n, *tail)} {np.dtype(dtype)}")
                columns[name] = a
    except MapError:
        raise
    except FileNotFoundError:
        raise MapError(f"{path}: no such map file") from None
    except (OSError, ValueError, KeyError, zipfile.BadZipFile, json.JSONDecodeError, EOFError) as err:
        raise MapError(f"{path}: unreadable or truncated map file ({type(err).__name__}: {err})") from None
    lm = LandmarkMap(capacity=max(n, 16))
    for name, a in columns.items():
        getattr(lm, name)[:n] = a
    lm._n = n
    if not np.all(np.isfinite(lm.p_ned_m[:n])) or not np.all(np.isfinite(lm.info_packed[:n])):
        raise MapError(f"{path}: map holds non-finite positions or information")
    lm.sync_index()  # built here, so that the first frame after loading is not the one that pays for it
    return lm, frame
