"""Pyramids of scale and coarse-to-fine correlation (maps.pyramid) against analytic truth."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from kernel_reference.pyramid_reference import register_reference
from kernel_scenes import texture

from maps.pyramid import (
    PyramidError,
    build_pyramid,
    exhaustive_multiply_adds,
    register,
)

H = W = 256


def blobs(rows: np.ndarray, cols: np.ndarray, seed: int = 1, n: int = 150) -> np.ndarray:
    """A smooth analytic image: a sum of Gaussian blobs, sampled at any (row, col)."""
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-20, H + 20, (n, 2))
    sigmas = rng.uniform(3, 10, n)
    amps = rng.uniform(-1, 1, n)
    out = np.zeros(rows.shape)
    for (r0, c0), s, a in zip(centres, sigmas, amps, strict=True):
        out += a * np.exp(-((rows - r0) ** 2 + (cols - c0) ** 2) / (2 * s * s))
    return out.astype(np.float32)


def shifted(shift_rc: tuple[float, float], seed: int = 1) -> np.ndarray:
    """The analytic image translated by +shift: ``img[r, c] = f(r - sr, c - sc)``."""
    r, c = np.mgrid[0:H, 0:W].astype(np.float64)
    return blobs(r - shift_rc[0], c - shift_rc[1], seed)


def test_pyramid_levels_are_block_means():
    rng = np.random.default_rng(0)
    img = rng.random((256, 256)).astype(np.float32)
    pyr = build_pyramid(img, levels=4)
    assert [p.shape for p in pyr] == [(256, 256), (128, 128), (64, 64), (32, 32)]
    # Level 3 pixel (0, 0) is the mean of the top-left 8x8 block.
    assert np.isclose(pyr[3][0, 0], img[:8, :8].mean(), atol=1e-6)
    assert np.isclose(pyr[1][5, 7], img[10:12, 14:16].mean(), atol=1e-6)


def test_pyramid_leaves_invalid_pixels_out_of_the_average():
    img = np.arange(16, dtype=np.float32).reshape(4, 4)
    valid = np.ones((4, 4), bool)
    valid[0, 0] = False
    valid[2:, 2:] = False
    pyr = build_pyramid(img, levels=2, valid=valid)
    assert np.isclose(pyr[1][0, 0], (1 + 4 + 5) / 3)
    assert np.isnan(pyr[1][1, 1])


@pytest.mark.parametrize("seed", range(6))
def test_register_recovers_subpixel_shifts(seed):
    rng = np.random.default_rng(100 + seed)
    truth = rng.uniform(-15, 15, 2)
    m = register(shifted((0.0, 0.0)), shifted(tuple(truth)))
    assert np.abs(m.shift_rc - truth).max() < 0.1
    assert m.peak > 0.99 and m.confidence > 0.8


def test_register_costs_far_less_than_exhaustive_search():
    m = register(shifted((0.0, 0.0)), shifted((9.4, -13.2)))
    assert exhaustive_multiply_adds((H, W), 16) / m.multiply_adds >= 50


def test_mask_keeps_a_corrupted_region_out():
    truth = (2.3, -6.6)
    mov = shifted(truth)
    valid = np.ones((H, W), bool)
    valid[:, :100] = False
    mov[:, :100] = np.random.default_rng(3).normal(0, 5, (H, 100))
    m = register(shifted((0.0, 0.0)), mov, valid_moving=valid)
    assert np.abs(m.shift_rc - truth).max() < 0.1


def test_rotation_search_recovers_angle_and_shift():
    angle, truth = np.deg2rad(4.0), np.array([3.2, -5.7])
    r, c = np.mgrid[0:H, 0:W].astype(np.float64)
    cy, cx = (H - 1) / 2, (W - 1) / 2
    # moving = reference turned by +angle (x right, y up) about the centre, then shifted.
    x, y = c - truth[1] - cx, -(r - truth[0] - cy)
    ca, sa = np.cos(-angle), np.sin(-angle)
    mov = blobs(-(sa * x + ca * y) + cy, ca * x - sa * y + cx)
    m = register(blobs(r, c), mov, rotations_rad=np.deg2rad(np.arange(-8, 8.5, 1.0)))
    assert abs(np.rad2deg(m.rotation_rad) - 4.0) < 0.1
    assert np.abs(m.shift_rc - truth).max() < 0.2


def test_shift_beyond_the_limit_is_not_trusted():
    m = register(shifted((0.0, 0.0)), shifted((12.0, 0.0)), max_shift_px=4)
    assert m.confidence == 0.0
    assert np.abs(m.shift_rc).max() <= 4.5


def test_textureless_image_has_no_confidence():
    flat = np.full((64, 64), 3.0, np.float32)
    assert register(flat, flat).confidence == 0.0


@pytest.mark.parametrize(
    ("args", "kwargs", "needle"),
    [
        ((np.zeros((4, 4, 3)), np.zeros((4, 4))), {}, "2-D"),
        ((np.zeros((32, 32)), np.zeros((32, 32))), {"valid_moving": np.ones((8, 8))}, "(8, 8)"),
        ((np.zeros((32, 32)), np.zeros((32, 32))), {"levels": 0}, "levels"),
        ((np.ones((16, 16)), np.ones((16, 16))), {"initial_shift_rc": (40, 0)}, "larger than"),
    ],
)
def test_bad_input_is_refused_with_the_value(args, kwargs, needle):
    with pytest.raises(PyramidError, match=None) as err:
        register(*args, **kwargs)
    assert needle in str(err.value)


def test_real_image_integer_shift(real_data):
    """A real KITTI frame cropped at two known integer offsets: exact ground truth."""
    img = cv2.imread(str(real_data / "kitti-flow" / "frame1.png"), cv2.IMREAD_GRAYSCALE)
    ref = img[60:316, 400:656].astype(np.float32)
    mov = img[60 - 7 : 316 - 7, 400 + 11 : 656 + 11].astype(np.float32)  # moving = ref + (7, -11)
    m = register(ref, mov)
    assert np.abs(m.shift_rc - [7.0, -11.0]).max() < 0.1
    assert m.confidence > 0.5


def test_an_edge_gives_no_confidence_along_its_length():
    """The aperture problem: stripes along the rows fix the column shift but not the row one."""
    _, c = np.mgrid[0:H, 0:W].astype(np.float64)
    stripes = np.sin(c / 7.0) + 0.5 * np.sin(c / 3.1)
    moved = np.sin((c - 2.5) / 7.0) + 0.5 * np.sin((c - 2.5) / 3.1)
    m = register(stripes, moved)
    assert abs(m.shift_rc[1] - 2.5) < 0.1
    assert m.confidence == 0.0


def test_a_window_larger_than_the_image_is_refused_like_the_reference() -> None:
    """The compiled climb refuses a window larger than the image as the numpy climb does."""
    ref = texture((16, 16), 3, blur=1.0)
    for reg in (register, register_reference):
        with pytest.raises(PyramidError, match="larger than the image"):
            reg(ref, ref[:3, :3])


@pytest.mark.parametrize("offset", [0.0, 50.0, 1000.0])
def test_registration_does_not_depend_on_the_attribute_offset(offset):
    """A range-like image (tens of metres varying by millimetres) registers like the same
    image near zero: the correlation sums keep their precision after the mean comes out."""
    rng = np.random.default_rng(7)
    relief = cv2.GaussianBlur(rng.random((320, 320)).astype(np.float32), (0, 0), 2.0)
    big = relief * np.float32(0.01)  # a few millimetres of relief
    shift = (9, -13)
    ref = big[32:288, 32:288] + np.float32(offset)
    mov = big[32 - shift[0] : 288 - shift[0], 32 - shift[1] : 288 - shift[1]] + np.float32(offset)
    m = register(ref, mov, max_shift_px=16)
    assert np.abs(m.shift_rc - shift).max() < 0.05
    assert 0.99 < m.peak <= 1.0 + 1e-6
    assert m.confidence > 0.7
