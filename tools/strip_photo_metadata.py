"""Copy photos without their attitude and altitude metadata (for the locate acceptance without metadata).

    python tools/strip_photo_metadata.py SRC_DIR OUT_DIR [GLOB]

Keeps the pixels (re-encoded at JPEG quality 95) and the EXIF GPS latitude and longitude (used only to score
a fix); drops the GPS altitude and the whole XMP block (DJI's RelativeAltitude, gimbal and flight angles).
"""

from __future__ import annotations

import sys
from pathlib import Path

from PIL import ExifTags, Image

from auxgps.io.photos import list_photos


def strip(src: Path, dst: Path) -> None:
    with Image.open(src) as im:
        exif = im.getexif()
        gps = exif.get_ifd(ExifTags.IFD.GPSInfo)
        for tag in (ExifTags.GPS.GPSAltitudeRef, ExifTags.GPS.GPSAltitude):
            gps.pop(tag, None)
        exif[ExifTags.IFD.GPSInfo] = gps
        im.save(dst, "JPEG", exif=exif, quality=95)  # Pillow writes no XMP unless asked


if __name__ == "__main__":
    if len(sys.argv) not in (3, 4):
        sys.exit(__doc__)
    out = Path(sys.argv[2])
    out.mkdir(parents=True, exist_ok=True)
    for path in list_photos(sys.argv[1], sys.argv[3:] or None):
        strip(path, out / path.name)
        print(out / path.name)
