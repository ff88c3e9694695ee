"""Numpy oracles of the compiled crease passes of :mod:`sp.surfaces` (tests only).

:func:`near_blocks_reference` is the oracle of :func:`sp.surfaces.near_blocks` (one shifted
comparison of the block grid per offset: the same pairs, another order),
:func:`crease_pixels_reference` of :func:`sp.surfaces.crease_pixels` (the candidate pixels
expanded, then filtered: the same output), and :func:`find_creases_reference` is
:func:`sp.surfaces.find_creases` with both passes in numpy.
"""

from __future__ import annotations

from typing import Any
from unittest import mock

import numpy as np

from sp import surfaces


def near_blocks_reference(block_label: np.ndarray, gap: int) -> tuple[np.ndarray, np.ndarray]:
    """Oracle of :func:`sp.surfaces.near_blocks` (one shifted comparison of the grid per offset)."""
    nbr, nbc = block_label.shape
    idx = np.arange(nbr * nbc).reshape(nbr, nbc)
    offsets = [(0, dc) for dc in range(1, gap + 1)]
    offsets += [(dr, dc) for dr in range(1, gap + 1) for dc in range(-gap, gap + 1)]
    out_i, out_j = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    for dr, dc in offsets:
        if dr >= nbr or 2 * abs(dc) > nbc:
            continue
        a = block_label[: nbr - dr]
        b = np.roll(block_label, -dc, axis=1)[dr:]
        hit = (a >= 0) & (b >= 0) & (a != b)
        out_i.append(idx[: nbr - dr][hit])
        out_j.append(np.roll(idx, -dc, axis=1)[dr:][hit])
    return np.concatenate(out_i), np.concatenate(out_j)


def crease_pixels_reference(
    pair: np.ndarray,
    blk: np.ndarray,
    n_block_cols: int,
    block: tuple[int, int],
    label: np.ndarray,
    free: np.ndarray,
    xyz: np.ndarray,
    id_a: np.ndarray,
    id_b: np.ndarray,
    p0: np.ndarray,
    u: np.ndarray,
    tol_m: float,
    tol_per_m: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Oracle of :func:`sp.surfaces.crease_pixels` (the candidate pixels expanded, then
    filtered)."""
    H, W = label.shape
    bh, bw = block
    br, bc = np.divmod(blk, n_block_cols)
    pr = (br[:, None] * bh + np.arange(bh).repeat(bw)[None, :]).reshape(-1)
    pc = (bc[:, None] * bw + np.tile(np.arange(bw), bh)[None, :]).reshape(-1)
    q = np.repeat(pair, bh * bw)
    ok = (pr < H) & (pc < W)
    px, q = pr[ok] * W + pc[ok], q[ok]
    own = label.reshape(-1)[px]
    ok = (own == id_a[q]) | (own == id_b[q]) | ((own < 0) & free.reshape(-1)[px])
    px, q = px[ok], q[ok]
    p = xyz.reshape(-1, 3)[px]
    d = p - p0[q]
    tol2 = np.maximum(tol_m**2, tol_per_m**2 * np.einsum("ij,ij->i", p, p))
    with np.errstate(invalid="ignore"):
        on = np.einsum("ij,ij->i", d, d) - np.einsum("ij,ij->i", d, u[q]) ** 2 <= tol2
    return px[on].astype(np.int64), q[on].astype(np.int64)


def find_creases_reference(*args: Any, **kwargs: Any) -> surfaces.Creases:
    """:func:`sp.surfaces.find_creases` (same arguments) with its two compiled passes replaced
    by their oracles for the call (one place defines the rest); not for use from threads."""
    with (
        mock.patch.object(surfaces, "near_blocks", near_blocks_reference),
        mock.patch.object(surfaces, "crease_pixels", crease_pixels_reference),
    ):
        return surfaces.find_creases(*args, **kwargs)
