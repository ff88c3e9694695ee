"""``np.minimum`` / ``np.maximum`` of two scalars inside compiled kernels (numba): NaN when
either is NaN, as numpy's do (Python's ``min`` / ``max`` would keep the other operand)."""

from __future__ import annotations

import numba


@numba.njit(cache=True, nogil=True)
def minimum(a, b):  # pragma: no cover
    """``np.minimum(a, b)`` of two floats: NaN when either is NaN."""
    if a != a:
        return a
    if b != b:
        return b
    return a if a <= b else b


@numba.njit(cache=True, nogil=True)
def maximum(a, b):  # pragma: no cover
    """``np.maximum(a, b)`` of two floats: NaN when either is NaN."""
    if a != a:
        return a
    if b != b:
        return b
    return a if a >= b else b
