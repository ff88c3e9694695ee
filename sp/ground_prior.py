"""The ground the world model expects: a prior for SP's ground segmentation of far returns.

Reference 001, 4.5.4 and 4.6 (sensory processing compares what it observes with what the world
model predicts; the world model's maps hold the terrain, 4.4.10). A return far out is often the
only one its column has on an object (a car's roof seen over nearer cars, the top of a low rock
one row above the ground): the column walk (:mod:`sp.ground`) then sees a gentle rise from the
last ground return and calls it ground. The terrain map already knows the ground around it,
fused from nearer views in earlier sweeps. A far return standing well above the lowest ground
the map knows nearby is not ground.

A low object far out is met by one row only, a few decimetres up, and nothing in one sweep
tells that row's hits from a crest of rough terrain that shades the ground behind it. Several
sweeps do: as the vehicle closes in, one row's hits climb a rock's face, all in the same cell,
while its hits on a crest slide over the terrain, each cell's returns at the one height of the
surface there. So a cell whose lowest and highest returns seen (the map's ``elevation_min``
and ``elevation_max`` layers) lie far apart holds something upright, and a far return in it
standing clear of its lowest is not ground (``span_m``, ``span_rise_m``; on a body lower
than ``low_body_m``, a return nearer its lowest, ``low_rise_m``: the row's later hits sink
down the face as the range grows).

The map is given as its storage: a toroidal (n, n) grid of ground heights, world z in metres,
NaN where unknown; cell ``(ix, iy)`` (``ix = floor(x / resolution_m)``) lives at
``[iy % n, ix % n]`` and is in the window when ``origin_cell <= (ix, iy) < origin_cell + n``
(the convention of :mod:`maps.level`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from core.errors import EngineError


class GroundPriorError(EngineError, ValueError):
    """A ground prior SP cannot use; names the value."""


@dataclass(frozen=True)
class GroundPriorConfig:
    """How SP uses the world model's ground (metres, degrees); SP given none (the node's
    ``ground_prior_level`` None, or SP called alone) keeps the column walk's ground.

    min_range_m:  only returns at least this far (range from the sensor) are checked;
                  nearer, the rows lie close enough for the column walk alone.
    above_m:      a ground return more than this above the expected ground is not ground:
                  above a curb or a rut, below the hits of a 32-beam sensor on a low rock or
                  a bush far out (its rows lie 0.7 m apart at 30 m, so the one row that hits
                  a 0.8 m rock hits it 0.1-0.7 m up); higher, those rocks and bushes and the
                  lower returns of parked cars stay ground. The price: a person far out is
                  now and then seen first by the legs alone (and called a rock or a bush).
    object_margin_m: a return more than ``above_m`` plus this above the expected ground makes
                  the segment that holds it an object, however low it stands over the ground
                  below it in its column (level 4 returns segments under
                  ``min_object_height_m`` to the ground): far out, a column's last ground
                  returns are often the object's own lower returns, and its height measured
                  from them too small (the one row on a bush at 35 m stands 0.9 m over the
                  terrain and 0.3 m over its column's ground). The margin keeps out the top
                  of a steep bank, which stands about ``above_m`` over the lowest cell beside
                  it raised by the slope.
    on_ground_m, on_ground_share, on_ground_below_m: a segment standing less than
                  ``on_ground_below_m`` over the ground below it in its column, with at least
                  ``on_ground_share`` of its returns within
                  ``on_ground_m`` of the ground the map holds at their places, is terrain the
                  column walk misjudged and goes back to the ground (:func:`on_known_ground`):
                  the top of a bank or a crest seen past a dip, where the column's ground,
                  continued from before the dip, lies under the terrain. Not when its row
                  shows it standing (:func:`sp.ground.raised_in_rows`): the map may have
                  fused a low object's own returns as ground before. Taller segments are
                  never taken back: a car seen only by its roof over nearer cars may lie on
                  cells the map took for ground.
    on_ground_min_range_m: the marking's own nearest range (m): near, the map knows the
                  terrain best, and the column walk misjudges a fold there as it does a
                  crest far out.
    span_m, span_rise_m: a ground return (at least ``min_range_m`` away) in a cell whose
                  returns seen so far span more than ``span_m`` in height, standing more than
                  ``span_rise_m`` over the lowest of them, makes its segment an object
                  (module docstring). A 0.4 m cell of terrain sloping 20 degrees spans 0.15 m;
                  the one row on a 0.35-1.2 m rock spans its face over a few sweeps. 0.3 m,
                  not 0.5 m (development seeds): on the open world's seeds 21-39 misses 221
                  -> 183 of 2015 box-frames with no false positive either way (the returns it
                  adds were all on true objects: rocks and bushes 0.35-0.7 m high, which the
                  former span never saw their faces reach); default world misses 128 -> 116
                  of 4596; the village's 894 -> 891 and false positives 2304 -> 2288; the car
                  park's misses 3129 -> 3088 and false positives 5346 ->
                  5538 (the lowest returns of parked cars make a second, low segment beside
                  the car's, tracked as a second object now and then; MOTA 0.886 -> 0.884);
                  0.25 m added false positives on the terrain's own folds.
    low_body_m, low_rise_m: ... and in a cell whose returns span at most ``low_body_m``,
                  the face of a body lower than that (a rock, a bush), a return more than
                  ``low_rise_m`` over the lowest is on that face too: as the range grows one
                  row's hits sink down the face sweep after sweep, and without it they fell
                  back to the ground once under ``span_rise_m``, so a rock passed by was
                  never hit often enough to be confirmed. Cells of a car, a person or a wall
                  span more and keep ``span_rise_m`` (their ground beside the body, 0.1-0.2 m
                  over the lowest return, would be taken for it). Development seeds, against
                  ``span_rise_m`` alone: default world misses 116 -> 78 of 4596 (false
                  positives 49 -> 47); open world (21-39) 183 -> 154 of 2015, none; car park
                  misses 3088 -> 3026, false positives 5538 -> 5580 (MOTA 0.8837 ->
                  0.8838); village false positives 2288 -> 2363 (MOTA 0.8744 -> 0.8720): a
                  parked car's rim cells span less than the car and give its lowest returns
                  a segment of their own, now and then tracked as a second object.
                  ``span_rise_m`` 0.1 m in every cell found about as many (default 116 -> 75,
                  open 183 -> 154) but gave the car park 906 more false positives (0.15 m:
                  285), its cars' ground beside them taken for their bodies.
    radius_m:     the expected ground at a point is the lowest known ground within this
                  distance of it, each cell raised by ``slope_deg`` over its distance (a slope
                  is not taken for an object; a car's roof is judged against the ground
                  beside it, not the roof the map may have fused as ground when it saw
                  nothing lower).
    """

    min_range_m: float = 15.0
    above_m: float = 0.5
    object_margin_m: float = 0.2
    on_ground_m: float = 0.2
    on_ground_share: float = 0.9
    on_ground_below_m: float = 1.0
    on_ground_min_range_m: float = 0.0
    span_m: float = 0.3
    span_rise_m: float = 0.2
    low_body_m: float = 0.8
    low_rise_m: float = 0.1
    radius_m: float = 2.0
    slope_deg: float = 15.0

    def __post_init__(self) -> None:
        if not (self.min_range_m >= 0 and self.above_m > 0 and self.radius_m >= 0):
            raise GroundPriorError(
                f"ground prior min_range_m {self.min_range_m}, above_m {self.above_m}, "
                f"radius_m {self.radius_m}: need >= 0, > 0, >= 0"
            )
        if not (
            self.on_ground_m >= 0
            and 0 < self.on_ground_share <= 1
            and self.on_ground_min_range_m >= 0
        ):
            raise GroundPriorError(
                f"ground prior on_ground_m {self.on_ground_m}, on_ground_share "
                f"{self.on_ground_share}, on_ground_min_range_m {self.on_ground_min_range_m}: "
                "need >= 0, in (0, 1], >= 0"
            )
        if not self.object_margin_m >= 0:
            raise GroundPriorError(
                f"ground prior object_margin_m {self.object_margin_m} is not >= 0"
            )
        if not (self.low_body_m >= 0 and self.low_rise_m >= 0):
            raise GroundPriorError(
                f"ground prior low_body_m {self.low_body_m}, low_rise_m {self.low_rise_m}: "
                "need >= 0, >= 0"
            )
        if not (self.span_m > 0 and self.span_rise_m >= 0):
            raise GroundPriorError(
                f"ground prior span_m {self.span_m}, span_rise_m {self.span_rise_m}: need > 0, >= 0"
            )
        if not 0 <= self.slope_deg < 80:
            raise GroundPriorError(f"ground prior slope_deg {self.slope_deg} is not in [0, 80)")


@dataclass(frozen=True)
class GroundPrior:
    """Ground heights the world model expects (module docstring for the grid convention).

    z_m:          (n, n) float world z of the ground (m), NaN unknown; toroidal storage.
    origin_cell:  (ix0, iy0) the window's lowest cell.
    resolution_m: cell edge (m).
    z_min_m, z_max_m: (n, n) float world z of the lowest and highest returns seen in each
                  cell (m), NaN none, same storage; None: not known (no span test).
    """

    z_m: np.ndarray
    origin_cell: tuple[int, int]
    resolution_m: float
    z_min_m: np.ndarray | None = None
    z_max_m: np.ndarray | None = None

    def __post_init__(self) -> None:
        z = np.asarray(self.z_m)
        if z.ndim != 2 or z.shape[0] != z.shape[1] or z.shape[0] < 1:
            raise GroundPriorError(f"ground prior grid has shape {z.shape}; needs (n, n)")
        if not self.resolution_m > 0:
            raise GroundPriorError(f"ground prior resolution_m {self.resolution_m} is not > 0")
        if (self.z_min_m is None) != (self.z_max_m is None):
            raise GroundPriorError("ground prior needs both z_min_m and z_max_m, or neither")
        for name in ("z_min_m", "z_max_m"):
            a = getattr(self, name)
            if a is not None and np.shape(a) != z.shape:
                raise GroundPriorError(
                    f"ground prior {name} has shape {np.shape(a)}; needs {z.shape} as z_m"
                )

    def lowest_around(self, radius_m: float) -> np.ndarray:
        """(n, n) float32 toroidal grid: the lowest known height in the square of (2k + 1)^2
        cells around each cell (k = ``radius_m`` // resolution), wrapping over the storage's
        edge (+inf where none known). For a cell at least k cells inside the window it is a
        lower bound of the ground expected there (:func:`above_prior`)."""
        k = int(radius_m // self.resolution_m)
        z = np.asarray(self.z_m, dtype=np.float32)
        z = np.where(np.isnan(z), np.float32(np.inf), z)
        if k == 0:
            return z
        import cv2

        padded = np.pad(z, k, mode="wrap")
        low = cv2.erode(padded, np.ones((2 * k + 1, 2 * k + 1), np.uint8))
        return low[k:-k, k:-k]


@numba.njit(cache=True, nogil=True)
def _lowest_near(z, cx, cy, ix0, iy0, off_x, off_y, rise):  # pragma: no cover
    """The lowest of (height + rise) over the window's known cells at cell (cx, cy) plus each
    offset (K,): z (n, n) toroidal heights, NaN unknown; NaN when none is known."""
    n = z.shape[0]
    best = np.nan
    for q in range(off_x.shape[0]):
        nx, ny = cx + off_x[q], cy + off_y[q]
        if ix0 <= nx < ix0 + n and iy0 <= ny < iy0 + n:
            v = z[ny % n, nx % n] + rise[q]
            if v == v and not v >= best:
                best = v
    return best


#: :func:`above_prior` codes: a ground return the prior leaves ground, one above the ground it
#: expects (not ground), one that makes its segment an object (``object_margin_m``).
GROUND, ABOVE, OBJECT = 0, 1, 2


def above_prior(
    xyz_w: np.ndarray,
    range_m: np.ndarray,
    ground: np.ndarray,
    prior: GroundPrior,
    config: GroundPriorConfig,
) -> np.ndarray:
    """(H, W) int8 code of each pixel: ``ABOVE`` for the ``ground`` pixels (H, W) bool at range
    ``range_m`` (H, W) m of at least ``min_range_m`` whose world point ``xyz_w`` (H, W, 3) m
    lies more than ``above_m`` above the ground ``prior`` expects there (module docstring:
    the lowest known cell within ``radius_m``, raised by ``slope_deg`` over its distance),
    ``OBJECT`` for those more than ``above_m + object_margin_m`` above it, or in a cell whose
    returns span more than ``span_m`` and more than ``span_rise_m`` over its lowest, or more
    than ``low_rise_m`` where they span at most ``low_body_m`` (when the prior knows the
    cells' lowest and highest returns), ``GROUND`` elsewhere."""
    obj = config.above_m + config.object_margin_m
    args = _kernel_args(xyz_w, range_m, ground, prior, config, config.min_range_m, obj)
    if prior.z_min_m is None or prior.z_max_m is None:
        lo = hi = np.empty((0, 0), dtype=np.float32)
    else:
        lo, hi = np.asarray(prior.z_min_m), np.asarray(prior.z_max_m)
    spans = (config.span_m, config.span_rise_m, config.low_body_m, config.low_rise_m)
    return _above_prior_kernel(*args, lo, hi, *map(float, spans))


def on_known_ground(
    xyz_w: np.ndarray,
    range_m: np.ndarray,
    valid: np.ndarray,
    prior: GroundPrior,
    config: GroundPriorConfig,
) -> np.ndarray:
    """(H, W) bool: the ``valid`` (H, W) bool pixels at range ``range_m`` (H, W) m of at least
    ``on_ground_min_range_m`` whose world point ``xyz_w`` (H, W, 3) m lies within ``on_ground_m`` of
    the ground ``prior`` holds in its own cell, where that cell's height is itself ground by
    :func:`above_prior` (a parked car's body far out, which the map fused as ground where it
    saw nothing lower, stands above the ground known beside it and is not trusted)."""
    near_m = config.on_ground_min_range_m
    args = _kernel_args(xyz_w, range_m, valid, prior, config, near_m, config.on_ground_m)
    return _on_known_kernel(*args)


def _kernel_args(
    xyz_w: np.ndarray,
    range_m: np.ndarray,
    mask: np.ndarray,
    prior: GroundPrior,
    config: GroundPriorConfig,
    min_range_m: float,
    limit_m: float,
) -> tuple:
    """The arguments of the compiled passes, in their order: the pixels, the prior's grid and
    its pruning square, the pass's nearest range and thresholds (``limit_m`` its own) and the
    cell offsets."""
    res = float(prior.resolution_m)
    slope_tan = float(np.tan(np.radians(config.slope_deg)))
    return (
        np.ascontiguousarray(xyz_w, dtype=np.float64),
        np.ascontiguousarray(range_m),
        np.ascontiguousarray(mask, dtype=np.bool_),
        prior.lowest_around(config.radius_m),
        np.asarray(prior.z_m),
        int(prior.origin_cell[0]),
        int(prior.origin_cell[1]),
        res,
        float(min_range_m),
        float(config.above_m),
        float(limit_m),
        int(config.radius_m // res),
        *_offsets(res, config.radius_m, slope_tan),
    )


def _offsets(
    res_m: float, radius_m: float, slope_tan: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The cell offsets (K,) int64 x and y whose centres lie within ``radius_m`` of a cell's
    centre (cells of ``res_m``), and the rise (K,) m allowed over each (``slope_tan`` x its
    distance)."""
    k = int(radius_m // res_m)
    dx, dy = np.meshgrid(np.arange(-k, k + 1), np.arange(-k, k + 1))
    d = res_m * np.hypot(dx, dy).ravel()
    near = d <= radius_m
    return dx.ravel()[near].astype(np.int64), dy.ravel()[near].astype(np.int64), slope_tan * d[near]


@numba.njit(cache=True, nogil=True)
def _surely_not_above(zp, cx, cy, low, n, ix0, iy0, k):  # pragma: no cover
    """Whether height ``zp`` is not above the ground expected at cell (cx, cy), shown by the
    dilated square ``low`` alone (:meth:`GroundPrior.lowest_around`, a lower bound of it for
    cells at least ``k`` inside the window; nearer the edge the square wraps, so never)."""
    inner = ix0 + k <= cx < ix0 + n - k and iy0 + k <= cy < iy0 + n - k
    return inner and not zp > low[cy % n, cx % n]


@numba.njit(cache=True, nogil=True)
def _expected_at(cx, cy, z, memo, ix0, iy0, off_x, off_y, rise):  # pragma: no cover
    """The ground expected at cell (cx, cy) (:func:`_lowest_near`; NaN when nothing is known
    near), remembered in ``memo`` (n, n) (inf: not computed) for cells of the window."""
    n = z.shape[0]
    if not (ix0 <= cx < ix0 + n and iy0 <= cy < iy0 + n):
        return _lowest_near(z, cx, cy, ix0, iy0, off_x, off_y, rise)
    e = memo[cy % n, cx % n]
    if e == np.inf:
        e = _lowest_near(z, cx, cy, ix0, iy0, off_x, off_y, rise)
        memo[cy % n, cx % n] = e
    return e


@numba.njit(cache=True, nogil=True)
def _above_prior_kernel(  # pragma: no cover
    xyz_w, range_m, ground, low, z, ix0, iy0, res, min_range, above, obj, k, off_x, off_y, rise,
    z_lo, z_hi, span, span_rise, low_body, low_rise,
):  # fmt: skip
    """:func:`above_prior` pixel by pixel. Most far ground is ground: where the dilated
    square shows it (:func:`_surely_not_above`) the exact expected ground is not needed.
    ``z_lo``, ``z_hi``: the cells' lowest and highest returns, (0, 0) when not known."""
    H, W = ground.shape
    n = z.shape[0]
    spans = z_lo.shape[0] == n
    out = np.zeros((H, W), dtype=np.int8)
    memo = np.empty((0, 0))
    for i in range(H):
        for j in range(W):
            if not ground[i, j] or not range_m[i, j] >= min_range:
                continue
            zp = xyz_w[i, j, 2] - above
            cx = np.int64(np.floor(xyz_w[i, j, 0] / res))
            cy = np.int64(np.floor(xyz_w[i, j, 1] / res))
            if spans and ix0 <= cx < ix0 + n and iy0 <= cy < iy0 + n:
                lo = z_lo[cy % n, cx % n]
                # NaN (nothing seen) compares False
                spread = z_hi[cy % n, cx % n] - lo
                over_lo = xyz_w[i, j, 2] - lo
                on_low_face = spread <= low_body and over_lo > low_rise
                if spread > span and (over_lo > span_rise or on_low_face):
                    out[i, j] = OBJECT
                    continue
            if _surely_not_above(zp, cx, cy, low, n, ix0, iy0, k):
                continue
            if memo.shape[0] == 0:
                memo = np.full((n, n), np.inf)
            e = _expected_at(cx, cy, z, memo, ix0, iy0, off_x, off_y, rise)
            # NaN (nothing known near) compares False
            out[i, j] = OBJECT if xyz_w[i, j, 2] - obj > e else (ABOVE if zp > e else GROUND)
    return out


@numba.njit(cache=True, nogil=True)
def _on_known_kernel(  # pragma: no cover
    xyz_w, range_m, valid, low, z, ix0, iy0, res, min_range, above, tol, k, off_x, off_y, rise
):
    """:func:`on_known_ground` pixel by pixel; a cell's own height is judged as
    :func:`_above_prior_kernel` judges a return."""
    H, W = valid.shape
    n = z.shape[0]
    out = np.zeros((H, W), dtype=np.bool_)
    memo = np.empty((0, 0))
    for i in range(H):
        for j in range(W):
            if not valid[i, j] or not range_m[i, j] >= min_range:
                continue
            cx = np.int64(np.floor(xyz_w[i, j, 0] / res))
            cy = np.int64(np.floor(xyz_w[i, j, 1] / res))
            if not (ix0 <= cx < ix0 + n and iy0 <= cy < iy0 + n):
                continue
            cz = z[cy % n, cx % n]
            if not abs(xyz_w[i, j, 2] - cz) <= tol:  # NaN (unknown) compares False
                continue
            if _surely_not_above(cz - above, cx, cy, low, n, ix0, iy0, k):
                out[i, j] = True
                continue
            if memo.shape[0] == 0:
                memo = np.full((n, n), np.inf)
            e = _expected_at(cx, cy, z, memo, ix0, iy0, off_x, off_y, rise)
            out[i, j] = not cz - above > e
    return out
