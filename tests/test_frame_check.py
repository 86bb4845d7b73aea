"""Frames not fit to locate from: frozen, covered, blinded, blurred; a frame rate that collapses."""

import cv2
import numpy as np
import pytest

from auxgps.core.frame_check import FrameCheck


def ground(seed=0, shape=(720, 1280)):
    """A textured ground image, like a field or a roof seen from above: detail at every scale from 1 to 32 px."""
    rng = np.random.default_rng(seed)
    acc = np.zeros(shape, np.float32)
    for k, amp in ((32, 60), (16, 40), (8, 30), (4, 20), (2, 15), (1, 10)):
        coarse = rng.standard_normal((shape[0] // k, shape[1] // k)).astype(np.float32)
        acc += amp * cv2.resize(coarse, (shape[1], shape[0]), interpolation=cv2.INTER_LINEAR)
    return cv2.cvtColor(np.clip(128 + acc, 0, 255).astype(np.uint8), cv2.COLOR_GRAY2BGR)


def test_a_sharp_textured_frame_is_fit():
    fc = FrameCheck()
    assert fc.check(0.0, ground(0), px_per_s=None) is None
    assert fc.check(0.1, ground(1), px_per_s=None) is None


def test_a_repeated_frame_is_frozen_only_while_the_vehicle_moves():
    img = ground(0)
    fc = FrameCheck()
    fc.check(0.0, img, px_per_s=None)
    assert fc.check(0.1, img.copy(), px_per_s=None).startswith("frozen camera")
    near = cv2.add(img, np.ones_like(img))  # re-encoded: a grey level off everywhere
    assert fc.check(0.2, near, px_per_s=None).startswith("frozen camera")
    assert fc.check(0.3, near.copy(), px_per_s=0.0) is None  # hovering: the same view is no fault
    assert fc.check(0.4, ground(1), px_per_s=None) is None


@pytest.mark.parametrize("fault, starts", [
    ("dark", "image 50% black"),
    ("saturated", "image 50% saturated"),
    ("blur", "image blurred"),
])
def test_covered_blinded_and_blurred_frames_are_named(fault, starts):
    img = ground(0)
    if fault == "dark":
        img[:, : img.shape[1] // 2] = 0  # a strap over half the lens
    elif fault == "saturated":
        img[:, : img.shape[1] // 2] = 255
    else:
        img = cv2.GaussianBlur(img, (0, 0), 3.0)
    reason = FrameCheck().check(0.0, img, px_per_s=None)
    assert reason is not None and reason.startswith(starts), reason


def test_mild_blur_and_a_quarter_in_shadow_are_still_fit():
    img = ground(0)
    assert FrameCheck().check(0.0, cv2.GaussianBlur(img, (0, 0), 1.0), px_per_s=None) is None
    img[: img.shape[0] // 2, : img.shape[1] // 2] = 0
    assert FrameCheck().check(0.0, img, px_per_s=None) is None


def test_a_collapsing_frame_rate_is_said_once_and_its_recovery_too():
    fc = FrameCheck()
    t, notes = 0.0, []
    for _ in range(20):
        t += 1 / 30
        notes.append(fc.rate_note(t))
    for dt in (0.5, 0.6, 0.5):  # the driver stalls: 2 frames a second
        t += dt
        notes.append(fc.rate_note(t))
    for _ in range(3):
        t += 1 / 30
        notes.append(fc.rate_note(t))
    said = [n for n in notes if n]
    assert len(said) == 2 and said[0].startswith("camera frame rate fell") and said[1].startswith("camera frame rate back"), said


def test_a_slow_vehicle_seeing_the_same_image_is_not_frozen_until_it_has_moved_two_small_pixels():
    img = ground(0)
    fc = FrameCheck()
    fc.check(0.0, img, px_per_s=100.0)
    assert fc.check(1 / 30, img.copy(), px_per_s=100.0) is None  # 3 px moved: alike at 160 px, no fault
    assert fc.check(0.2, img.copy(), px_per_s=100.0).startswith("frozen camera: the frame repeats the one of 0.20 s ago")
