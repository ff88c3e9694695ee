"""Numpy oracle of the compiled climb of :mod:`maps.pyramid` (tests only).

:func:`register_reference` is :func:`maps.pyramid.register` with every climb in numpy
(:func:`maps.pyramid._climb_steps`, the loop the masked search runs at run time) in place of
the compiled one (:func:`maps.pyramid.pyramid_kernels.climb`): the same pyramids, levels, limits
and confidence around it, so a difference is the climb's. The compiled search must find the
same peak, surface and confidence (see ``tests/test_kernel_equivalence.py``).
"""

from __future__ import annotations

from typing import Any
from unittest import mock

import numpy as np

from maps import pyramid


def _numpy_climb(
    ref: np.ndarray, mov: np.ndarray, center: tuple[int, int], extent: list[int], reach: int
) -> tuple[tuple[int, int], np.ndarray, float, int, bool]:
    """:func:`maps.pyramid._climb_compiled` by the numpy steps, without masks."""
    return pyramid._climb_steps(ref, mov, center, extent, reach, None, None)


def register_reference(reference: np.ndarray, moving: np.ndarray, **kwargs: Any) -> pyramid.Match:
    """:func:`maps.pyramid.register` (same arguments) with the unmasked climb in numpy.

    The engine's own function runs with its compiled climb replaced for the call (one place
    defines the pyramid, the levels and the confidence); not for use from several threads."""
    with mock.patch.object(pyramid, "_climb_compiled", _numpy_climb):
        return pyramid.register(reference, moving, **kwargs)
