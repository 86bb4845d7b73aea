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
