"""Numpy oracle of the compiled PSD test of :mod:`kd_store.covariance` (tests only).

:func:`psd_mask_reference` is the oracle of :func:`kd_store.covariance.psd_mask`: a packed 6x6
covariance is positive semidefinite when the Cholesky factorisation of
``C + tol * scale * I`` succeeds (``scale = max(1, largest diagonal entry)``), unrolled over
columns and vectorised over blocks of matrices. The kernel must give the same answers.
"""

from __future__ import annotations

import numpy as np

from kd_store.covariance import PACK_INDEX

_BLOCK = 8192  # rows per block: keeps the unrolled factorisation's temporaries in cache


def psd_mask_reference(
    cov21: np.ndarray, tol: float = 1e-9, scale: np.ndarray | None = None
) -> np.ndarray:
    """Which packed 6x6 covariances are positive semidefinite: (N, 21) -> (N,) bool.

    Cholesky of ``C + tol * scale * I`` succeeds exactly when the smallest
    eigenvalue of C exceeds ``-tol * scale``; the factorisation is unrolled over
    columns so a batch of a million matrices costs a few dozen vector operations.
    The scale is ``max(1, largest diagonal entry)`` (bounds every entry of a PSD matrix);
    pass it as ``scale`` (N,) when the caller has it already.
    """
    cov21 = np.asarray(cov21, dtype=np.float64)
    if len(cov21) > _BLOCK:
        return np.concatenate(
            [
                psd_mask_reference(
                    cov21[i : i + _BLOCK], tol, None if scale is None else scale[i : i + _BLOCK]
                )
                for i in range(0, len(cov21), _BLOCK)
            ]
        )
    A = np.ascontiguousarray(np.asarray(cov21, dtype=np.float64).T)  # (21, N)
    if scale is None:
        scale = np.maximum(1.0, np.maximum.reduce([A[PACK_INDEX[(i, i)]] for i in range(6)]))
    shift = tol * scale
    ok = np.ones(A.shape[1], dtype=bool)
    L: list[list[np.ndarray | None]] = [[None] * 6 for _ in range(6)]
    for j in range(6):
        s = A[PACK_INDEX[(j, j)]] + shift
        for k in range(j):
            s = s - L[j][k] ** 2
        ok &= s > 0
        d = np.sqrt(np.where(s > 0, s, 1.0))
        L[j][j] = d
        for i in range(j + 1, 6):
            t = A[PACK_INDEX[(j, i)]]
            for k in range(j):
                t = t - L[i][k] * L[j][k]
            L[i][j] = t / d
    return ok
