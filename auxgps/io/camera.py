"""Camera sources: a simulated world rendered at the simulator's true pose, a video file, an OpenCV device.

``open_camera("sim:WORLD.yaml" | "PATH.mp4" | "0", ...)``. ``read()`` returns a :class:`Frame` or None when no
frame is available now; a corrupt frame is logged and skipped, never raised.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from auxgps.core.camera import CameraPose, PinholeCamera
from auxgps.core.events import Frame
from auxgps.core.geometry import R_ned_body_from_euler
from auxgps.errors import ConfigError

log = logging.getLogger(__name__)


class SimCamera:
    """Renders a world file at the pose the simulator says is true (SIMSTATE / SIM_STATE).

    ``truth()`` returns the latest :class:`auxgps.io.link.Truth` or None. The world's origin must be where the
    simulator's home is. A truth sample is rendered once.
    """

    def __init__(self, world_path: str, camera: PinholeCamera, R_body_cam: np.ndarray, truth: Callable) -> None:
        # The simulator is loaded only when this source is asked for: the flying code imports none of it.
        from auxgps.sim.render import Renderer
        from auxgps.sim.world import load_world

        self.world = load_world(world_path)
        self.renderer = Renderer(self.world, camera)
        self.R_body_cam = R_body_cam
        self.truth = truth
        self._last_t: float | None = None

    def read(self) -> Frame | None:
        tr = self.truth()
        if tr is None or tr.t_s == self._last_t:
            return None
        self._last_t = tr.t_s
        p = self.world.frame.to_ned(lat_deg=tr.lat_deg, lon_deg=tr.lon_deg, alt_amsl_m=tr.alt_amsl_m if tr.alt_amsl_m is not None else self.world.frame.alt_amsl_m)
        if tr.alt_amsl_m is None:
            return None  # SIMSTATE carries no altitude; wait for SIM_STATE
        pose = CameraPose(np.asarray(p, float), R_ned_body_from_euler(*tr.euler_rad) @ self.R_body_cam)
        return Frame(tr.t_s, self.renderer.render(pose).image_bgr)

    def close(self) -> None:
        pass


class CaptureCamera:
    """A video file or a camera device through OpenCV's VideoCapture."""

    def __init__(self, source: str | int) -> None:
        self.source = source
        self.cap = cv2.VideoCapture(source)
        if not self.cap.isOpened():
            raise ConfigError(f"camera {source!r}: cannot be opened")
        self.is_file = isinstance(source, str)
        self.fps = self.cap.get(cv2.CAP_PROP_FPS) or 30.0
        self._t0 = time.monotonic()
        self._n = 0

    def read(self) -> Frame | None:
        ok, image = self.cap.read()
        if not ok or image is None or image.ndim != 3 or image.dtype != np.uint8:
            if not ok and self.is_file:
                return None  # end of file
            log.warning("camera %r: unreadable frame skipped", self.source)
            return None
        self._n += 1
        t = self._t0 + self._n / self.fps if self.is_file else time.monotonic()
        return Frame(t, image)

    def close(self) -> None:
        self.cap.release()


def open_camera(spec: str, camera: PinholeCamera, R_body_cam: np.ndarray, truth: Callable | None = None):
    """``sim:WORLD.yaml``, a video file path, or an integer device index."""
    if spec.startswith("sim:"):
        if truth is None:
            raise ConfigError("camera sim: needs the simulator's truth (SIMSTATE / SIM_STATE) from the link")
        return SimCamera(spec[4:], camera, R_body_cam, truth)
    if spec.isdigit():
        return CaptureCamera(int(spec))
    if not Path(spec).exists():
        raise ConfigError(f"camera {spec!r}: no such file, and not sim:WORLD.yaml or a device index")
    return CaptureCamera(spec)


def calibration_images(*, video: str | None = None, images: str | None = None, every_s: float = 0.5):
    """Grey images (H, W) uint8 to calibrate from: one every ``every_s`` seconds of a video, or every image of a
    folder (sorted by name). An unreadable file is logged and skipped; a missing source is a :class:`ConfigError`."""
    if (video is None) == (images is None):
        raise ConfigError("camera calibrate: give --video FILE or --images DIR")
    if images is not None:
        folder = Path(images)
        if not folder.is_dir():
            raise ConfigError(f"--images {images}: not a folder")
        files = sorted(p for p in folder.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"))
        if not files:
            raise ConfigError(f"--images {images}: no images (PNG, JPEG, BMP, TIFF) in it")
        for path in files:
            gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
            if gray is None:
                log.warning("%s: not readable as an image; skipped", path)
                continue
            yield path.name, gray
        return
    if not Path(video).exists():
        raise ConfigError(f"--video {video}: no such file")
    cap = cv2.VideoCapture(video)
    if not cap.isOpened():
        raise ConfigError(f"--video {video}: cannot be opened as a video")
    step = max(1, int(round((cap.get(cv2.CAP_PROP_FPS) or 30.0) * every_s)))
    k = 0
    try:
        while True:
            ok, image = cap.read()
            if not ok:
                return
            if k % step == 0 and image is not None and image.ndim == 3:
                yield f"frame {k}", cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
            k += 1
    finally:
        cap.release()
