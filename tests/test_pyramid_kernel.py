"""The compiled climb (maps.pyramid_kernels) against its numpy reference
(``register(..., compiled=False)``): the same peak, surface and confidence on smooth and real
images, shifted, limited, started off the peak, of unequal shapes, without texture, along an
edge; the same refusal when a window cannot be built."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from maps.pyramid import PyramidError, register


def texture(shape: tuple[int, int], seed: int, blur: float = 2.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.random(shape).astype(np.float32), (0, 0), blur)
    return img * 100.0 + 20.0


def crops(base: np.ndarray, shift: tuple[int, int], size: tuple[int, int], pad: int = 24):
    """``ref`` and ``mov = ref`` translated by ``shift`` (rows, cols), both cut from ``base``."""
    (dr, dc), (h, w) = shift, size
    ref = base[pad : pad + h, pad : pad + w]
    mov = base[pad - dr : pad - dr + h, pad - dc : pad - dc + w]
    return ref, mov


def assert_same_match(ref: np.ndarray, mov: np.ndarray, **kwargs) -> None:
    a = register(ref, mov, compiled=True, **kwargs)
    b = register(ref, mov, compiled=False, **kwargs)
    np.testing.assert_allclose(a.shift_rc, b.shift_rc, atol=1e-4)
    np.testing.assert_allclose(a.surface, b.surface, atol=2e-5)
    assert abs(a.peak - b.peak) < 2e-5
    assert abs(a.confidence - b.confidence) < 1e-4
    assert a.levels_used == b.levels_used
    # the compiled climb sums only the offsets it visits
    assert 0 < a.multiply_adds <= b.multiply_adds or a.multiply_adds == b.multiply_adds == 0


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("shift", [(0, 0), (9, -13), (-3, 5), (14, 15)])
def test_compiled_climb_equals_reference_on_textures(seed, shift):
    ref, mov = crops(texture((320, 320), seed), shift, (256, 256))
    assert_same_match(ref, mov, max_shift_px=16)
    assert_same_match(ref, mov)  # no limit: each level climbs as far as it must


@pytest.mark.parametrize(
    "kwargs",
    [
        {"max_shift_px": 4},  # the true shift lies beyond: pinned at the limit
        {"levels": 1, "initial_shift_rc": (8.0, -12.0)},  # one level, started near the peak
        {"levels": 1},  # one level from zero: a long climb with fresh windows on the way
        {"levels": 2, "max_shift_px": 30},
    ],
)
def test_compiled_climb_equals_reference_on_limits_and_starts(kwargs):
    ref, mov = crops(texture((320, 320), 7), (9, -13), (256, 256))
    assert_same_match(ref, mov, **kwargs)


def test_compiled_climb_equals_reference_on_unequal_and_small_images():
    base = texture((300, 300), 11)
    ref = base[20:276, 30:250]
    mov = base[15:215, 33:233]
    assert_same_match(ref, mov)
    small_ref, small_mov = crops(texture((64, 64), 12, blur=1.0), (1, -2), (24, 24), pad=8)
    assert_same_match(small_ref, small_mov)


def test_compiled_climb_equals_reference_without_texture_and_along_an_edge():
    flat = np.full((64, 64), 3.0, np.float32)
    assert_same_match(flat, flat)
    assert register(flat, flat).confidence == 0.0
    _, c = np.mgrid[0:256, 0:256].astype(np.float64)
    stripes = np.sin(c / 7.0) + 0.5 * np.sin(c / 3.1)
    moved = np.sin((c - 2.5) / 7.0) + 0.5 * np.sin((c - 2.5) / 3.1)
    a, b = (register(stripes, moved, compiled=x) for x in (True, False))
    # along the rows every offset correlates alike up to rounding: where the climb stops
    # there is arbitrary (and the confidence 0); across them both find the shift
    assert abs(a.shift_rc[1] - b.shift_rc[1]) < 1e-3
    assert abs(a.shift_rc[1] - 2.5) < 0.1
    assert a.confidence == b.confidence == 0.0


def test_compiled_climb_equals_reference_on_real_frames(real_data):
    img = cv2.imread(str(real_data / "kitti-flow" / "frame1.png"), cv2.IMREAD_GRAYSCALE)
    ref = img[60:316, 400:656].astype(np.float32)
    mov = img[51:307, 413:669].astype(np.float32)  # moving = ref + (9, -13)
    assert_same_match(ref, mov, max_shift_px=16)
    assert np.abs(register(ref, mov, max_shift_px=16).shift_rc - (9, -13)).max() < 0.05


def test_compiled_climb_refuses_a_window_larger_than_the_image_like_the_reference():
    ref = texture((16, 16), 3, blur=1.0)
    for compiled in (True, False):
        with pytest.raises(PyramidError, match="larger than the image"):
            register(ref, ref[:3, :3], compiled=compiled)
