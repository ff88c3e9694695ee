"""The large plain-window path (cross sums as dot products over the reference's memory) gives
the same correlation surface as normalised correlation computed directly in float64."""

from __future__ import annotations

import cv2
import numpy as np

from maps.pyramid import register


def _ncc64(ref: np.ndarray, mov: np.ndarray, dr: int, dc: int, win: tuple) -> float:
    """Normalised correlation of mov[win] against ref shifted by (dr, dc), float64."""
    (r0, r1), (c0, c1) = win
    a = ref[r0 - dr : r1 - dr, c0 - dc : c1 - dc].astype(np.float64)
    b = mov[r0:r1, c0:c1].astype(np.float64)
    a, b = a - a.mean(), b - b.mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))


def test_full_size_surface_matches_float64_correlation() -> None:
    rng = np.random.default_rng(3)
    base = cv2.GaussianBlur(rng.random((300, 300)).astype(np.float32), (0, 0), 2.0) * 100 + 50
    shift = (5, -7)
    ref = base[20:276, 20:276]
    mov = base[20 - shift[0] : 276 - shift[0], 20 - shift[1] : 276 - shift[1]]
    m = register(ref, mov, levels=1, max_shift_px=8, initial_shift_rc=shift)
    assert np.abs(m.shift_rc - shift).max() < 0.05
    # The window at centre (5, -7) with reach 2 (see maps.pyramid._Window).
    win = ((5 + 2, 256), (0, 256 - 7 - 2))
    expected = np.array(
        [[_ncc64(ref, mov, 5 + i, -7 + j, win) for j in (-1, 0, 1)] for i in (-1, 0, 1)]
    )
    np.testing.assert_allclose(m.surface, expected, atol=1e-5)
