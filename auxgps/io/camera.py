"""Camera sources: a simulated world rendered at the simulator's true pose, a camera device, a GStreamer or RTSP
pipeline, a video file, a folder of images (see :func:`open_camera`).

``read()`` returns a :class:`Frame` or None when no frame is available now; a corrupt frame is logged and
skipped, never raised; a source whose frames do not match the camera model is one :class:`ConfigError`.
"""

from __future__ import annotations

import logging
import threading
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


class NewestFrame:
    """The newest frame a source's own thread delivered, kept until the frame loop takes it; one not taken before
    the next arrives is dropped, never queued (a frame that waited is a fix at a position the drone has left).
    ``delivered`` and ``dropped`` count them; an error the thread met is raised to the reader."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._frame: Frame | None = None
        self._error: Exception | None = None
        self.delivered = 0
        self.dropped = 0

    def put(self, frame: Frame) -> None:
        with self._cond:
            if self._frame is not None:
                self.dropped += 1
            self._frame = frame
            self.delivered += 1
            self._cond.notify()

    def fail(self, err: Exception) -> None:
        with self._cond:
            self._error = err
            self._cond.notify()

    def take(self, timeout_s: float) -> Frame | None:
        with self._cond:
            if self._frame is None and self._error is None:
                self._cond.wait(timeout_s)
            if self._error is not None:
                raise self._error
            frame, self._frame = self._frame, None
            return frame


class SimCamera:
    """Renders a world file at the pose the simulator says is true (SIMSTATE / SIM_STATE).

    ``truth()`` returns the latest :class:`auxgps.io.link.Truth` or None. The world's origin must be where the
    simulator's home is. A truth sample is rendered once. Without ``fps`` a frame is rendered when the frame loop
    reads (as fast as it processes). With ``fps`` a thread of its own renders the newest truth that many times a
    second, as a camera delivers, and the frame loop gets the newest frame (:class:`NewestFrame`: the rest are
    dropped and counted); the truth must come at least that often (`auxgps run` asks for it at twice ``fps``).
    """

    def __init__(self, world_path: str, camera: PinholeCamera, R_body_cam: np.ndarray, truth: Callable, fps: float | None = None) -> None:
        # The simulator is loaded only when this source is asked for: the flying code imports none of it.
        from auxgps.sim.render import Renderer
        from auxgps.sim.world import load_world

        self.world = load_world(world_path)
        self.renderer = Renderer(self.world, camera)
        self.R_body_cam = R_body_cam
        self.truth = truth
        self.fps = fps
        self._last_t: float | None = None
        self._slot = NewestFrame() if fps else None
        self._stop = threading.Event()
        self._thread = None
        if fps:
            self._thread = threading.Thread(target=self._render_loop, daemon=True, name="sim-camera")
            self._thread.start()

    @property
    def delivered(self) -> int | None:
        """Frames the rendering thread delivered (None: rendered on reading, nothing to drop)."""
        return self._slot.delivered if self._slot is not None else None

    @property
    def dropped(self) -> int | None:
        return self._slot.dropped if self._slot is not None else None

    def _render_newest(self) -> Frame | None:
        tr = self.truth()
        if tr is None or tr.t_s == self._last_t:
            return None
        self._last_t = tr.t_s
        p = self.world.frame.to_ned(lat_deg=tr.lat_deg, lon_deg=tr.lon_deg, alt_amsl_m=tr.alt_amsl_m if tr.alt_amsl_m is not None else self.world.frame.alt_amsl_m)
        if tr.alt_amsl_m is None:
            return None  # SIMSTATE carries no altitude; wait for SIM_STATE
        pose = CameraPose(np.asarray(p, float), R_ned_body_from_euler(*tr.euler_rad) @ self.R_body_cam)
        return Frame(tr.t_s, self.renderer.render(pose).image_bgr)

    def _render_loop(self) -> None:
        period = 1.0 / self.fps
        next_t = time.monotonic()
        try:
            while not self._stop.is_set():
                next_t += period
                frame = self._render_newest()
                if frame is not None:
                    self._slot.put(frame)
                delay = next_t - time.monotonic()
                if delay > 0:
                    self._stop.wait(delay)
                else:
                    next_t = time.monotonic()  # rendering fell behind the rate: on from now, no burst
        except Exception as err:  # noqa: BLE001 - the reader names it; a dead thread must not look like a still camera
            log.exception("simulated camera stopped")
            self._slot.fail(ConfigError(f"simulated camera stopped: {type(err).__name__}: {err}"))

    def read(self, timeout_s: float = 0.05) -> Frame | None:
        if self._slot is not None:
            return self._slot.take(timeout_s)
        return self._render_newest()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=1.0)


def capture_time(read_s: float, pos_msec: float) -> float:
    """A live frame's time on the monotonic clock: the driver's own buffer timestamp where it gives one (V4L2's,
    through OpenCV's CAP_PROP_POS_MSEC, is taken on the monotonic clock at capture), else the moment the read
    returned, which a busy computer delays. Other backends give a position in the stream there, not a time on
    this clock: told apart by being more than a second from ``read_s`` (or after it)."""
    stamp_s = pos_msec / 1000.0
    return stamp_s if np.isfinite(stamp_s) and 0.0 <= read_s - stamp_s < 1.0 else read_s


class CaptureCamera:
    """A camera device (an index, a V4L2 path), a GStreamer or RTSP pipeline, or a video file, through OpenCV.

    A live source is read by a thread of its own as fast as it delivers, each frame stamped with the driver's
    capture time where it gives one on the monotonic clock (:func:`capture_time`), else as it arrives, and only
    the newest is kept: a frame loop slower than the camera gets the newest frame,
    never one that waited in the driver's queue (stamped late, it would be a fix at the wrong time).
    ``dropped`` counts the frames never read. A file's frames are read in turn, stamped at its frame rate from the
    start. ``size`` (width, height): what the camera model expects; a source giving other frames is a
    :class:`ConfigError` at its first frame, not frames read with the wrong geometry.
    """

    def __init__(self, source: str | int, *, live: bool, size: tuple[int, int] | None = None, api: int = cv2.CAP_ANY,
                 hint: str = "") -> None:
        self.source = source
        self.cap = cv2.VideoCapture(source, api)
        if not self.cap.isOpened():
            raise ConfigError(f"camera {source!r}: cannot be opened{hint}")
        self.live = live
        self.size = size
        self.fps = self.cap.get(cv2.CAP_PROP_FPS) or 30.0
        self._t0 = time.monotonic()
        self._n = 0
        self._checked = False
        self._slot = NewestFrame()
        self._stop = threading.Event()
        self._grabber = None
        if live:
            self._grabber = threading.Thread(target=self._grab, daemon=True, name="camera")
            self._grabber.start()

    def _check(self, image) -> bool:
        if image is None or image.ndim != 3 or image.dtype != np.uint8:
            log.warning("camera %r: unreadable frame skipped", self.source)
            return False
        if not self._checked and self.size is not None:
            self._checked = True
            if (image.shape[1], image.shape[0]) != tuple(self.size):
                raise ConfigError(f"camera {self.source!r} gives {image.shape[1]}x{image.shape[0]} px frames, the camera model is "
                                  f"{self.size[0]}x{self.size[1]}: calibrate it (auxgps camera calibrate) or set the camera's size")
        return True

    def _grab(self) -> None:
        while not self._stop.is_set():
            ok, image = self.cap.read()
            t = capture_time(time.monotonic(), self.cap.get(cv2.CAP_PROP_POS_MSEC))
            if not ok:
                log.warning("camera %r: no frame", self.source)
                time.sleep(0.01)
                continue
            try:
                if not self._check(image):
                    continue
            except ConfigError as err:
                self._slot.fail(err)
                return
            self._slot.put(Frame(t, image))

    @property
    def delivered(self) -> int | None:
        """Frames the live source delivered (None: a file, read in turn, nothing to drop)."""
        return self._slot.delivered if self.live else None

    @property
    def dropped(self) -> int | None:
        return self._slot.dropped if self.live else None

    def read(self, timeout_s: float = 0.05) -> Frame | None:
        if self.live:
            return self._slot.take(timeout_s)
        ok, image = self.cap.read()
        if not ok:
            return None  # end of file
        if not self._check(image):
            return None
        self._n += 1
        return Frame(self._t0 + self._n / self.fps, image)

    def close(self) -> None:
        self._stop.set()
        if self._grabber is not None:
            self._grabber.join(timeout=1.0)
        self.cap.release()


IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


class ImageFolderCamera:
    """The images of a folder in name order, as frames ``1 / fps`` apart from the start (as a video file)."""

    def __init__(self, folder: Path, fps: float = 10.0, size: tuple[int, int] | None = None) -> None:
        self.files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not self.files:
            raise ConfigError(f"camera {str(folder)!r}: a folder without images ({', '.join(IMAGE_SUFFIXES)})")
        self.fps, self.size = fps, size
        self._t0 = time.monotonic()
        self._n = 0

    def read(self) -> Frame | None:
        while self._n < len(self.files):
            path = self.files[self._n]
            self._n += 1
            image = cv2.imread(str(path), cv2.IMREAD_COLOR)
            if image is None:
                log.warning("camera: %s is not readable as an image; skipped", path)
                continue
            if self.size is not None and (image.shape[1], image.shape[0]) != tuple(self.size):
                log.warning("camera: %s is %dx%d px, the camera model %dx%d; skipped", path, image.shape[1], image.shape[0], *self.size)
                continue
            return Frame(self._t0 + self._n / self.fps, image)
        return None

    def close(self) -> None:
        pass


def open_camera(spec: str, camera: PinholeCamera, R_body_cam: np.ndarray, truth: Callable | None = None, sim_fps: float | None = None):
    """A camera source from ``--camera``:

    - ``sim:WORLD`` the simulated world rendered at the simulator's true pose (SITL, the emulator); with
      ``sim_fps``, rendered that many times a second by a thread of its own, as a camera delivers;
    - ``0`` a device index, ``/dev/video0`` a V4L2 device;
    - a GStreamer pipeline (any text with ``!``, ending in ``appsink``), or an ``rtsp://`` or ``http://`` stream;
    - a video file, or a folder of images (in name order).
    """
    size = (camera.width_px, camera.height_px)
    if sim_fps is not None and not spec.startswith("sim:"):
        raise ConfigError(f"a simulated camera's frame rate was given for camera {spec!r}: it goes with sim:WORLD only "
                          "(a real camera delivers at its own rate)")
    if spec.startswith("sim:"):
        if truth is None:
            raise ConfigError("camera sim: needs the simulator's truth (SIMSTATE / SIM_STATE) from the link")
        return SimCamera(spec[4:], camera, R_body_cam, truth, fps=sim_fps)
    if spec.isdigit():
        return CaptureCamera(int(spec), live=True, size=size)
    if spec.startswith("/dev/"):
        if not Path(spec).exists():
            raise ConfigError(f"camera {spec!r}: no such device")
        return CaptureCamera(spec, live=True, size=size, api=cv2.CAP_V4L2)
    if "!" in spec:
        return CaptureCamera(spec, live=True, size=size, api=cv2.CAP_GSTREAMER,
                             hint=" as a GStreamer pipeline (this OpenCV " + ("has" if _has_gstreamer() else "has no") + " GStreamer;"
                             " opencv-python-headless from PyPI has none: use a system OpenCV built with it)")
    if "://" in spec:
        return CaptureCamera(spec, live=True, size=size, api=cv2.CAP_FFMPEG, hint=" as a network stream")
    path = Path(spec)
    if path.is_dir():
        return ImageFolderCamera(path, size=size)
    if not path.exists():
        raise ConfigError(f"camera {spec!r}: no such file or folder, and not sim:WORLD, a device (0, /dev/video0), a GStreamer "
                          "pipeline or an rtsp:// stream")
    return CaptureCamera(spec, live=False, size=size)


def _has_gstreamer() -> bool:
    info = cv2.getBuildInformation()
    return any(line.strip().startswith("GStreamer:") and "YES" in line for line in info.splitlines())


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
