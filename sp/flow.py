"""Image flow by pyramid correlation, with recursive estimation (reference 001, 4.5.6 Level 1
Filtering, Figure 41; 4.5.5 Pyramids of Scale).

* :func:`correlation_flow` is the dense, windowed form of :func:`maps.pyramid.register` (the
  same pyramids and the same 9-offset search with a parabola peak fit): at every pixel
  the normalised correlation over a ``window_px`` square is evaluated at the 9 offsets zero and
  plus or minus one pixel around the current flow, on each pyramid level from coarse to fine,
  the best offset moves the flow, and a parabola through the 3x3 values gives the sub-pixel
  peak (4.5.5). All pixels are done at once with box filters.
* :class:`ImageFlow` runs the loop of Figure 41 over a sequence: the predicted image
  ``I*(x + dx, y + dy, t) = I(x, y, t - 1)``, the correlation offset between predicted and
  observed image as the pixel flow error, a per-pixel recursive (Kalman) update of the flow,
  and the blend with list, surface and object flow where those exist:
  ``dx/dt = c1 dx/dt(pixel) + c2 dx/dt(list) + c3 dx/dt(surface) + c4 dx/dt(object)``,
  ``c1 + c2 + c3 + c4 = 1``. The difference image ``I - I*`` is kept for later levels.

Flow is (H, W, 2) float32 ``(dx, dy)`` in pixels per frame at the pixels of the earlier image:
``next[y + dy, x + dx] ~= prev[y, x]`` (the convention of OpenCV and KITTI); rates in px/s are
flow divided by the frame interval (4.5.5: ``dx/dt = Dx / Dt``). Numpy core with OpenCV box
filters, remapping and resizing.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from core.errors import EngineError
from maps.pyramid import build_pyramid

MIN_COARSE_PX = 24  # the coarsest level keeps at least this many pixels a side


class FlowError(EngineError, ValueError):
    """Images or flows of the wrong size or dtype, or an impossible configuration."""


@dataclass(frozen=True)
class FlowConfig:
    """Image-flow settings (defaults in one place).

    levels:            pyramid levels; 0 picks as many as keep the coarsest level at least
                       max(24, 2 window_px + 2) px a side.
    window_px:         side of the square correlation window at every level (odd).
    steps_per_level:   9-offset correlation steps at each level (each moves up to 1 px).
    finest_level:      the finest pyramid level correlated (0 = full size); the flow is then
                       scaled up bilinearly (as OpenCV's DIS does with its finest scale).
    coarse_radius_px:  at the coarsest level every offset within this radius (at most a
                       quarter of that level's size) is tried: the search's reach there; 1 gives
                       the plain 9 offsets.
    smooth_px:         median filter applied to the flow after each level (odd, 0 for none).
    fill_px, min_confidence: pixels whose correlation peak is below min_confidence take the
                       confidence-weighted mean flow of a fill_px square around them.
    process_noise_px:  per-frame standard deviation of flow change (recursive filter Q).
    measurement_noise_px: standard deviation of a fully confident correlation offset (R).
    gate_sigma:        measurements further than this many standard deviations from the
                       prediction are rejected as false matches.
    """

    levels: int = 0
    window_px: int = 11
    steps_per_level: int = 1
    finest_level: int = 1
    coarse_radius_px: int = 12
    smooth_px: int = 5
    fill_px: int = 31
    min_confidence: float = 0.6
    process_noise_px: float = 1.0
    measurement_noise_px: float = 0.5
    gate_sigma: float = 3.0

    def __post_init__(self) -> None:
        if self.window_px < 3 or self.window_px % 2 == 0:
            raise FlowError(f"window_px must be odd and >= 3, got {self.window_px}")
        if self.smooth_px not in (0, 1, 3, 5):
            raise FlowError(f"smooth_px must be 0, 1, 3 or 5, got {self.smooth_px}")
        if self.steps_per_level < 1 or self.levels < 0:
            raise FlowError(
                f"steps_per_level >= 1 and levels >= 0 needed, got {self.steps_per_level}, "
                f"{self.levels}"
            )


def _gray(image: np.ndarray, name: str) -> np.ndarray:
    a = np.asarray(image)
    if a.ndim == 3 and a.shape[2] == 3 and a.dtype.kind in "fiu":
        a = a.astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)
    if a.ndim != 2 or a.dtype.kind not in "fiu":
        raise FlowError(
            f"{name} must be an (H, W) or (H, W, 3) numeric image, got {a.shape} {a.dtype}"
        )
    return a.astype(np.float32, copy=False)


def _n_levels(shape: tuple[int, int], config: FlowConfig) -> int:
    n, size = 1, min(shape)
    least = max(MIN_COARSE_PX, 2 * config.window_px + 2)
    while size // 2 >= least and (config.levels == 0 or n < config.levels):
        size //= 2
        n += 1
    return n


_EPS = 1e-3  # added to local standard deviations (intensity units) before dividing


def _blur(a: np.ndarray, window: int, dst: np.ndarray | None = None) -> np.ndarray:
    """Mean over a ``window`` square around each pixel (edges reflected)."""
    return cv2.blur(a, (window, window), dst=dst, borderType=cv2.BORDER_REFLECT)


def _stats(a: np.ndarray, window: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Local mean, standard deviation and 1 / (standard deviation + eps) over the window."""
    mean = _blur(a, window)
    var = cv2.subtract(_blur(cv2.multiply(a, a), window), cv2.multiply(mean, mean))
    std = cv2.sqrt(cv2.max(var, 0.0))
    return mean, std, cv2.divide(1.0, cv2.add(std, _EPS))


class _Level:
    """One pyramid level of the earlier image with its local statistics and pixel grid."""

    def __init__(self, a: np.ndarray, window: int) -> None:
        self.a, self.window = a, window
        self.mean, self.std, self.inv_std = _stats(a, window)
        h, w = a.shape
        self.grid_x, self.grid_y = np.meshgrid(
            np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32)
        )

    def warp(self, b: np.ndarray, fx: np.ndarray, fy: np.ndarray) -> np.ndarray:
        """``out[y, x] = b[y + fy, x + fx]`` (bilinear, edges replicated)."""
        return cv2.remap(
            b,
            cv2.add(self.grid_x, fx),
            cv2.add(self.grid_y, fy),
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        )

    def correlate(self, b: np.ndarray, radius: int) -> tuple[np.ndarray, np.ndarray]:
        """Local normalised correlation of the level's image with ``b`` shifted by every
        ``(dy, dx)`` within ``radius`` (``b[y + dy, x + dx]``), as an (H, 2r+1, 2r+1, W)
        volume indexed ``[y, dy + r, dx + r, x]``, and the (H, W) local standard deviation of
        ``b``.

        All offsets and pixels at once: in the (H, K, W) layout the stack of products is one
        image of H rows for the box filter down the columns and one of H K rows for the box
        filter along the rows, so two calls filter every offset."""
        h, w = self.a.shape
        n = 2 * radius + 1
        b_mean, b_std, b_inv = _stats(b, self.window)
        pad = (radius,) * 4
        pb, pm, pi = (cv2.copyMakeBorder(x, *pad, cv2.BORDER_REPLICATE) for x in (b, b_mean, b_inv))

        def stack(image: np.ndarray) -> np.ndarray:  # (h, n, n, w) view of shifted copies
            return np.lib.stride_tricks.sliding_window_view(image, (h, w)).transpose(2, 0, 1, 3)

        a = self.a[:, None, None, :]
        vol = np.multiply(stack(pb), a, out=np.empty((h, n, n, w), np.float32))
        border = cv2.BORDER_REFLECT
        cv2.blur(
            vol.reshape(h, n * n * w),
            (1, self.window),
            dst=vol.reshape(h, n * n * w),
            borderType=border,
        )
        cv2.blur(
            vol.reshape(h * n * n, w),
            (self.window, 1),
            dst=vol.reshape(h * n * n, w),
            borderType=border,
        )
        vol -= stack(pm) * self.mean[:, None, None, :]
        vol *= stack(pi)
        vol *= self.inv_std[:, None, None, :]
        return vol, b_std


def _nine_offset_step(vol: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """From the (H, 3, 3, W) correlations at the 9 offsets: the move (dx, dy) per pixel, the
    best offset or, where the centre is best, the sub-pixel peak of a parabola through the
    centre row and column; and the peak correlation."""
    peak = vol.max(axis=(1, 2))
    eq = vol == peak[:, None, None, :]
    centre = eq[:, 1, 1]
    up, down = eq[:, 0].any(axis=1), eq[:, 2].any(axis=1)
    left, right = eq[:, :, 0].any(axis=1), eq[:, :, 2].any(axis=1)
    dy = down.astype(np.float32) - up
    dx = right.astype(np.float32) - left
    c = vol[:, 1, 1]
    for d, lo, hi in ((dy, vol[:, 0, 1], vol[:, 2, 1]), (dx, vol[:, 1, 0], vol[:, 1, 2])):
        den = lo - 2.0 * c + hi
        with np.errstate(invalid="ignore", divide="ignore"):
            s = np.clip(np.where(den < -1e-6, 0.5 * (lo - hi) / den, 0.0), -0.5, 0.5)
        np.copyto(d, s.astype(np.float32), where=centre)
    return dx, dy, peak


def _wide_search(level: _Level, b: np.ndarray, radius: int) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel, the integer offset (dx, dy) within ``radius`` with the highest local
    correlation: where the search starts, at the coarsest level only (small images)."""
    vol, _ = level.correlate(b, radius)
    h, n, _, w = vol.shape
    best = np.ascontiguousarray(vol.reshape(h, n * n, w).transpose(0, 2, 1)).argmax(axis=2)
    return (best % n - radius).astype(np.float32), (best // n - radius).astype(np.float32)


def correlation_flow(
    prev: np.ndarray,
    next_: np.ndarray,
    config: FlowConfig | None = None,
    init_flow: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Dense flow from ``prev`` to ``next_`` by coarse-to-fine windowed correlation.

    prev, next_: (H, W) grey or (H, W, 3) colour images of the same size.
    init_flow:   optional (H, W, 2) predicted flow to start from (px per frame).
    Returns flow (H, W, 2) float32 ``(dx, dy)`` with ``next_[y + dy, x + dx] ~= prev[y, x]``,
    and confidence (H, W) float32 in 0..1 (the correlation peak, 0 where there is no texture).
    """
    cfg = config or FlowConfig()
    a0, b0 = _gray(prev, "prev image"), _gray(next_, "next image")
    if a0.shape != b0.shape:
        raise FlowError(f"image sizes differ: prev {a0.shape}, next {b0.shape}")
    if min(a0.shape) < cfg.window_px:
        raise FlowError(
            f"correlation window {cfg.window_px} px is larger than the image {a0.shape}"
        )
    if init_flow is not None and np.shape(init_flow) != (*a0.shape, 2):
        raise FlowError(f"init_flow has shape {np.shape(init_flow)}, want {(*a0.shape, 2)}")
    n = _n_levels(a0.shape, cfg)
    pa, pb = build_pyramid(a0, n), build_pyramid(b0, n)
    h, w = pa[-1].shape
    if init_flow is None:
        fx, fy = np.zeros((h, w), np.float32), np.zeros((h, w), np.float32)
    else:
        small = cv2.resize(init_flow, (w, h), interpolation=cv2.INTER_AREA) / 2 ** (n - 1)
        fx, fy = np.ascontiguousarray(small[..., 0]), np.ascontiguousarray(small[..., 1])
    finest = min(cfg.finest_level, n - 1)
    for lev in range(n - 1, finest - 1, -1):
        a, b = pa[lev], pb[lev]
        if fx.shape != a.shape:
            size = (a.shape[1], a.shape[0])
            fx = 2.0 * cv2.resize(fx, size, interpolation=cv2.INTER_LINEAR)
            fy = 2.0 * cv2.resize(fy, size, interpolation=cv2.INTER_LINEAR)
        # Wide search at the coarsest level only, kept within a quarter of its size.
        radius = min(cfg.coarse_radius_px, min(a.shape) // 4) if lev == n - 1 else 1
        fx, fy, conf = _refine_level(_Level(a, cfg.window_px), b, fx, fy, cfg, radius)
    if finest > 0:
        size, scale = (a0.shape[1], a0.shape[0]), float(2**finest)
        fx = scale * cv2.resize(fx, size, interpolation=cv2.INTER_LINEAR)
        fy = scale * cv2.resize(fy, size, interpolation=cv2.INTER_LINEAR)
        conf = cv2.resize(conf, size, interpolation=cv2.INTER_LINEAR)
    return np.stack([fx, fy], axis=-1), conf


def _refine_level(
    level: _Level,
    b: np.ndarray,
    fx: np.ndarray,
    fy: np.ndarray,
    cfg: FlowConfig,
    radius: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Correlation steps at one level (9 offsets each, after a wide search where the search
    starts), then weak pixels filled from their neighbours and a median filter."""
    if radius > 1:
        dx, dy = _wide_search(level, level.warp(b, fx, fy), radius)
        fx, fy = fx + dx, fy + dy
    for _ in range(cfg.steps_per_level):
        vol, b_std = level.correlate(level.warp(b, fx, fy), 1)
        dx, dy, peak = _nine_offset_step(vol)
        fx, fy = fx + dx, fy + dy
    floor = 1e-2 * (float(np.abs(level.a).max()) + 1e-6)
    textured = cv2.min(level.std, b_std) > floor
    conf = np.where(textured, np.clip(peak, 0.0, 1.0), 0.0).astype(np.float32)
    fx, fy = _fill_weak(fx, fy, conf, cfg)
    if cfg.smooth_px > 1:
        fx, fy = cv2.medianBlur(fx, cfg.smooth_px), cv2.medianBlur(fy, cfg.smooth_px)
    return fx, fy, conf


def _fill_weak(
    fx: np.ndarray, fy: np.ndarray, conf: np.ndarray, cfg: FlowConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Where the correlation is weak, take the flow of the surrounding pixels (4.5.6: "the
    flow rate sometimes can be inferred from the flow of surrounding pixels"): a confidence-
    weighted mean over ``fill_px`` replaces pixels whose confidence is below ``min_confidence``.
    """
    c2 = cv2.multiply(conf, conf)
    wgt = cv2.multiply(c2, c2)
    den = cv2.add(_blur(wgt, cfg.fill_px), 1e-12)
    weak = conf < cfg.min_confidence
    out = []
    for f in (fx, fy):
        mean = cv2.divide(_blur(cv2.multiply(wgt, f), cfg.fill_px), den)
        out.append(np.where(weak, mean, f).astype(np.float32))
    return out[0], out[1]


def warp_forward(image: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """The predicted image ``I*(x + dx, y + dy) = I(x, y)`` for a flow at ``image``'s pixels,
    approximated by sampling ``I`` at ``(x - dx, y - dy)`` (exact for locally constant flow)."""
    I = _gray(image, "image")
    if np.shape(flow) != (*I.shape, 2):
        raise FlowError(f"flow has shape {np.shape(flow)}, the image {I.shape}")
    f = np.asarray(flow, np.float32)
    return _Level(I, 3).warp(I, -f[..., 0], -f[..., 1])


@dataclass
class EntityFlow:
    """Flow known from a higher level (list, surface or object entities): (H, W, 2) px per
    frame and its confidence (H, W) in 0..1 (0 where the pixel belongs to no such entity)."""

    flow: np.ndarray
    confidence: np.ndarray


@dataclass
class FlowState:
    """What :class:`ImageFlow` knows after a cycle (arrays (H, W) or (H, W, 2) float32).

    flow:        best estimate of the flow from the previous frame to this one (px per frame).
    variance:    its per-pixel variance, px^2 (the recursive filter's P).
    confidence:  correlation confidence of this cycle's pixel flow measurement.
    predicted:   the image predicted for this cycle, ``I*(t)`` (None on the first cycle).
    difference:  observed minus predicted, ``I(t) - I*(t)`` (None on the first cycle).
    rate_px_s:   flow divided by the frame interval, (dx/dt, dy/dt) in px/s.
    """

    t_ns: int
    image: np.ndarray
    flow: np.ndarray
    variance: np.ndarray
    confidence: np.ndarray
    predicted: np.ndarray | None = None
    difference: np.ndarray | None = None
    rate_px_s: np.ndarray | None = None
    weights: dict[str, float] = field(default_factory=dict)


class ImageFlow:
    """Recursive image-flow estimation over a sequence of frames (Figure 41).

    Each :meth:`update` predicts the image from the previous image and flow, measures the
    flow error by correlating prediction and observation, updates the flow per pixel with a
    Kalman gain ``K = P / (P + R)`` (``R`` grows as the correlation confidence falls), and
    blends in higher-level entity flows with weights proportional to their confidences.
    """

    def __init__(self, config: FlowConfig | None = None) -> None:
        self.config = config or FlowConfig()
        self.state: FlowState | None = None

    def predicted_image(self) -> np.ndarray | None:
        """``I*(t + 1)``: the last image moved along the current flow (None before a frame)."""
        if self.state is None:
            return None
        return warp_forward(self.state.image, self.state.flow)

    def update(
        self,
        image: np.ndarray,
        t_ns: int,
        list_flow: EntityFlow | None = None,
        surface_flow: EntityFlow | None = None,
        object_flow: EntityFlow | None = None,
    ) -> FlowState:
        I = _gray(image, "image")
        cfg = self.config
        s = self.state
        if s is not None and s.image.shape != I.shape:
            raise FlowError(
                f"image at t_ns={t_ns} has shape {I.shape}, the sequence {s.image.shape}"
            )
        if s is not None and t_ns <= s.t_ns:
            raise FlowError(f"image at t_ns={t_ns} is not after the previous one at {s.t_ns}")
        if s is None:
            zero = np.zeros((*I.shape, 2), np.float32)
            big = np.full(I.shape, 1e6, np.float32)
            self.state = FlowState(t_ns, I, zero, big, np.zeros(I.shape, np.float32))
            return self.state
        predicted = warp_forward(s.image, s.flow)
        # Predict: constant flow, uncertainty grows by Q.
        f_pred, P = s.flow, s.variance + cfg.process_noise_px**2
        # Measure: the correlation offset between prediction and observation is the flow error.
        f_meas, conf = correlation_flow(s.image, I, cfg, init_flow=f_pred)
        R = cfg.measurement_noise_px**2 / np.maximum(conf, 1e-3) ** 2
        K = P / (P + R)
        # Gate: an innovation far outside its expected spread is a false match, not news.
        innovation2 = np.sum((f_meas - f_pred) ** 2, axis=-1)
        K = np.where(innovation2 > cfg.gate_sigma**2 * (P + R), 0.0, K).astype(np.float32)
        f_pixel = f_pred + K[..., None] * (f_meas - f_pred)
        P = (1 - K) * P
        flow, weights = _blend(f_pixel, 1.0 / (1.0 + P), list_flow, surface_flow, object_flow)
        dt_s = (t_ns - s.t_ns) * 1e-9
        self.state = FlowState(
            t_ns=t_ns,
            image=I,
            flow=flow,
            variance=P.astype(np.float32),
            confidence=conf,
            predicted=predicted,
            difference=I - predicted,
            rate_px_s=(flow / dt_s).astype(np.float32),
            weights=weights,
        )
        return self.state


def _blend(
    f_pixel: np.ndarray,
    c_pixel: np.ndarray,
    *entity_flows: EntityFlow | None,
) -> tuple[np.ndarray, dict[str, float]]:
    """``f = sum c_i f_i / sum c_i`` over pixel, list, surface and object flow (the weights
    normalised per pixel so that c1 + c2 + c3 + c4 = 1); returns the mean weight of each."""
    names = ("pixel", "list", "surface", "object")
    flows, confs = [f_pixel], [c_pixel.astype(np.float32)]
    used = ["pixel"]
    for name, e in zip(names[1:], entity_flows, strict=True):
        if e is None:
            continue
        if e.flow.shape != f_pixel.shape or e.confidence.shape != f_pixel.shape[:2]:
            raise FlowError(
                f"{name} flow has shape {e.flow.shape} / confidence {e.confidence.shape}, "
                f"want {f_pixel.shape} / {f_pixel.shape[:2]}"
            )
        flows.append(np.asarray(e.flow, np.float32))
        confs.append(np.clip(np.asarray(e.confidence, np.float32), 0.0, 1.0))
        used.append(name)
    total = np.sum(confs, axis=0)
    total = np.where(total > 0, total, 1.0)
    weights = [c / total for c in confs]
    flow = sum(w[..., None] * f for w, f in zip(weights, flows, strict=True))
    return flow.astype(np.float32), {n: float(w.mean()) for n, w in zip(used, weights, strict=True)}
