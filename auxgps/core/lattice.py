"""Values computed exactly on a lattice of nodes every ``step`` pixels and interpolated bilinearly in between
(a reprojection, a ray's hit on the ground): :func:`node_axis` places the nodes, :func:`upsample` fills the
pixels. Used where the exact map is smooth over a lattice cell (an orthophoto's reprojection into a view, a
photo's projection onto the ground)."""

from __future__ import annotations

import cv2
import numpy as np


def node_axis(n_px: int, step: int) -> np.ndarray:
    """Coordinates of the nodes along an axis of ``n_px`` pixels, ``step * k + (step - 1) / 2`` for k from -1
    to ceil(n_px / step): where ``cv2.resize`` by ``step``, cropped by ``step``, puts its samples (see
    :func:`upsample`)."""
    k = np.arange(-1, -(-n_px // step) + 1)
    return step * k + (step - 1) / 2.0


def upsample(nodes: np.ndarray, n_rows: int, n_cols: int, step: int) -> np.ndarray:
    """Values at the nodes of :func:`node_axis` ((gh, gw) or (gh, gw, C) float32) -> bilinear at every pixel
    (n_rows, n_cols[, C]): cv2.resize with the nodes exactly on its sample positions, so in-between pixels are
    interpolated and none extrapolated."""
    gh, gw = nodes.shape[:2]
    big = cv2.resize(nodes, (gw * step, gh * step), interpolation=cv2.INTER_LINEAR)
    return big[step : step + n_rows, step : step + n_cols]
