"""Camera sources: a video file, a folder of images, devices and pipelines; each mistake is a named error."""

import cv2
import numpy as np
import pytest

from auxgps.core.camera import PinholeCamera
from auxgps.core.geometry import R_BODY_CAM_DOWN
from auxgps.errors import ConfigError
from auxgps.io.camera import open_camera

CAMERA = PinholeCamera.from_hfov(320, 240, np.pi / 2)


def frames(n, size=(320, 240)):
    rng = np.random.default_rng(1)
    return [rng.integers(0, 255, (size[1], size[0], 3), dtype=np.uint8) for _ in range(n)]


def test_a_folder_of_images_is_read_in_name_order_and_a_bad_file_skipped(tmp_path):
    imgs = frames(3)
    for k, img in enumerate(imgs):
        cv2.imwrite(str(tmp_path / f"{k:02d}.png"), img)
    (tmp_path / "01b.png").write_bytes(b"not an image")
    cam = open_camera(str(tmp_path), CAMERA, R_BODY_CAM_DOWN)
    got = [cam.read() for _ in range(4)]
    assert [np.array_equal(g.image_bgr, i) for g, i in zip(got[:3], imgs)] == [True, True, True] and got[3] is None
    assert got[0].t_s < got[1].t_s < got[2].t_s


def test_a_video_file_gives_its_frames_then_none(tmp_path):
    path = tmp_path / "v.avi"
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (320, 240))
    for img in frames(5):
        w.write(img)
    w.release()
    cam = open_camera(str(path), CAMERA, R_BODY_CAM_DOWN)
    got = []
    while (f := cam.read()) is not None:
        got.append(f)
    assert len(got) == 5 and all(f.image_bgr.shape == (240, 320, 3) for f in got)
    assert np.allclose(np.diff([f.t_s for f in got]), 0.1)  # its frame rate, not the reading's pace


def test_frames_of_another_size_than_the_camera_model_are_one_named_error(tmp_path):
    path = tmp_path / "v.avi"
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (640, 480))
    for img in frames(2, (640, 480)):
        w.write(img)
    w.release()
    cam = open_camera(str(path), CAMERA, R_BODY_CAM_DOWN)
    with pytest.raises(ConfigError, match="640x480 px frames, the camera model is 320x240"):
        cam.read()


@pytest.mark.parametrize(
    "spec, names",
    [
        ("/dev/video99", "no such device"),
        ("no/such/file.mp4", "no such file or folder"),
        ("videotestsrc ! videoconvert ! appsink", "GStreamer"),
        ("sim:one_cube_1m", "needs the simulator's truth"),
    ],
)
def test_a_source_that_cannot_be_opened_is_named(spec, names):
    with pytest.raises(ConfigError, match=names):
        open_camera(spec, CAMERA, R_BODY_CAM_DOWN)


@pytest.mark.realtime
def test_a_live_camera_faster_than_the_frame_loop_gives_the_newest_frame_and_counts_the_rest(monkeypatch):
    """A camera at 200 frames a second with a driver queue, a frame loop taking 50 ms a frame: each frame read is
    the newest, stamped within a few ms of its capture (read straight from the queue, it would be ever older and
    stamped late), and the frames never read are counted."""
    import time

    import cv2

    from auxgps.io.camera import CaptureCamera

    class QueuedCamera:
        """Frame n is captured at t0 + n / 200 s and waits in the driver's queue until read."""

        def __init__(self, *args):
            self.t0, self.n, self.captured_s = time.monotonic(), 0, {}

        def isOpened(self):
            return True

        def get(self, prop):
            return 200.0

        def read(self):
            self.n += 1
            t = self.t0 + self.n / 200.0
            time.sleep(max(0.0, t - time.monotonic()))
            self.captured_s[self.n % 256] = t
            return True, np.full((48, 64, 3), self.n % 256, np.uint8)

        def release(self):
            pass

    monkeypatch.setattr(cv2, "VideoCapture", QueuedCamera)
    cam = CaptureCamera(0, live=True, size=(64, 48))
    try:
        stamp_errors = []
        for _ in range(10):
            frame = cam.read(timeout_s=1.0)
            assert frame is not None
            stamp_errors.append(frame.t_s - cam.cap.captured_s[int(frame.image_bgr[0, 0, 0])])
            time.sleep(0.05)  # processing
    finally:
        cam.close()
    assert max(stamp_errors) < 0.02, stamp_errors
    assert cam.dropped >= 50  # about 9 of every 10 frames


def test_a_live_frame_keeps_the_drivers_capture_time_when_it_is_on_the_monotonic_clock():
    from auxgps.io.camera import capture_time

    assert capture_time(1000.30, 1000_120.0) == pytest.approx(1000.12)  # V4L2: stamped at capture, read 0.18 s later
    assert capture_time(1000.30, 4_000.0) == 1000.30  # a stream position, not this clock
    assert capture_time(1000.30, 1000_500.0) == 1000.30  # after the read: not a capture time
    assert capture_time(1000.30, float("nan")) == 1000.30


def test_a_frame_rate_for_a_camera_that_is_not_simulated_is_refused_by_name(tmp_path):
    with pytest.raises(ConfigError, match="goes with sim:WORLD only"):
        open_camera(str(tmp_path), CAMERA, R_BODY_CAM_DOWN, sim_fps=30.0)


def test_a_simulated_camera_whose_thread_fails_names_the_failure_to_the_frame_loop():
    def truth():
        raise RuntimeError("truth source gone")

    cam = open_camera("sim:one_cube_1m", CAMERA, R_BODY_CAM_DOWN, truth=truth, sim_fps=50.0)
    try:
        with pytest.raises(ConfigError, match="simulated camera stopped: RuntimeError: truth source gone"):
            for _ in range(100):
                cam.read(timeout_s=0.1)
    finally:
        cam.close()


@pytest.mark.realtime
def test_a_simulated_camera_at_its_own_rate_gives_the_newest_frame_and_counts_those_not_taken():
    """The simulator's truth at 100 Hz, the camera at 50 frames a second, a frame loop taking 100 ms: each frame read
    is the newest (rendered from a truth under 50 ms old), and about four of every five are dropped, not queued."""
    import time

    from auxgps.io.link import Truth
    from auxgps.sim.world import load_world

    frame = load_world("one_cube_1m").frame
    t0 = time.monotonic()

    def truth():
        t = t0 + np.floor((time.monotonic() - t0) * 100.0) / 100.0
        lat, lon, alt = frame.to_geodetic(np.array([0.0, 2.0 * (t - t0), -10.0]))
        return Truth(t, float(lat), float(lon), float(alt), np.zeros(3))

    cam = open_camera("sim:one_cube_1m", CAMERA, R_BODY_CAM_DOWN, truth=truth, sim_fps=50.0)
    try:
        ages, times = [], []
        for _ in range(10):
            f = cam.read(timeout_s=1.0)
            assert f is not None
            ages.append(time.monotonic() - f.t_s)
            times.append(f.t_s)
            time.sleep(0.1)  # processing
    finally:
        cam.close()
    assert max(ages) < 0.05, ages
    assert np.all(np.diff(times) > 0.05)  # never a queued older frame
    assert cam.delivered >= 40 and cam.dropped >= 30, (cam.delivered, cam.dropped)
