"""Is a camera frame fit to locate from? Frozen, covered, blinded and blurred frames are refused before detection.

A fix from a bad frame is worse than none: a driver that stalls repeats its last image with fresh timestamps, and
each repeat located again is a fix at a position the drone has left. :class:`FrameCheck` looks at each frame at a
small size (``size_px`` on its long side; well under a millisecond) and names what is wrong:

- **frozen**: the frame repeats the last one that differed (no pixel of the small image changed by more than
  ``frozen_max_diff`` grey levels) although the vehicle has moved ``frozen_min_motion_px`` full-size pixels since
  (the caller's apparent speed, from the filter; unknown: any repeat), and the image has something to see (standard
  deviation over ``min_structure`` levels: over featureless ground, successive frames are alike anyway). Frames a
  slow vehicle takes a fraction of a pixel apart are alike and not a fault; nor is a vehicle hovering still.
- **dark**: more than ``max_dark_share`` of the pixels at or under ``dark_level`` (a strap over the lens, night);
- **saturated**: more than ``max_saturated_share`` at or over ``saturated_level`` (the sun in view, a gain gone);
- **blurred**: the fine detail gone: the Laplacian's energy is less than ``min_sharpness`` times that of the same
  frame smoothed once more (a sharp frame loses most of it to that smoothing, a blurred one little). Judged only
  where the frame has edges to judge by.
- a **frame rate** that collapses is not a reason to refuse a frame (each has its own capture time), but it is
  named: :meth:`FrameCheck.rate_note` says when frames come more than ``slow_factor`` times further apart than
  they did.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class FrameCheckConfig:
    size_px: int = 160
    frozen_max_diff: int = 3
    frozen_min_motion_px: float = 16.0  # two pixels of the small image
    min_structure: float = 2.0
    dark_level: int = 8
    max_dark_share: float = 0.4
    saturated_level: int = 250
    max_saturated_share: float = 0.4
    min_sharpness: float = 2.6  # sharp frames: 6 to 15 (rendered worlds, the Brighton and Seneca photos); Gaussian blur of 3 px: under 2.3
    min_edge_energy: float = 1.0  # mean squared Laplacian (grey levels^2) below which blur is not judged
    slow_factor: float = 3.0


class FrameCheck:
    """Per-frame fitness, with the memory a frozen camera and a slowing frame rate need."""

    def __init__(self, cfg: FrameCheckConfig | None = None) -> None:
        self.cfg = cfg or FrameCheckConfig()
        self._last_small: np.ndarray | None = None  # the reference: the last frame that differed from its predecessor
        self._ref_t_s = 0.0
        self._last_t_s: float | None = None
        self._intervals: deque[float] = deque(maxlen=30)
        self._slow = False

    def small_grey(self, grey: np.ndarray) -> np.ndarray:
        h, w = grey.shape[:2]
        s = self.cfg.size_px / max(h, w)
        return cv2.resize(grey, (max(1, round(w * s)), max(1, round(h * s))), interpolation=cv2.INTER_AREA)

    def check(self, t_s: float, image_bgr: np.ndarray, px_per_s: float | None) -> str | None:
        """What is wrong with this frame, in a few words, or None when it is fit to locate from. ``px_per_s``: how
        fast the scene moves across the image at its centre, full-size px/s (None: unknown)."""
        cfg = self.cfg
        full = cv2.cvtColor(image_bgr, cv2.COLOR_BGR2GRAY) if image_bgr.ndim == 3 else image_bgr
        small = self.small_grey(full)
        ref = self._last_small
        if ref is None or ref.shape != small.shape:
            self._last_small, self._ref_t_s = small, t_s
        else:
            diff = cv2.absdiff(small, ref)
            if int(diff.max()) > cfg.frozen_max_diff:
                self._last_small, self._ref_t_s = small, t_s  # it changed: the new reference
            else:
                moved_px = np.inf if px_per_s is None else px_per_s * (t_s - self._ref_t_s)
                if moved_px >= cfg.frozen_min_motion_px and float(small.std()) > cfg.min_structure:
                    return (f"frozen camera: the frame repeats the one of {t_s - self._ref_t_s:.2f} s ago (no pixel changed by more "
                            f"than {int(diff.max())} grey levels) while the vehicle moved")
        n = small.size
        dark = float(np.count_nonzero(small <= cfg.dark_level)) / n
        if dark > cfg.max_dark_share:
            return f"image {dark:.0%} black (lens covered?)"
        bright = float(np.count_nonzero(small >= cfg.saturated_level)) / n
        if bright > cfg.max_saturated_share:
            return f"image {bright:.0%} saturated (sun in view?)"
        half = cv2.pyrDown(full).astype(np.float32)
        energy = cv2.norm(cv2.Laplacian(half, cv2.CV_32F), cv2.NORM_L2SQR) / half.size  # mean squared Laplacian
        if energy >= cfg.min_edge_energy:
            lap_smooth = cv2.Laplacian(cv2.GaussianBlur(half, (0, 0), 1.0), cv2.CV_32F)
            sharpness = energy / max(cv2.norm(lap_smooth, cv2.NORM_L2SQR) / half.size, 1e-9)
            if sharpness < cfg.min_sharpness:
                return f"image blurred (sharpness {sharpness:.2f}, under {cfg.min_sharpness:g})"
        return None

    def rate_note(self, t_s: float) -> str | None:
        """A line when the frame rate collapses (and when it recovers), else None."""
        last, self._last_t_s = self._last_t_s, t_s
        if last is None or t_s <= last:
            return None
        dt = t_s - last
        usual = float(np.median(self._intervals)) if len(self._intervals) >= 10 else None
        note = None
        if usual is not None and dt > self.cfg.slow_factor * usual and not self._slow:
            self._slow = True
            note = f"camera frame rate fell: {dt:.2f} s between frames, usually {usual:.3f} s"
        elif usual is not None and self._slow and dt <= 2.0 * usual:
            self._slow = False
            note = f"camera frame rate back: {dt:.3f} s between frames"
        if not self._slow:
            self._intervals.append(dt)
        return note
