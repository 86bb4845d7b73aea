"""An image-folder source: geotagged photos, their metadata and their pixels.

Metadata is read with Pillow (EXIF, and DJI's XMP block through ``Image.getxmp``, which parses with defusedxml):

- GPS latitude, longitude (degrees) and altitude (m above mean sea level, as the EXIF GPS block says);
- DJI's ``RelativeAltitude`` (m above the take-off point) and the gimbal's and the airframe's roll, pitch and yaw
  (degrees in the files, radians here);
- capture time (``DateTimeOriginal``), focal length (mm) and its 35 mm equivalent, make and model.

A field a file lacks is ``None`` and named in :attr:`PhotoMeta.missing`: a photo without attitude or height is
still usable (the locator solves the full pose). A file that is not a readable image at all is a
:class:`PhotoError` naming it; the callers turn it into a per-file message. Pixels are decoded by Pillow, which
refuses a truncated JPEG instead of filling its missing rows with grey.

Metadata are priors, never facts: a viewer may have turned the pixels without touching the EXIF orientation.
"""

from __future__ import annotations

import fnmatch
import math
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

import numpy as np
from PIL import ExifTags, Image, UnidentifiedImageError

from auxgps.errors import PhotoError

PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff")

#: The fields a photo may lack, in the order :attr:`PhotoMeta.missing` names them.
OPTIONAL_FIELDS = (
    "gps",
    "gps_altitude",
    "relative_altitude",
    "gimbal_attitude",
    "flight_attitude",
    "capture_time",
    "focal_length",
)


@dataclass(frozen=True)
class PhotoMeta:
    """What one photo's metadata says. Every optional field is ``None`` when the file does not hold it.

    Attributes
    ----------
    path : the file
    width_px, height_px : int, the stored pixel size (EXIF orientation is not applied)
    lat_deg, lon_deg : float, WGS84, deg
    alt_amsl_m : float, the EXIF GPS altitude, m above mean sea level (below when the reference says so)
    rel_alt_m : float, DJI RelativeAltitude, m above the take-off point
    gimbal_rpy_rad : (roll, pitch, yaw) of the camera, rad, NED; pitch -pi/2 looks straight down
    flight_rpy_rad : (roll, pitch, yaw) of the airframe, rad, NED
    capture_time : datetime without a time zone (EXIF DateTimeOriginal is local camera time)
    focal_mm, focal_35mm : float, mm
    make, model, software : str ('' when absent)
    orientation : int, the EXIF orientation tag (1 is normal)
    missing : the :data:`OPTIONAL_FIELDS` this file lacks
    """

    path: Path
    width_px: int
    height_px: int
    lat_deg: float | None = None
    lon_deg: float | None = None
    alt_amsl_m: float | None = None
    rel_alt_m: float | None = None
    gimbal_rpy_rad: tuple[float, float, float] | None = None
    flight_rpy_rad: tuple[float, float, float] | None = None
    capture_time: datetime | None = None
    focal_mm: float | None = None
    focal_35mm: float | None = None
    make: str = ""
    model: str = ""
    software: str = ""
    orientation: int = 1
    missing: tuple[str, ...] = field(default=())

    @property
    def has_gps(self) -> bool:
        return self.lat_deg is not None and self.lon_deg is not None

    @property
    def camera_id(self) -> str:
        """'MAKE MODEL WxH': photos with the same id share intrinsics."""
        return f"{self.make} {self.model} {self.width_px}x{self.height_px}".strip()


def list_photos(folder: Path | str, only: list[str] | None = None) -> list[Path]:
    """Photos in ``folder`` (not recursive), sorted by name, optionally only those whose file name matches one of
    the glob patterns in ``only`` (each may hold several, comma-separated). Raises :class:`PhotoError` when the
    folder is missing or nothing matches."""
    folder = Path(folder)
    if not folder.is_dir():
        raise PhotoError(f"{folder}: no such folder")
    patterns = [p.strip() for arg in (only or []) for p in arg.split(",") if p.strip()]
    files = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in PHOTO_SUFFIXES)
    if patterns:
        files = [p for p in files if any(fnmatch.fnmatchcase(p.name, pat) for pat in patterns)]
    if not files:
        what = f" matching {', '.join(patterns)}" if patterns else ""
        raise PhotoError(f"{folder}: no photos{what} (looked for {', '.join(PHOTO_SUFFIXES)})")
    return files


def _float(value) -> float | None:
    try:
        x = float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return x if math.isfinite(x) else None


def _dms_to_deg(dms, ref) -> float | None:
    try:
        d, m, s = (float(v) for v in dms)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    deg = d + m / 60.0 + s / 3600.0
    if not math.isfinite(deg):
        return None
    if isinstance(ref, bytes):
        ref = ref.decode("ascii", "ignore")
    return -deg if str(ref).strip().upper() in ("S", "W") else deg


def _text(value) -> str:
    if isinstance(value, bytes):
        value = value.decode("utf-8", "ignore")
    return str(value).replace("\x00", "").strip() if value is not None else ""


def _xmp_description(image: Image.Image) -> dict:
    """The flat attributes of the XMP rdf:Description (DJI puts its drone-dji fields there); {} when none."""
    try:
        xmp = image.getxmp()
    except Exception:  # a malformed XMP block is a missing one, not a broken photo
        return {}
    desc = xmp.get("xmpmeta", {}).get("RDF", {}).get("Description", {}) if isinstance(xmp, dict) else {}
    if isinstance(desc, list):  # several Description elements: merge their attributes
        merged: dict = {}
        for d in desc:
            if isinstance(d, dict):
                merged.update(d)
        desc = merged
    return desc if isinstance(desc, dict) else {}


def _rpy(desc: dict, prefix: str) -> tuple[float, float, float] | None:
    values = [_float(desc.get(f"{prefix}{axis}Degree")) for axis in ("Roll", "Pitch", "Yaw")]
    if any(v is None for v in values):
        return None
    return tuple(math.radians(v) for v in values)  # type: ignore[return-value]


def read_photo_meta(path: Path | str) -> PhotoMeta:
    """Read one photo's metadata (not its pixels). Raises :class:`PhotoError` if it is not a readable image."""
    path = Path(path)
    try:
        with Image.open(path) as image:
            width, height = image.size
            exif = image.getexif()
            gps = exif.get_ifd(ExifTags.IFD.GPSInfo)
            sub = exif.get_ifd(ExifTags.IFD.Exif)
            desc = _xmp_description(image)
    except FileNotFoundError:
        raise PhotoError(f"{path}: no such file") from None
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as err:
        raise PhotoError(f"{path}: not a readable image ({type(err).__name__}: {err})") from None

    G = ExifTags.GPS
    lat = _dms_to_deg(gps.get(G.GPSLatitude), gps.get(G.GPSLatitudeRef, "N"))
    lon = _dms_to_deg(gps.get(G.GPSLongitude), gps.get(G.GPSLongitudeRef, "E"))
    if lat is not None and lon is not None and (abs(lat) > 90 or abs(lon) > 180 or (lat == 0 and lon == 0)):
        lat = lon = None  # a zeroed GPS block is a receiver without a fix
    alt = _float(gps.get(G.GPSAltitude))
    if alt is not None and _text(gps.get(G.GPSAltitudeRef, b"\x00")) in ("\x01", "1"):
        alt = -alt
    rel_alt = _float(desc.get("RelativeAltitude"))
    t = None
    stamp = _text(sub.get(ExifTags.Base.DateTimeOriginal) or exif.get(ExifTags.Base.DateTime))
    if stamp:
        try:
            t = datetime.strptime(stamp[:19], "%Y:%m:%d %H:%M:%S")
        except ValueError:
            t = None
    focal = _float(sub.get(ExifTags.Base.FocalLength))
    focal35 = _float(sub.get(ExifTags.Base.FocalLengthIn35mmFilm))
    meta = dict(
        lat_deg=lat if lon is not None else None,
        lon_deg=lon if lat is not None else None,
        alt_amsl_m=alt,
        rel_alt_m=rel_alt,
        gimbal_rpy_rad=_rpy(desc, "Gimbal"),
        flight_rpy_rad=_rpy(desc, "Flight"),
        capture_time=t,
        focal_mm=focal if focal and focal > 0 else None,
        focal_35mm=focal35 if focal35 and focal35 > 0 else None,
    )
    present = {
        "gps": meta["lat_deg"] is not None,
        "gps_altitude": alt is not None,
        "relative_altitude": rel_alt is not None,
        "gimbal_attitude": meta["gimbal_rpy_rad"] is not None,
        "flight_attitude": meta["flight_rpy_rad"] is not None,
        "capture_time": t is not None,
        "focal_length": meta["focal_mm"] is not None,
    }
    return PhotoMeta(
        path=path,
        width_px=int(width),
        height_px=int(height),
        make=_text(exif.get(ExifTags.Base.Make)),
        model=_text(exif.get(ExifTags.Base.Model)),
        software=_text(exif.get(ExifTags.Base.Software)),
        orientation=int(exif.get(ExifTags.Base.Orientation, 1) or 1),
        missing=tuple(k for k in OPTIONAL_FIELDS if not present[k]),
        **meta,
    )


def load_gray(path: Path | str, max_side_px: int = 0) -> tuple[np.ndarray, float]:
    """Decode a photo as (H, W) uint8 grey, its longer side at most ``max_side_px`` (0: full resolution).

    Large JPEGs are reduced while decoding (libjpeg's DCT scaling by 1/2, 1/4 or 1/8), then with area
    averaging to the exact size. Returns the image and the factor ``s`` from its pixels to the stored ones:
    a pixel centre ``u`` here is ``(u + 0.5) * s - 0.5`` in the full-size photo.

    Raises :class:`PhotoError` naming the file if it is missing, not an image, truncated or corrupt.
    """
    return _decode(path, "L", max_side_px)


def load_rgb(path: Path | str, max_side_px: int = 0) -> tuple[np.ndarray, float]:
    """Decode a photo as (H, W, 3) uint8 RGB; otherwise as :func:`load_gray`."""
    return _decode(path, "RGB", max_side_px)


def _decode(path: Path | str, mode: str, max_side_px: int) -> tuple[np.ndarray, float]:
    path = Path(path)
    try:
        with Image.open(path) as image:
            full_w, full_h = image.size
            if max_side_px and max(full_w, full_h) > max_side_px:
                # draft() picks the largest DCT reduction that still leaves at least the requested size.
                ratio = max_side_px / max(full_w, full_h)
                image.draft(mode, (math.ceil(full_w * ratio), math.ceil(full_h * ratio)))
            pixels = np.asarray(image.convert(mode))
    except FileNotFoundError:
        raise PhotoError(f"{path}: no such file") from None
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as err:
        raise PhotoError(f"{path}: unreadable, truncated or corrupt image ({type(err).__name__}: {err})") from None
    if pixels.size == 0:
        raise PhotoError(f"{path}: image is empty")
    h, w = pixels.shape[:2]
    if max_side_px and max(w, h) > max_side_px:
        import cv2

        r = max_side_px / max(w, h)
        pixels = cv2.resize(pixels, (max(1, round(w * r)), max(1, round(h * r))), interpolation=cv2.INTER_AREA)
    scale = full_w / pixels.shape[1]
    return np.ascontiguousarray(pixels), float(scale)
