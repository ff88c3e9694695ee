"""Pyramids of scale and coarse-to-fine correlation (reference 4.5.5 "Pyramids of Scale").

One implementation serves image flow, entity correlation and map registration:

* :func:`build_pyramid` turns any attribute image into a list of images, each half the size of
  the one before, by averaging 2x2 blocks (4.5.5: "averaging attributes from several higher
  resolution pixels"), so a 256x256 image becomes 256, 128, 64 and 32.
* :func:`register` finds the translation (and, as an option, the rotation) between two images:
  at the coarsest level it evaluates the normalised correlation at the 9 offsets zero and plus
  or minus one pixel in rows and columns, moves to the best one, doubles the offset for the next
  finer level and evaluates 9 offsets again, down to full size (4.5.5: "a form of binary search
  for the correlation offset peak"). A quadratic fit through the 3x3 correlation values at the
  finest level gives the sub-pixel peak.

Images are (H, W) float arrays indexed ``[row, col]``; offsets are ``(rows, cols)`` in pixels of
the full-size image. Masks (attention windows, validity) are (H, W) bool or float weights in
[0, 1]; a pixel with weight 0 takes no part in the correlation.

numpy, with OpenCV for block means, window sums and the optional rotation search; the climb
of an unmasked search is compiled (:mod:`maps.pyramid_kernels`, the search's hot loop), with
the numpy climb kept as its reference and for masked searches.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import NoReturn

import cv2
import numpy as np

from core.errors import EngineError
from maps import pyramid_kernels

MIN_LEVEL_SIZE_PX = 8  # a pyramid level smaller than this per side carries no usable structure
MAX_CLIMB_STEPS = 32  # 9-offset steps allowed per level while the peak is not yet the centre
EAGER_WINDOW_PX = 64 * 64  # windows up to this size get all their offsets in one call
TABLE_MAX_PX = 128 * 128  # regions up to this size get their window sums from summed-area tables
CLIMB_REACH_PX = 2  # a correlation window serves offsets this far from where it was built
CLIMB_MIN_GAIN = 1e-6  # the search moves only for a correlation at least this much better
FLAT_STD = 1e-9  # an image window with a smaller standard deviation has no texture
APERTURE_RATIO = 0.02  # least curvature of the peak along its flattest direction vs steepest


class PyramidError(EngineError, ValueError):
    """An image, mask or search that the pyramid code cannot work with; names the value."""


@dataclass(frozen=True)
class Match:
    """Result of :func:`register`.

    shift_rc:    (2,) float64, pixels: ``moving[r, c] ~= reference[r - shift_r, c - shift_c]``
                 (moving is reference translated by +shift, after rotation when one was searched).
    peak:        normalised correlation at the integer peak, -1..1.
    confidence:  0..1; the peak correlation (clipped at 0) times the fraction of the image the
                 correlation window covered; 0 when the window has no texture, the peak is not
                 a peak along every direction (an edge or a flat patch: the aperture problem)
                 or it sits on the border of the allowed search.
    rotation_rad: rotation of moving against reference about the image centre (counter-clockwise
                 in the (col right, row up) sense, i.e. x right / y up), 0 unless searched.
    multiply_adds: multiply-add operations spent on correlation sums (for cost comparisons).
    levels_used: pyramid levels searched.
    surface:     (3, 3) correlation around the integer peak, indexed ``[dr + 1, dc + 1]``.
    """

    shift_rc: np.ndarray
    peak: float
    confidence: float
    rotation_rad: float = 0.0
    multiply_adds: int = 0
    levels_used: int = 0
    surface: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)), repr=False)


def _as_image(image: np.ndarray, name: str) -> np.ndarray:
    a = np.asarray(image)
    if a.ndim != 2:
        raise PyramidError(f"{name} must be a 2-D (H, W) image, got shape {a.shape}")
    if a.dtype.kind not in "fiub":
        raise PyramidError(f"{name} must be numeric, got dtype {a.dtype}")
    if min(a.shape) < 2:
        raise PyramidError(f"{name} is too small to correlate: shape {a.shape}")
    return a.astype(np.float32, copy=False) if a.dtype != np.float64 else a


def _as_weight(valid: np.ndarray | None, shape: tuple[int, ...], name: str) -> np.ndarray | None:
    if valid is None:
        return None
    w = np.asarray(valid)
    if w.shape != shape:
        raise PyramidError(f"{name} has shape {w.shape}, the image has shape {shape}")
    return w.astype(np.float32)


def _centred(image: np.ndarray, weight: np.ndarray | None) -> np.ndarray:
    """float32 image minus its (weighted) mean, so float32 correlation sums keep precision
    even for attributes far from zero (ranges of 50 m varying by centimetres)."""
    if weight is None:
        mean = cv2.sumElems(image)[0] / image.size  # double accumulators
    else:
        sw = float(weight.sum(dtype=np.float64))
        mean = float((image * weight).sum(dtype=np.float64) / sw) if sw > 0 else 0.0
    return image - np.float32(mean)  # float32 throughout (the same as rounding afterwards)


def downsample(image: np.ndarray) -> np.ndarray:
    """Average 2x2 blocks: (H, W) -> (H // 2, W // 2); an odd last row or column is dropped.
    (OpenCV's area resampling at exactly half size is this block mean, and fast.)"""
    h, w = image.shape[0] // 2, image.shape[1] // 2
    a = image[: 2 * h, : 2 * w]
    if a.dtype in (np.float32, np.float64) and h > 0 and w > 0:
        return cv2.resize(a, (w, h), interpolation=cv2.INTER_AREA)
    a = a.astype(np.float64)
    return 0.25 * (a[0::2, 0::2] + a[1::2, 0::2] + a[0::2, 1::2] + a[1::2, 1::2])


def _weighted_pyramids(
    image: np.ndarray, weight: np.ndarray | None, levels: int
) -> tuple[list[np.ndarray], list[np.ndarray] | None]:
    """Image and weight pyramids; each coarse pixel is the weighted mean of its 2x2 block and
    its weight the mean of their weights (so weights are fractions of valid area)."""
    if weight is None:
        images = [image]
        for _ in range(1, levels):
            images.append(downsample(images[-1]))
        return images, None
    image = np.where(weight > 0, image, 0.0).astype(image.dtype)
    images, weights = [image], [weight]
    for _ in range(1, levels):
        w = downsample(weights[-1])
        s = downsample(images[-1] * weights[-1])
        images.append(np.divide(s, w, out=np.zeros_like(s), where=w > 0))
        weights.append(w)
    return images, weights


def max_levels(shape: tuple[int, ...]) -> int:
    """How many levels an image of this shape supports with the coarsest >= 8 px per side."""
    n, size = 1, min(shape[:2])
    while size // 2 >= MIN_LEVEL_SIZE_PX:
        size //= 2
        n += 1
    return n


def build_pyramid(
    image: np.ndarray, levels: int = 4, valid: np.ndarray | None = None
) -> list[np.ndarray]:
    """Pyramid of scale of an attribute image (4.5.5).

    image:  (H, W) numeric attribute image (range, intensity, gradient, ...).
    levels: number of images returned; level 0 is ``image`` itself (as float), level k is
            (H >> k, W >> k), each pixel the mean of a 2x2 block of level k - 1.
    valid:  optional (H, W) bool mask or [0, 1] weights: invalid pixels are left out of the
            averages; a coarse pixel with no valid pixel under it is NaN.
    Returns a list of float arrays (float32 unless the input was float64).
    """
    a = _as_image(image, "image")
    if levels < 1 or (a.shape[0] >> (levels - 1)) < 1 or (a.shape[1] >> (levels - 1)) < 1:
        raise PyramidError(f"levels={levels} is impossible for an image of shape {a.shape}")
    w = _as_weight(valid, a.shape, "valid")
    images, weights = _weighted_pyramids(a, w, levels)
    if weights is None:
        return images
    return [
        np.where(wl > 0, im, np.nan).astype(im.dtype)
        for im, wl in zip(images, weights, strict=True)
    ]


def _collapsed(region: np.ndarray, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """``region`` (h + b, w + b) with the rows and columns every (h, w) window shares summed
    into one: two (2b + 1, 2b + 1) float64 arrays, of the pixels and of their squares, whose
    k x k boxes, k = b + 1, sum the same pixels as the windows (top and bottom b rows, left and
    right b columns kept one by one, the shared middle collapsed to one row and one column)."""
    b = region.shape[0] - h
    block = region[b:h, b:w]
    band_rows = np.vstack((region[:b], region[h:])).astype(np.float64)  # (2b, W)
    band_cols = np.hstack((region[b:h, :b], region[b:h, w:])).astype(np.float64)  # (h - b, 2b)
    out = []
    for rows, cols, total in (
        (band_rows, band_cols, cv2.sumElems(block)[0]),
        (band_rows**2, band_cols**2, cv2.norm(block, cv2.NORM_L2SQR)),  # double accumulators
    ):
        c = np.empty((2 * b + 1, 2 * b + 1))
        c[:b, :b], c[:b, b + 1 :] = rows[:b, :b], rows[:b, w:]
        c[b + 1 :, :b], c[b + 1 :, b + 1 :] = rows[b:, :b], rows[b:, w:]
        mid_of_rows = rows[:, b:w].sum(axis=1)
        c[:b, b], c[b + 1 :, b] = mid_of_rows[:b], mid_of_rows[b:]
        mid_of_cols = cols.sum(axis=0)
        c[b, :b], c[b, b + 1 :] = mid_of_cols[:b], mid_of_cols[b:]
        c[b, b] = total
        out.append(c)
    return out[0], out[1]


def _window_sums(region: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Sums and sums of squares of every (h, w) = ``shape`` window of ``region``.

    region: (h + k - 1, w + k - 1) float32. Returns two (k, k) float64 arrays indexed by the
    window's top-left corner; squares are taken in double. A small region gets summed-area
    tables (one OpenCV call); a large one would spill two float64 tables out of the cache, so
    the rows and columns all its windows share are summed once into one row and one column
    (:func:`_collapsed`) and the tables are taken over that small (2k - 1, 2k - 1) array.
    """
    h, w = shape
    k = region.shape[0] - h + 1
    if region.size <= TABLE_MAX_PX:
        tables = cv2.integral2(region, sdepth=cv2.CV_64F, sqdepth=cv2.CV_64F)
        h0, w0 = h, w
    else:
        tables = [cv2.integral(c) for c in _collapsed(region, h, w)]
        h0 = w0 = k
    return tuple(
        t[h0 : h0 + k, w0 : w0 + k] - t[:k, w0 : w0 + k] - t[h0 : h0 + k, :k] + t[:k, :k]
        for t in tables
    )


def _no_overlap(center_rc: tuple[int, int], reach: int, ref_shape, mov_shape) -> NoReturn:
    raise PyramidError(
        f"offset {center_rc} +- {reach} px leaves no overlap between images of shapes "
        f"{ref_shape} and {mov_shape}: the correlation window is larger than the image"
    )


class _Window:
    """Normalised correlation of one fixed window of ``mov`` against ``ref`` near an offset.

    The window holds every pixel of ``mov`` whose partner ``ref[r - dr, c - dc]`` exists for
    every offset within ``reach`` (Chebyshev) of ``center_rc``, so all values compare the same
    pixels of ``mov``. ``table[dr - center_r + reach, dc - center_c + reach]`` caches values
    (NaN: no texture); small plain windows fill the whole table in one call, large ones fill
    entries on demand. ``multiply_adds`` counts the work.
    """

    def __init__(
        self,
        ref: np.ndarray,
        mov: np.ndarray,
        center_rc: tuple[int, int],
        reach: int,
        w_ref: np.ndarray | None,
        w_mov: np.ndarray | None,
    ) -> None:
        h, w = mov.shape
        cr, cc = center_rc
        r0, r1 = max(0, cr + reach), min(h, ref.shape[0] + cr - reach)
        c0, c1 = max(0, cc + reach), min(w, ref.shape[1] + cc - reach)
        if r1 - r0 < 2 or c1 - c0 < 2:
            _no_overlap(center_rc, reach, ref.shape, mov.shape)
        self.center, self.reach = center_rc, reach
        k = 2 * reach + 1
        self.table = np.full((k, k), np.nan)
        self.done = np.zeros((k, k), dtype=bool)
        self.complete = False  # every entry of the table is known
        self.multiply_adds = 0
        self.flat: np.ndarray | None = None  # ref's memory as one row, for the large plain path
        self.flat_t: np.ndarray | None = None  # the padded template as one row, its partner
        t = mov[r0:r1, c0:c1]
        self.n = t.size
        # ref window for offset (dr, dc) starts at (r0 - dr, c0 - dc); the region spans them all.
        rows = slice(r0 - cr - reach, r1 - cr + reach)
        cols = slice(c0 - cc - reach, c1 - cc + reach)
        self.region = ref[rows, cols]
        self.w_region = None if w_ref is None else w_ref[rows, cols]
        if w_mov is None and w_ref is None:
            self.wt = None
            self.t = self._template(t, ref)
            self.t_norm = cv2.norm(self.t, cv2.NORM_L2)  # double accumulators
            self.cover = self.n / mov.size
            if self.t_norm < FLAT_STD * math.sqrt(self.n):
                self.done[:] = True  # no texture: every offset correlates as NaN
                self.complete = True
                return
            # Window sums come indexed by window top-left corner; flip to offset order.
            s, ss = _window_sums(self.region, t.shape)
            s, ss = s[::-1, ::-1], ss[::-1, ::-1]
            self.multiply_adds += self.n + self.region.size  # template norm, region squares
            var = ss - s * s / self.n
            self.denominator = np.where(
                var > (FLAT_STD**2) * self.n, self.t_norm * np.sqrt(np.maximum(var, 0.0)), np.nan
            )
            if self.n <= EAGER_WINDOW_PX:
                # Small windows: all (2 reach + 1)^2 cross sums in one call beats a call each
                # (OpenCV's plain cross-correlation, indexed by window top-left like the sums).
                cross = cv2.matchTemplate(self.region, self.t, cv2.TM_CCORR)[::-1, ::-1]
                self.multiply_adds += k * k * self.n
                self.table = cross / self.denominator
                self.done[:] = True
                self.complete = True
            elif self.flat_t is not None:
                self.flat = ref.reshape(-1)
                self.flat_origin = (rows.start, cols.start, ref.shape[1])
        else:
            self.t = t
            self.wt = np.ones_like(t) if w_mov is None else w_mov[r0:r1, c0:c1]
            self.twt = self.t * self.wt
            total = mov.size if w_mov is None else max(float(w_mov.sum()), 1e-9)
            self.cover = min(1.0, float(self.wt.sum()) / total)

    def _template(self, t: np.ndarray, ref: np.ndarray) -> np.ndarray:
        """``t`` minus its mean (float32). A large window whose ``ref`` is one float32 block
        gets its cross sums as 1-D dot products over ``ref``'s memory (BLAS, faster than a 2-D
        window sum): the template is then written into a buffer padded with
        zeros to ``ref``'s row length, so one contiguous run of ``ref`` starting at a window's
        top-left pixel lines up with it row for row and the pixels between window rows meet
        the zero padding; ``flat_t`` is that buffer as one row (None for the 2-D path)."""
        mean = np.float32(cv2.sumElems(t)[0] / self.n)
        if self.n <= EAGER_WINDOW_PX or ref.dtype != np.float32 or not ref.flags.c_contiguous:
            return t - mean
        h, w = t.shape
        width = ref.shape[1]
        padded = np.empty((h, width), np.float32)
        np.subtract(t, mean, out=padded[:, :w])
        padded[:, w:] = 0.0
        self.flat_len = (h - 1) * width + w  # the trailing padding of the last row is not needed
        self.flat_t = padded.reshape(-1)[: self.flat_len]
        return padded[:, :w]

    def covers(self, center_rc: tuple[int, int]) -> bool:
        """Whether the 3x3 neighbourhood of ``center_rc`` lies inside this window's reach."""
        return (
            max(abs(center_rc[0] - self.center[0]), abs(center_rc[1] - self.center[1]))
            <= self.reach - 1
        )

    def surface(self, center_rc: tuple[int, int]) -> np.ndarray:
        """(3, 3) correlation at ``center_rc + {-1, 0, 1}^2``, indexed ``[dr + 1, dc + 1]``."""
        i0 = center_rc[0] - self.center[0] + self.reach - 1
        j0 = center_rc[1] - self.center[1] + self.reach - 1
        if self.complete:
            return self.table[i0 : i0 + 3, j0 : j0 + 3].copy()
        for i in range(i0, i0 + 3):
            for j in range(j0, j0 + 3):
                if not self.done[i, j]:
                    self.table[i, j] = self._value(i, j)
                    self.done[i, j] = True
        return self.table[i0 : i0 + 3, j0 : j0 + 3].copy()

    def _ref_window(self, i: int, j: int, image: np.ndarray) -> np.ndarray:
        k = 2 * self.reach
        h, w = self.t.shape
        return image[k - i : k - i + h, k - j : k - j + w]

    def _value(self, i: int, j: int) -> float:
        win = self._ref_window(i, j, self.region)
        if self.wt is None:
            if self.flat is not None:
                # Window (i, j) starts at region[2 reach - i, 2 reach - j] (see _ref_window).
                row0, col0, width = self.flat_origin
                k = 2 * self.reach
                start = (row0 + k - i) * width + col0 + k - j
                run = self.flat[start : start + self.flat_len]
                self.multiply_adds += self.flat_len  # padding products count as work too
                return float(np.dot(run, self.flat_t)) / self.denominator[i, j]
            self.multiply_adds += self.n
            return float(np.einsum("ij,ij->", win, self.t)) / self.denominator[i, j]
        if self.w_region is None:
            ww, wtt = self.wt, self.twt
        else:
            ww = self.wt * self._ref_window(i, j, self.w_region)
            wtt = ww * self.t
        sw = float(np.einsum("ij->", ww))
        if sw <= 0:
            return np.nan
        wr = ww * win
        sa, sb = float(np.einsum("ij->", wr)), float(np.einsum("ij->", wtt))
        saa = float(np.einsum("ij,ij->", wr, win))
        sbb = float(np.einsum("ij,ij->", wtt, self.t))
        sab = float(np.einsum("ij,ij->", wr, self.t))
        self.multiply_adds += 8 * self.n
        va, vb = saa - sa * sa / sw, sbb - sb * sb / sw
        if va <= (FLAT_STD**2) * sw or vb <= (FLAT_STD**2) * sw:
            return np.nan
        return (sab - sa * sb / sw) / np.sqrt(va * vb)


def _subpixel(surface: np.ndarray) -> tuple[float, float]:
    """Sub-pixel peak offset (rows, cols) in [-0.5, 0.5] from a 3x3 correlation surface, by a
    parabola through the centre and its two neighbours along each axis (NaN counts as -1)."""
    f = [[-1.0 if v != v else v for v in row] for row in surface.tolist()]
    mid = f[1][1]
    d = [0.0, 0.0]
    for axis, (lo, hi) in enumerate(((f[0][1], f[2][1]), (f[1][0], f[1][2]))):
        den = lo - 2.0 * mid + hi
        if den < 0:
            d[axis] = min(max(0.5 * (lo - hi) / den, -0.5), 0.5)
    return d[0], d[1]


def _best_of_nine(values: list[float]) -> int:
    """Index of the first largest non-NaN value (row-major over the 3x3), -1 if all are NaN."""
    best = -1
    for k, v in enumerate(values):
        if v == v and (best < 0 or v > values[best]):
            best = k
    return best


def _climb(
    ref: np.ndarray,
    mov: np.ndarray,
    start_rc: tuple[int, int],
    w_ref: np.ndarray | None,
    w_mov: np.ndarray | None,
    limit_px: float | None,
) -> tuple[tuple[int, int], np.ndarray, float, int, bool]:
    """Move the 9-offset search to its best offset until the centre is the peak.

    The search stays within ``limit_px`` and within half the image either way (so the window
    keeps at least half the image); it moves only for a strictly better correlation, so a flat
    direction (an edge) does not send it wandering. Returns the integer peak, its (3, 3)
    correlation surface indexed ``[dr + 1, dc + 1]``, the window coverage, the multiply-adds
    spent and whether the peak is pinned (at a limit, or out of steps). Without masks the
    climb runs in :func:`maps.pyramid_kernels.climb` (:func:`_climb_compiled`); with masks in
    numpy (:func:`_climb_steps`, the same windows and steps: the kernel's reference too)."""
    extent = [max(s // 2 - CLIMB_REACH_PX, 0) for s in mov.shape[:2]]
    if limit_px is not None:
        extent = [max(min(e, math.floor(limit_px)), 0) for e in extent]
    center = (
        min(max(int(start_rc[0]), -extent[0]), extent[0]),
        min(max(int(start_rc[1]), -extent[1]), extent[1]),
    )
    reach = CLIMB_REACH_PX
    if max(extent) == CLIMB_REACH_PX and 4 * (reach + 1) <= min(mov.shape[:2]):
        # The whole search fits one window a pixel wider (the coarsest level, mostly): built
        # once, where a climb to the edge would build a second one.
        reach += 1
    if w_ref is None and w_mov is None:
        return _climb_compiled(ref, mov, center, extent, reach)
    return _climb_steps(ref, mov, center, extent, reach, w_ref, w_mov)


def _climb_compiled(
    ref: np.ndarray,
    mov: np.ndarray,
    center: tuple[int, int],
    extent: list[int],
    reach: int,
) -> tuple[tuple[int, int], np.ndarray, float, int, bool]:
    """The unmasked climb of :func:`_climb` in :func:`maps.pyramid_kernels.climb`."""
    surface = np.empty((3, 3))
    out = np.zeros(6, dtype=np.int64)
    cover = pyramid_kernels.climb(
        ref, mov, center[0], center[1], extent[0], extent[1], reach, MAX_CLIMB_STEPS,
        CLIMB_MIN_GAIN, FLAT_STD, surface, out,
    )  # fmt: skip
    if out[2] == pyramid_kernels.NO_OVERLAP:
        _no_overlap((int(out[4]), int(out[5])), reach, ref.shape, mov.shape)
    return (int(out[0]), int(out[1])), surface, cover, int(out[3]), bool(out[2])


def _climb_steps(
    ref: np.ndarray,
    mov: np.ndarray,
    center: tuple[int, int],
    extent: list[int],
    reach: int,
    w_ref: np.ndarray | None,
    w_mov: np.ndarray | None,
) -> tuple[tuple[int, int], np.ndarray, float, int, bool]:
    """The climb of :func:`_climb` in numpy, from ``center`` within ``extent`` (rows, cols),
    windows ``reach`` px beyond the 3x3: the masked search runs it, and it is the definition
    the compiled climb is held to (``tests/kernel_reference/pyramid_reference.py``)."""
    ops = 0
    win = _Window(ref, mov, center, reach, w_ref, w_mov)
    for _ in range(MAX_CLIMB_STEPS):
        if not win.covers(center):
            ops += win.multiply_adds
            win = _Window(ref, mov, center, reach, w_ref, w_mov)
        surface = win.surface(center)
        out_r = [abs(center[0] + d) > extent[0] for d in (-1, 0, 1)]
        out_c = [abs(center[1] + d) > extent[1] for d in (-1, 0, 1)]
        pinned = any(out_r) or any(out_c)
        if pinned:  # offsets beyond the search limit take no part
            surface[np.logical_or.outer(out_r, out_c)] = np.nan
        values = surface.ravel().tolist()
        best = _best_of_nine(values)
        done = ops + win.multiply_adds
        if best < 0:
            return center, surface, win.cover, done, False
        centre_value = values[4] if math.isfinite(values[4]) else -math.inf
        if best == 4 or values[best] <= centre_value + CLIMB_MIN_GAIN:
            return center, surface, win.cover, done, pinned
        center = (center[0] + best // 3 - 1, center[1] + best % 3 - 1)
    return center, surface, win.cover, ops + win.multiply_adds, True


def _confidence(surface: np.ndarray, cover: float, pinned: bool) -> float:
    """Peak correlation (clipped to 0..1) times window coverage; 0 when the peak is pinned at
    the search limit, has no texture, or is not a peak along every direction: the correlation
    must fall away along rows, columns and both diagonals, and along the flattest of them by at
    least ``APERTURE_RATIO`` of the steepest (an edge or a flat patch correlates equally well
    along its length: the aperture problem)."""
    f = surface.tolist()
    if pinned or not all(math.isfinite(v) for row in f for v in row):
        return 0.0
    c = f[1][1]
    curvatures = (
        f[0][1] + f[2][1] - 2 * c,  # rows
        f[1][0] + f[1][2] - 2 * c,  # columns
        (f[0][0] + f[2][2] - 2 * c) / 2,  # diagonals (their steps are sqrt(2) long)
        (f[0][2] + f[2][0] - 2 * c) / 2,
    )
    flattest, steepest = max(curvatures), min(curvatures)
    if flattest >= 0 or flattest > APERTURE_RATIO * steepest:
        return 0.0
    return min(max(c, 0.0), 1.0) * min(max(float(cover), 0.0), 1.0)


def _register_translation(
    ref_pyr: list[np.ndarray],
    mov_pyr: list[np.ndarray],
    wref_pyr: list[np.ndarray] | None,
    wmov_pyr: list[np.ndarray] | None,
    max_shift_px: float | None,
    initial_rc: tuple[float, float] = (0.0, 0.0),
) -> Match:
    levels = len(ref_pyr)
    top = levels - 1
    center = (round(initial_rc[0] / 2**top), round(initial_rc[1] / 2**top))
    ops = 0
    for lev in range(top, -1, -1):
        limit = None if max_shift_px is None else max_shift_px / 2**lev
        wr = None if wref_pyr is None else wref_pyr[lev]
        wm = None if wmov_pyr is None else wmov_pyr[lev]
        center, surface, cover, n, pinned = _climb(
            ref_pyr[lev], mov_pyr[lev], center, wr, wm, limit
        )
        ops += n
        if lev > 0:
            # Start the finer level from the sub-pixel peak, so it rarely needs to climb.
            sub_r, sub_c = _subpixel(surface)
            center = (round(2.0 * (center[0] + sub_r)), round(2.0 * (center[1] + sub_c)))
    peak = float(surface[1, 1]) if np.isfinite(surface[1, 1]) else -1.0
    if limit is not None and max(abs(center[0]), abs(center[1])) >= limit:
        pinned = True
    shift = np.array(center, dtype=np.float64) + _subpixel(surface)
    return Match(
        shift_rc=shift,
        peak=peak,
        confidence=_confidence(surface, cover, pinned),
        multiply_adds=int(ops),
        levels_used=levels,
        surface=surface,
    )


def rotate_image(image: np.ndarray, angle_rad: float, border: float = 0.0) -> np.ndarray:
    """Rotate an (H, W) image about its centre by ``angle_rad`` counter-clockwise in the
    (x right, y up) sense; bilinear; pixels from outside take ``border``."""

    h, w = image.shape
    cy, cx = (h - 1) / 2.0, (w - 1) / 2.0
    # Output pixel (col x, row y) samples input at R(-a) about the centre, with y pointing down
    # in the array: a counter-clockwise turn (y up) is clockwise in (col, row).
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    M = np.array([[c, -s, cx - c * cx + s * cy], [s, c, cy - s * cx - c * cy]])
    return cv2.warpAffine(
        image.astype(np.float32),
        M,
        (w, h),
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=border,
    )


def register(
    reference: np.ndarray,
    moving: np.ndarray,
    *,
    levels: int = 4,
    max_shift_px: float | None = None,
    valid_reference: np.ndarray | None = None,
    valid_moving: np.ndarray | None = None,
    rotations_rad: Sequence[float] | None = None,
    initial_shift_rc: tuple[float, float] = (0.0, 0.0),
) -> Match:
    """Coarse-to-fine correlation of two images (4.5.5): the offset, peak and confidence.

    reference, moving: (H, W) numeric images of the same attribute (shapes may differ).
    levels:        pyramid levels to use (fewer when the image is too small: the coarsest
                   level keeps >= 8 px per side). Each level adds reach: with one 9-offset step
                   per level the search covers +-(2^levels - 1) px, and each level climbs
                   further while its peak is off-centre.
    max_shift_px:  refuse offsets beyond this (Chebyshev norm, pixels); None for no limit.
    valid_reference, valid_moving: optional (H, W) masks or [0, 1] weights (attention windows).
    rotations_rad: optional candidate rotations of moving against reference; each is undone
                   about the image centre, the best peak wins and a parabola through its
                   neighbours refines the angle.
    initial_shift_rc: a predicted offset to start from (e.g. the previous cycle's flow).
    Returns a :class:`Match`; ``moving[r, c] ~= reference[r - shift_r, c - shift_c]``.
    """
    wref = _as_weight(valid_reference, np.shape(reference), "valid_reference")
    wmov = _as_weight(valid_moving, np.shape(moving), "valid_moving")
    ref = _as_image(reference, "reference").astype(np.float32, copy=False)
    mov = _as_image(moving, "moving").astype(np.float32, copy=False)
    # The correlation sums are float32: take the mean out first so they keep their precision.
    ref, mov = _centred(ref, wref), _centred(mov, wmov)
    if levels < 1:
        raise PyramidError(f"levels must be >= 1, got {levels}")
    if max_shift_px is not None and max_shift_px < 0:
        raise PyramidError(f"max_shift_px must be >= 0, got {max_shift_px}")
    half = np.array(mov.shape) / 2
    if np.any(np.abs(np.asarray(initial_shift_rc, dtype=np.float64)) > half):
        raise PyramidError(
            f"initial_shift_rc {tuple(initial_shift_rc)} overlaps less than half of the "
            f"{mov.shape} image: the correlation window would be larger than the image"
        )
    n = max(1, min(levels, max_levels(ref.shape), max_levels(mov.shape)))
    ref_pyr, wref_pyr = _weighted_pyramids(ref, wref, n)
    if rotations_rad is None or len(rotations_rad) == 0:
        mov_pyr, wmov_pyr = _weighted_pyramids(mov, wmov, n)
        return _register_translation(
            ref_pyr, mov_pyr, wref_pyr, wmov_pyr, max_shift_px, initial_shift_rc
        )
    return _register_rotation(
        ref_pyr, wref_pyr, mov, wmov, n, list(rotations_rad), max_shift_px, initial_shift_rc
    )


def _register_rotation(
    ref_pyr: list[np.ndarray],
    wref_pyr: list[np.ndarray] | None,
    mov: np.ndarray,
    wmov: np.ndarray | None,
    levels: int,
    angles: list[float],
    max_shift_px: float | None,
    initial_rc: tuple[float, float],
) -> Match:
    """Try each candidate rotation: undo it on ``moving`` (and its mask), register the
    translation, keep the best peak; a parabola over neighbouring angles refines the angle."""
    angles = sorted(float(a) for a in angles)
    w = np.ones(mov.shape, np.float32) if wmov is None else wmov
    results = []
    for a in angles:
        # moving = T(shift) R(a) reference; rotating moving by -a leaves a pure translation
        # R(-a) shift, which the translation search finds.
        mov_a = rotate_image(mov, -a)
        w_a = rotate_image(w, -a) > 0.999
        mov_pyr, wmov_pyr = _weighted_pyramids(mov_a, w_a.astype(np.float32), levels)
        m = _register_translation(
            ref_pyr, mov_pyr, wref_pyr, wmov_pyr, max_shift_px, tuple(initial_rc)
        )
        results.append(m)
    peaks = np.array([m.peak for m in results])
    k = int(np.argmax(peaks))
    angle = angles[k]
    if 0 < k < len(angles) - 1:
        lo, mid, hi = peaks[k - 1], peaks[k], peaks[k + 1]
        den = lo - 2 * mid + hi
        step = 0.5 * (angles[k + 1] - angles[k - 1])
        if den < 0:
            angle += float(np.clip(0.5 * (lo - hi) / den, -0.5, 0.5)) * step
    best = results[k]
    # The translation found is R(-a) shift; rotate it back by +a in (x, y) = (col, -row).
    c, s = np.cos(angle), np.sin(angle)
    x, y = best.shift_rc[1], -best.shift_rc[0]
    shift = np.array([-(s * x + c * y), c * x - s * y])
    return Match(
        shift_rc=shift,
        peak=best.peak,
        confidence=best.confidence,
        rotation_rad=angle,
        multiply_adds=sum(m.multiply_adds for m in results),
        levels_used=best.levels_used,
        surface=best.surface,
    )


def exhaustive_multiply_adds(shape: tuple[int, int], max_shift_px: int) -> int:
    """Multiply-adds of exhaustive normalised correlation of two (H, W) images over every
    offset within +-max_shift_px at full size, counted as :func:`register` counts its own: one
    per window pixel per offset for the cross sum, plus the squares for the window variances
    (window sums taken from summed-area tables, which need adds only)."""
    n_off = (2 * max_shift_px + 1) ** 2
    n_pix = (shape[0] - 2 * max_shift_px) * (shape[1] - 2 * max_shift_px)
    return n_off * n_pix + shape[0] * shape[1] + n_pix
