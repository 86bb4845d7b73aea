"""Procedural ground textures: a seeded 'gravel' of small shapes on a mottled ground, for feature-rich worlds.

A flat grey ground gives a few corners per cube and nothing else; a real survey sees hundreds of ground features
per frame. This texture gives that (hundreds to thousands of ORB corners in a 1280x720 view from 15 m at
2 cm/px) without shipping image files, and the same seed always gives the same ground.
"""

from __future__ import annotations

import cv2
import numpy as np


def gravel_texture(size_px: int, seed: int, shapes_per_kpx2: float = 2.5) -> np.ndarray:
    """A (size_px, size_px, 3) uint8 BGR texture: random polygons and rectangles, 3 to 14 px, on a mottled grey.

    Parameters
    ----------
    size_px : side of the square texture, px
    seed : seed of the generator; the same seed gives the same texture
    shapes_per_kpx2 : shapes per thousand square pixels
    """
    rng = np.random.default_rng(seed)
    h = w = int(size_px)
    low = rng.integers(70, 160, (h // 64 + 1, w // 64 + 1)).astype(np.uint8)
    img = np.repeat(cv2.resize(low, (w, h), interpolation=cv2.INTER_CUBIC)[..., None], 3, axis=2)
    for _ in range(int(h * w / 1000.0 * shapes_per_kpx2)):
        color = tuple(int(c) for c in rng.integers(20, 235, 3))
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        s = int(rng.integers(3, 14))
        if rng.random() < 0.5:
            pts = (np.array([x, y]) + rng.integers(-s, s + 1, (int(rng.integers(3, 6)), 2))).astype(np.int32)
            cv2.fillConvexPoly(img, cv2.convexHull(pts), color, lineType=cv2.LINE_AA)
        else:
            cv2.rectangle(img, (x, y), (x + int(rng.integers(2, s)), y + int(rng.integers(2, s))), color, -1)
    return img
