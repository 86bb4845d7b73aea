"""Carrying a fix's inliers into the next frames by optical flow, so that a positioning frame between full ones
costs a pyramidal Lucas-Kanade step instead of a detection, a match and a consensus.

A full positioning frame finds its landmarks among every feature's candidates and must rule out every other
reading of the frame; the frames a few hundredths of a second after it see the same corners a few pixels on.
:class:`InlierFlow` follows the pixels of the last fix's inliers into such a frame, starting each from where the
predicted pose puts its landmark, and keeps those that the flow run backwards brings home (forward-backward
check). What it gives is a set of (pixel, landmark) pairs for :meth:`Localiser.locate_followed`; whether they are
still a fix is the localiser's to say, and every full frame starts the inliers afresh.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class Followed:
    """Pairs carried into a frame: ``uv_px`` (K, 2) full-resolution px, ``lm_id`` (K,) their landmarks, ``scale``
    the detection scale of the frame they were first found in (its corners' precision), ``from_full_s`` when that
    frame was taken."""

    uv_px: np.ndarray
    lm_id: np.ndarray
    scale: float
    from_full_s: float


class InlierFlow:
    """The last fix's inlier pixels and landmarks, and the grey image they are in.

    ``window_px``, ``levels``: the Lucas-Kanade window and pyramid levels above the image; ``max_fb_px``: how
    far the backward flow may end from where a point started; ``max_points``: how many pairs are kept, spread over
    the image (the flow's time is in proportion to them, and a fix needs far fewer)."""

    def __init__(self, window_px: int = 11, levels: int = 2, max_fb_px: float = 0.5, max_points: int = 150) -> None:
        self.win = (int(window_px), int(window_px))
        self.levels = int(levels)
        self.max_fb_px = float(max_fb_px)
        self.max_points = int(max_points)
        self._criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 0.03)
        self.forget()

    def forget(self) -> None:
        """No pairs to follow: the next positioning frame is a full one."""
        self._grey = None
        self.pairs: Followed | None = None

    def remember(self, grey: np.ndarray, pairs: Followed) -> None:
        """``pairs`` are in ``grey`` (the frame's full-resolution grey image; kept, not copied); ``max_points`` of
        them at most, spread over it (:func:`spread_over`)."""
        if len(pairs.lm_id) > self.max_points:
            keep = spread_over(pairs.uv_px, grey.shape[1], grey.shape[0], self.max_points)
            pairs = Followed(pairs.uv_px[keep], pairs.lm_id[keep], pairs.scale, pairs.from_full_s)
        self._grey, self.pairs = grey, pairs

    def follow(self, grey: np.ndarray, guess_uv_px: np.ndarray) -> Followed:
        """The remembered pairs carried into ``grey`` (same size), starting each from ``guess_uv_px`` (K, 2): those
        the flow found both ways, within ``max_fb_px`` of its start on the way back, inside the image."""
        pairs = self.pairs
        if pairs is None or self._grey is None:
            raise RuntimeError("nothing to follow: remember a frame's pairs first")
        if grey.shape != self._grey.shape:
            raise ValueError(f"frame of {grey.shape[1]}x{grey.shape[0]} px follows one of {self._grey.shape[1]}x{self._grey.shape[0]}")
        p0 = pairs.uv_px.astype(np.float32).reshape(-1, 1, 2)
        guess = np.asarray(guess_uv_px, np.float32).reshape(-1, 1, 2).copy()
        bad_guess = ~np.all(np.isfinite(guess), axis=(1, 2))
        guess[bad_guess] = p0[bad_guess]
        flags = cv2.OPTFLOW_USE_INITIAL_FLOW
        p1, ok1, _ = cv2.calcOpticalFlowPyrLK(self._grey, grey, p0, guess, winSize=self.win, maxLevel=self.levels,
                                              criteria=self._criteria, flags=flags)
        back, ok2, _ = cv2.calcOpticalFlowPyrLK(grey, self._grey, p1, p0.copy(), winSize=self.win, maxLevel=self.levels,
                                                criteria=self._criteria, flags=flags)
        fb_px = np.linalg.norm((back - p0).reshape(-1, 2), axis=1)
        uv = p1.reshape(-1, 2).astype(float)
        h, w = grey.shape[:2]
        inside = (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] <= h - 1)
        keep = ok1.ravel().astype(bool) & ok2.ravel().astype(bool) & (fb_px <= self.max_fb_px) & inside & ~bad_guess
        return Followed(uv[keep], pairs.lm_id[keep], pairs.scale, pairs.from_full_s)


def spread_over(uv_px: np.ndarray, width_px: int, height_px: int, n: int, cells: int = 4) -> np.ndarray:
    """Indices of ``n`` of the points ``uv_px`` (K, 2), spread over a ``cells`` x ``cells`` grid of the image: the
    first of every cell, then the second of every cell, and so on (a fix's geometry wants the whole image, not the
    corner its strongest texture is in)."""
    col = np.clip((uv_px[:, 0] * cells / width_px).astype(int), 0, cells - 1)
    row = np.clip((uv_px[:, 1] * cells / height_px).astype(int), 0, cells - 1)
    cell = row * cells + col
    by_cell = np.argsort(cell, kind="stable")
    starts = np.searchsorted(cell[by_cell], np.arange(cells * cells))
    rank = np.empty(len(cell), int)
    rank[by_cell] = np.arange(len(cell)) - starts[cell[by_cell]]  # a point's place among its cell's
    return np.sort(np.lexsort((cell, rank))[:n])
