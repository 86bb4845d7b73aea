"""tools/ortho_compare.py: the shift, scale and turn of one orthophoto against another, on a pair whose answer is
known (the second written from the same texture with a set scale and shift)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import rasterio
from rasterio.transform import from_origin

from tests.conftest import load_tool

oc = load_tool("ortho_compare")

UTM = "EPSG:32617"
RES_M = 0.1
SIZE_PX = 2400  # 240 m square


def _texture(seed: int = 3) -> np.ndarray:
    rng = np.random.default_rng(seed)
    grey = np.zeros((SIZE_PX, SIZE_PX))
    for cell_px, weight in ((200, 1.0), (40, 0.7), (10, 0.5)):
        small = rng.normal(size=(SIZE_PX // cell_px + 2, SIZE_PX // cell_px + 2))
        grey += weight * cv2.resize(small, (SIZE_PX, SIZE_PX), interpolation=cv2.INTER_CUBIC)
    return np.clip(128 + 40 * grey, 0, 255).astype(np.uint8)


def _write(path, grey: np.ndarray, transform, crs=UTM) -> None:
    with rasterio.open(path, "w", driver="GTiff", width=grey.shape[1], height=grey.shape[0], count=3, dtype="uint8", crs=crs,
                       transform=transform) as ds:
        ds.write(np.repeat(grey[None], 3, axis=0))


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    """The first orthophoto, and a second whose content is 1 % larger about the centre and moved 1.2 m east and
    0.7 m south, so a window at (east e, north n) from the centre finds it shifted (1.2 + 0.01 e, -0.7 + 0.01 n)."""
    d = tmp_path_factory.mktemp("ortho_compare")
    x0, y0 = 500_000.0, 4_540_000.0
    grey = _texture()
    _write(d / "first.tif", grey, from_origin(x0, y0, RES_M, RES_M))
    scale, shift_e, shift_n = 1.01, 1.2, -0.7
    c = SIZE_PX / 2.0
    # Second pixel (col, row) shows the first's content at centre + (pixel - centre) / scale, less the shift
    A = np.array([[1 / scale, 0.0, c - c / scale - shift_e / RES_M], [0.0, 1 / scale, c - c / scale + shift_n / RES_M]])
    second = cv2.warpAffine(grey, A, (SIZE_PX, SIZE_PX), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REFLECT)
    _write(d / "second.tif", second, from_origin(x0, y0, RES_M, RES_M))
    return d / "first.tif", d / "second.tif", (scale, shift_e, shift_n)


def test_the_shift_and_scale_between_two_orthophotos_are_found(pair):
    first, second, (scale, shift_e, shift_n) = pair
    cmp = oc.compare(str(first), str(second), gsd_m=0.2, window_m=40.0)
    assert len(cmp.response) >= 9
    np.testing.assert_allclose(cmp.t_en_m, [shift_e, shift_n], atol=0.1)
    assert cmp.scale == pytest.approx(scale - 1.0, abs=0.001)
    assert abs(cmp.turn_rad) < 0.001
    assert cmp.residual_rms_m < 0.1
    same = oc.compare(str(first), str(first), gsd_m=0.2, window_m=40.0)
    assert np.max(np.abs(same.shift_en_m)) < 0.02 and abs(same.scale) < 1e-4


def test_orthophotos_of_different_ground_are_refused_with_a_reason(tmp_path, pair):
    first, _, _ = pair
    other = tmp_path / "elsewhere.tif"
    _write(other, _texture(seed=11), from_origin(500_000.0, 4_540_000.0, RES_M, RES_M))
    with pytest.raises(ValueError, match="windows of 40 m correlate"):
        oc.compare(str(first), str(other), gsd_m=0.2, window_m=40.0, min_response=0.3)
