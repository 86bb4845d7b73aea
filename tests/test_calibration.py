"""Camera calibration: chessboard views rendered by the simulator through a lens of known intrinsics and
distortion give them back."""

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from auxgps.config import load_pipeline_config
from auxgps.core.calibration import calibrate, distortion_difference_px, find_board
from auxgps.core.camera import CameraPose, PinholeCamera, camera_from_config
from auxgps.core.geometry import R_BODY_CAM_DOWN, LocalFrame, R_ned_body_from_euler
from auxgps.errors import CameraError
from auxgps.sim.render import Renderer
from auxgps.sim.world import World

REPO = Path(__file__).resolve().parent.parent
COLS, ROWS, SQUARE_M = 9, 6, 0.05  # inner corners, and the square's side
K_TRUE = np.array([[900.0, 0.0, 652.0], [0.0, 900.0, 355.0], [0.0, 0.0, 1.0]])
DIST_TRUE = np.array([-0.12, 0.05, 0.001, -0.0005, 0.0])  # a moderate barrel, slightly decentred
rtol_focal = 0.005  # 0.5 %, the figure
atol_lens_px = 0.5  # the two lenses put no ray more than half a pixel apart anywhere in the image


def chessboard_world(px_per_square: int = 20, margin_m: float = 3.0) -> World:
    """A chessboard of (COLS + 1) x (ROWS + 1) squares on white ground, centred on the origin, the ground wide enough
    that no view reaches its edge (the renderer mirrors a texture beyond it: a second board)."""
    m_per_px = SQUARE_M / px_per_square
    side_px = int(round((2 * margin_m + (COLS + 1) * SQUARE_M) / m_per_px))
    tex = np.full((side_px, side_px), 255, np.uint8)
    h, w = (ROWS + 1) * px_per_square, (COLS + 1) * px_per_square
    r0, c0 = (side_px - h) // 2, (side_px - w) // 2
    for i in range(ROWS + 1):
        for j in range(COLS + 1):
            if (i + j) % 2 == 0:
                tex[r0 + i * px_per_square : r0 + (i + 1) * px_per_square, c0 + j * px_per_square : c0 + (j + 1) * px_per_square] = 30
    return World(LocalFrame(47.0, 8.0, 400.0), (), None, cv2.cvtColor(tex, cv2.COLOR_GRAY2BGR), m_per_px, "test", "chessboard")


def views(camera: PinholeCamera, n: int = 30, seed: int = 4) -> list[np.ndarray]:
    """Grey images of the whole board from above, tilted up to 25 degrees, 0.45 to 0.8 m away, anywhere in the image
    (its corners too: distortion is worst there, and a calibration knows it only where the board has been)."""
    rng = np.random.default_rng(seed)
    renderer = Renderer(chessboard_world(), camera)
    out = []
    while len(out) < n:
        roll, pitch = rng.uniform(-0.45, 0.45, 2)
        R = R_ned_body_from_euler(roll, pitch, rng.uniform(-np.pi, np.pi)) @ R_BODY_CAM_DOWN
        height = rng.uniform(0.45, 0.8)
        # Aim the optical axis at a point near the board, so that it lands in different parts of the image.
        aim = np.array([*rng.uniform(-0.3, 0.3, 2), 0.0])
        p = aim - R[:, 2] * height / R[2, 2]
        img = renderer.render(CameraPose(p, R)).image_bgr
        gray = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        if find_board(gray, COLS, ROWS) is not None:
            out.append(gray)
    return out


@pytest.fixture(scope="module")
def lens():
    return PinholeCamera(1280, 720, K_TRUE, DIST_TRUE)


def test_a_simulated_lens_is_recovered(lens):
    grays = views(lens)
    cal = calibrate([find_board(g, COLS, ROWS) for g in grays], 1280, 720, COLS, ROWS, SQUARE_M)
    assert cal.K[0, 0] == pytest.approx(K_TRUE[0, 0], rel=rtol_focal) and cal.K[1, 1] == pytest.approx(K_TRUE[1, 1], rel=rtol_focal)
    assert np.allclose(cal.K[:2, 2], K_TRUE[:2, 2], atol=3.0)  # px
    assert np.all(np.abs(cal.dist[:4] - DIST_TRUE[:4]) <= [0.005, 0.01, 0.0005, 0.0005]), cal.dist  # k1 k2 p1 p2
    assert cal.dist[4] == 0.0  # k3 held, as OpenCV advises for an ordinary lens
    assert distortion_difference_px(K_TRUE, DIST_TRUE, cal.dist, 1280, 720) <= atol_lens_px
    assert cal.rms_px < 0.1
    assert len(cal.rejected) <= 2  # a view whose corners the simulator's edge smears is left out (seed 4: one)
    # and the test can fail: a lens without its distortion is far from the truth
    assert distortion_difference_px(K_TRUE, DIST_TRUE, np.zeros(5), 1280, 720) > 20


def test_too_few_views_is_a_named_error():
    with pytest.raises(CameraError, match="found in 2 view"):
        calibrate([np.zeros((COLS * ROWS, 2))] * 2, 1280, 720, COLS, ROWS, SQUARE_M)


@pytest.mark.slow
def test_the_command_writes_a_camera_file_the_pipeline_reads(lens, tmp_path):
    folder = tmp_path / "views"
    folder.mkdir()
    for k, g in enumerate(views(lens, n=30, seed=9)):
        cv2.imwrite(str(folder / f"{k:03d}.png"), g)
    cv2.imwrite(str(folder / "not_a_board.png"), np.full((720, 1280), 200, np.uint8))
    out = tmp_path / "camera.yaml"
    proc = subprocess.run([sys.executable, "-m", "auxgps.cli", "camera", "calibrate", "--images", str(folder), "--board", f"{COLS}x{ROWS}",
                           "--square-mm", str(SQUARE_M * 1000), "--out", str(out)], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "reprojection RMS" in proc.stdout and "30 of 31" in proc.stdout
    cam = camera_from_config(load_pipeline_config(out).camera)
    assert cam.K[0, 0] == pytest.approx(K_TRUE[0, 0], rel=rtol_focal)
    assert distortion_difference_px(K_TRUE, DIST_TRUE, cam.dist, 1280, 720) <= atol_lens_px
