"""The 6x6 state covariance over (x, y, z, vx, vy, vz): packing and the checks the KD makes.

Packed form: the 21 upper-triangle entries, row-major (the ``cov_pv`` column on disk). The
positive-semidefinite test is a Cholesky factorisation: one compiled loop over the matrices
(:func:`psd_mask`), and the same arithmetic unrolled over many matrices at once in numpy
(``psd_mask_reference``, a test oracle in ``tests/kernel_reference``).
"""

from __future__ import annotations

import numba
import numpy as np

from kd_store.errors import KDError

TRIU_6 = np.triu_indices(6)
PACK_INDEX = {(int(i), int(j)): k for k, (i, j) in enumerate(zip(*TRIU_6, strict=True))}
#: (36,) indices: full 6x6 (row-major) -> packed upper / its mirror in the lower triangle.
FLAT_UP = np.ravel_multi_index(TRIU_6, (6, 6))
FLAT_LO = np.ravel_multi_index((TRIU_6[1], TRIU_6[0]), (6, 6))
#: (36,) index into a packed (21,) covariance giving the full 6x6, row-major.
UNPACK_FLAT = np.array([PACK_INDEX[(min(i, j), max(i, j))] for i in range(6) for j in range(6)])
DIAG = [PACK_INDEX[(i, i)] for i in range(6)]
DIAG_INDEX = tuple(DIAG)
#: (6, 6) int64: packed position of entry (i, j) (either triangle).
_PACKED = UNPACK_FLAT.reshape(6, 6).astype(np.int64)
_OFF = np.array([k for k, (i, j) in enumerate(zip(*TRIU_6, strict=True)) if i != j])
_OFF_UP, _OFF_LO = FLAT_UP[_OFF], FLAT_LO[_OFF]


def pack_covariance(cov: np.ndarray) -> np.ndarray:
    """(N, 6, 6) symmetric -> (N, 21) upper triangle, row-major (C-contiguous)."""
    return np.take(cov.reshape(-1, 36), FLAT_UP, axis=1)


def unpack_covariance(cov21: np.ndarray) -> np.ndarray:
    """(N, 21) upper triangle -> (N, 6, 6) symmetric."""
    return cov21[:, UNPACK_FLAT].reshape(-1, 6, 6)


_BLOCK = 8192  # rows per block: keeps the unrolled factorisation's temporaries in cache


def psd_mask(cov21: np.ndarray, tol: float = 1e-9, scale: np.ndarray | None = None) -> np.ndarray:
    """Which packed 6x6 covariances are positive semidefinite: (N, 21) -> (N,) bool.

    Cholesky of ``C + tol * scale * I`` succeeds exactly when the smallest eigenvalue of C
    exceeds ``-tol * scale``. The scale is ``max(1, largest diagonal entry)`` (bounds every
    entry of a PSD matrix); pass it as ``scale`` (N,) when the caller has it already. One
    compiled pass (:func:`_psd_kernel`), the same arithmetic in the same order as
    ``psd_mask_reference``, so the same answers (NaN is never PSD).
    """
    A = np.ascontiguousarray(cov21, dtype=np.float64)
    if A.ndim != 2 or A.shape[1] != 21:
        raise KDError(f"packed covariances must be (N, 21), got shape {A.shape}")
    if scale is None:
        scale = np.maximum(1.0, np.maximum.reduce([A[:, k] for k in DIAG_INDEX]))
    return _psd_kernel(A, np.ascontiguousarray(scale, dtype=np.float64) * tol)


@numba.njit(cache=True, nogil=True)
def _psd_kernel(A: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """Per row of ``A`` (N, 21): whether the factorisation of the packed matrix plus
    ``shift`` on the diagonal has every pivot > 0 (``psd_mask_reference``, row by row)."""
    n = A.shape[0]
    ok = np.ones(n, dtype=np.bool_)
    L = np.zeros((6, 6))
    for m in range(n):
        for j in range(6):
            s = A[m, _PACKED[j, j]] + shift[m]
            for k in range(j):
                s = s - L[j, k] * L[j, k]
            if not s > 0:
                ok[m] = False
            d = np.sqrt(s) if s > 0 else 1.0
            L[j, j] = d
            for i in range(j + 1, 6):
                t = A[m, _PACKED[j, i]]
                for k in range(j):
                    t = t - L[i, k] * L[j, k]
                L[i, j] = t / d
    return ok


def _symmetric_within(flat: np.ndarray, tol: float, scale: np.ndarray) -> bool:
    """Whether every (36,) row of ``flat`` mirrors within ``tol * scale``; ``<=``, so a NaN or
    inf off the diagonal reads as not symmetric. In cache-sized blocks."""
    for i in range(0, len(flat), _BLOCK):
        block = flat[i : i + _BLOCK]
        d = np.take(block, _OFF_UP, axis=1)
        np.subtract(d, np.take(block, _OFF_LO, axis=1), out=d)
        np.abs(d, out=d)
        if not (d <= (tol * scale[i : i + _BLOCK])[:, None]).all():
            return False
    return True


def pack_checked(flat: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray, bool]:
    """(N, 36) covariances -> packed (N, 21) (a copy), scale (N,) = max(1, largest diagonal
    entry), and whether every one is symmetric within ``tol * scale``.

    Matrices from ``A @ A.T`` or a filter's Joseph update are usually exactly symmetric: one
    ``array_equal`` of the (N, 6, 6) array with its transpose (about the cost of a copy)
    settles those; only otherwise are the 15 mirrored pairs compared within the tolerance.
    The tolerance comparison is NaN-safe (a NaN or inf off the diagonal in either triangle is
    not symmetric), so with the packed entries finite ``symmetric`` also means all 36 are.
    """
    n = len(flat)
    cov21 = np.take(flat, FLAT_UP, axis=1)
    scale = np.maximum(1.0, np.maximum.reduce([cov21[:, k] for k in DIAG]))
    cov = flat.reshape(n, 6, 6)
    symmetric = bool(np.array_equal(cov, cov.transpose(0, 2, 1))) or _symmetric_within(
        flat, tol, scale
    )
    return cov21, scale, symmetric
