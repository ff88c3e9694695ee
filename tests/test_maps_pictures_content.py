"""What the pictures show: the scale bar (its corner, length and label against the metres per
pixel), the legend strip (colour bar and value range), label overlays (exactly the labelled
cells, blended), and hill shading of planes against Lambert's law."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from maps.level import LevelConfig, MapLevel
from maps.pictures import (
    LEGEND_PX,
    NO_DATA_BGR,
    TEXT_BGR,
    colourise,
    hillshade,
    label_colours,
    render_layer,
    render_levels,
)
from maps.stack import MapStack


def _level(res: float = 1.0, size: int = 64, name: str = "t") -> MapLevel:
    level = MapLevel(LevelConfig(name, res, size, keep_tiles=False))
    level.move_to(np.array([0.0, 0.0]))
    return level


def _ramp(level: MapLevel, top: float) -> MapLevel:
    """Elevation rising north from 0 at window row 0 to ``top`` at the last row (exact)."""
    rows = np.repeat(np.arange(level.size, dtype=np.float64)[:, None], level.size, axis=1)
    level.set_window("elevation", (rows * top / (level.size - 1)).astype(np.float32))
    return level


def _bar_px(map_img: np.ndarray) -> int:
    """Length (px) of the scale bar in the map part of a picture: the documented white bar,
    4 rows ending 8 px above the bottom edge, starting 8 px from the left edge."""
    h = map_img.shape[0]
    white = (map_img == np.array(TEXT_BGR, dtype=np.uint8)).all(axis=-1)
    bottom = white[h - 12 :]  # the bar and what lies under it (nothing white)
    rows = np.nonzero(bottom.any(axis=1))[0] + h - 12
    assert rows.tolist() == list(range(h - 11, h - 7)), f"bar rows {rows.tolist()}"
    runs = {tuple(np.nonzero(white[r])[0].tolist()) for r in rows}
    assert len(runs) == 1, "the bar's rows differ"
    cols = np.array(runs.pop())
    assert cols[0] == 8 and (np.diff(cols) == 1).all(), f"bar columns {cols}"
    return len(cols)


def _label_px(map_img: np.ndarray, text: str) -> None:
    """The bar's label reads ``text``: the picture above the bar equals ``text`` drawn on the
    uniform no-data background (the level is empty) where the renderer puts it."""
    h = map_img.shape[0]
    want = np.empty_like(map_img)
    want[:] = NO_DATA_BGR
    cv2.putText(want, text, (8, h - 16), cv2.FONT_HERSHEY_SIMPLEX, 0.4, TEXT_BGR, 1)
    np.testing.assert_array_equal(map_img[: h - 12, :80], want[: h - 12, :80])


@pytest.mark.parametrize(
    ("res", "size", "scale", "length_m", "n_px"),
    [
        (1.0, 64, 2, 10.0, 20),  # 0.5 m/px, 128 px wide: a fifth is 12.8 m -> 10 m
        (0.5, 64, 4, 5.0, 40),  # 0.125 m/px, 256 px: 6.4 m -> 5 m
        (0.04, 256, 2, 2.0, 100),  # 0.02 m/px, 512 px: 2.048 m -> 2 m
        (4.0, 256, 1, 200.0, 50),  # 4 m/px, 256 px: 204.8 m -> 200 m
    ],
)
def test_scale_bar_length_matches_metres_per_pixel(
    res: float, size: int, scale: int, length_m: float, n_px: int
) -> None:
    img = render_layer(_level(res, size), "elevation", scale=scale)
    map_img = img[:-LEGEND_PX]
    assert map_img.shape[:2] == (size * scale, size * scale)
    assert (map_img[:-16, 80:] == NO_DATA_BGR).all()  # empty level: only the bar is drawn
    m_per_px = res / scale
    n = _bar_px(map_img)
    assert n == n_px
    assert n * m_per_px == pytest.approx(length_m)
    _label_px(map_img, f"{length_m:g} m")


def test_every_panel_of_render_levels_has_its_own_scale_bar() -> None:
    stack = MapStack()  # default levels: 0.04, 0.4, 4, 30 m cells, 256 cells a side
    img = render_levels(stack.levels, "elevation", panel_px=512)
    h = 512
    want = [(2.0, 100), (20.0, 100), (200.0, 100), (1000.0, 67)]  # 30 m / 2 px: 66.7 -> 67
    for i, (length_m, n_px) in enumerate(want):
        panel = img[:h, i * (512 + 4) : i * (512 + 4) + 512]
        assert _bar_px(panel) == n_px
        m_per_px = stack.levels[i].resolution_m / 2
        assert abs(n_px * m_per_px - length_m) <= m_per_px / 2
        _label_px(panel, f"{length_m:g} m")
        assert (img[:, i * 516 + 512 : i * 516 + 516] == 0).all()  # the gap between panels


def _legend(img: np.ndarray) -> np.ndarray:
    return img[-LEGEND_PX:]


def test_legend_shows_the_value_range_of_the_layer() -> None:
    low, high = _ramp(_level(), 1.0), _ramp(_level(), 50.0)  # same name and layer, other range
    a, b = render_layer(low, "elevation"), render_layer(high, "elevation")
    assert a.shape == (128 + LEGEND_PX, 128, 3)
    la, lb = _legend(a), _legend(b)
    w = max(16, a.shape[1] // 3)  # the documented colour bar: a third of the width
    bar = cv2.applyColorMap(np.linspace(0, 255, w).astype(np.uint8)[None], cv2.COLORMAP_TURBO)
    for strip in (la, lb):
        np.testing.assert_array_equal(strip[16:24, 4 : 4 + w], np.repeat(bar, 8, axis=0))
    diff = (la != lb).any(axis=-1)
    assert diff.any(), "two layers with different ranges have the same legend"
    assert not diff[:, : 4 + w].any()  # the title and colour bar agree; only the range text
    # the default range is the layer's finite min..max: the same legend as asking for it
    np.testing.assert_array_equal(la, _legend(render_layer(low, "elevation", value_range=(0, 1))))
    np.testing.assert_array_equal(
        lb, _legend(render_layer(high, "elevation", value_range=(0.0, 50.0)))
    )
    other = _legend(render_layer(high, "elevation", value_range=(0.0, 60.0)))
    assert (other != lb).any()
    # the range text itself: drawn on the black strip right of the colour bar, under the title
    want = np.zeros_like(lb)
    cv2.putText(want, "0 .. 50", (4 + w + 4, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.35, TEXT_BGR, 1)
    assert want[14:, 4 + w :].any()
    np.testing.assert_array_equal(lb[14:, 4 + w :], want[14:, 4 + w :])


def test_legend_colour_bar_follows_the_layer() -> None:
    level = _ramp(_level(), 5.0)
    level.set_window("slope", np.full((64, 64), 0.2, np.float32))
    level.set_window("class_id", np.full((64, 64), 3, np.int32))
    w = max(16, 128 // 3)
    elev = _legend(render_layer(level, "elevation"))[16:24, 4 : 4 + w]
    slope = _legend(render_layer(level, "slope"))[16:24, 4 : 4 + w]
    viridis = cv2.applyColorMap(np.linspace(0, 255, w).astype(np.uint8)[None], cv2.COLORMAP_VIRIDIS)
    np.testing.assert_array_equal(slope, np.repeat(viridis, 8, axis=0))
    assert (elev != slope).any()
    labels = _legend(render_layer(level, "class_id"))
    assert not labels[14:].any()  # label layers: a title only, no colour bar or range
    assert labels[:14].any()


def _labels(size: int, n: int, seed: int, forbid: np.ndarray | None = None) -> np.ndarray:
    """``n`` labelled cells (ids 0..n-1, so id 0 is used) off the scale bar's corner."""
    rng = np.random.default_rng(seed)
    ok = np.ones((size, size), bool)
    ok[:16, :40] = False  # window rows 0.. are the image bottom, where the scale bar is
    if forbid is not None:
        ok &= forbid < 0
    cells = rng.choice(np.flatnonzero(ok), size=n, replace=False)
    ids = np.full(size * size, -1, np.int64)
    ids[cells] = np.arange(n)
    return ids.reshape(size, size)


def _check_overlay(over: np.ndarray, plain: np.ndarray, ids: np.ndarray, scale: int) -> None:
    """Pixels that differ are exactly the labelled cells (north up, ``scale`` px a cell), and
    there the picture is the half-and-half blend of the plain picture and the id's colour."""
    lab = ids >= 0
    want = np.kron(lab[::-1], np.ones((scale, scale), bool))
    changed = (over[:-LEGEND_PX] != plain[:-LEGEND_PX]).any(axis=-1)
    np.testing.assert_array_equal(changed, want)
    np.testing.assert_array_equal(over[-LEGEND_PX:], plain[-LEGEND_PX:])
    colours = np.kron(label_colours(ids)[::-1], np.ones((scale, scale, 1), np.uint8))
    blend = (0.5 * plain[:-LEGEND_PX] + 0.5 * colours).astype(np.uint8)
    np.testing.assert_array_equal(over[:-LEGEND_PX][want], blend[want])


def test_overlay_colours_exactly_the_labelled_cells() -> None:
    level = _ramp(_level(), 8.0)
    classes = _labels(64, 150, seed=1)
    entities = _labels(64, 90, seed=2, forbid=classes)  # other cells than the classes
    level.set_window("class_id", classes.astype(np.int32))
    level.set_window("entity_id", entities)
    plain = render_layer(level, "elevation", scale=2)
    _check_overlay(render_layer(level, "elevation", scale=2, overlay="class_id"), plain, classes, 2)
    _check_overlay(
        render_layer(level, "elevation", scale=2, overlay="entity_id"), plain, entities, 2
    )
    # an overlay of a layer with no labels changes nothing
    bare = _ramp(_level(), 8.0)
    np.testing.assert_array_equal(render_layer(bare, "elevation", scale=2, overlay="class_id"),
                                  render_layer(bare, "elevation", scale=2))  # fmt: skip


def test_render_levels_overlays_every_panel() -> None:
    fine, coarse = _ramp(_level(1.0, 64, "fine"), 4.0), _ramp(_level(4.0, 32, "coarse"), 4.0)
    ids = {"fine": _labels(64, 80, seed=3), "coarse": _labels(32, 30, seed=4)}
    for lvl in (fine, coarse):
        lvl.set_window("class_id", ids[lvl.name].astype(np.int32))
    over = render_levels([fine, coarse], "elevation", panel_px=128, overlay="class_id")
    plain = render_levels([fine, coarse], "elevation", panel_px=128)
    assert over.shape == (128 + LEGEND_PX, 2 * (128 + 4), 3)
    for i, (lvl, scale) in enumerate(((fine, 2), (coarse, 4))):
        cols = slice(i * 132, i * 132 + 128)
        _check_overlay(over[:, cols], plain[:, cols], ids[lvl.name], scale)


def _lambert(a: float, b: float, az_deg: float, alt_deg: float) -> float:
    """Lambertian shade of the plane z = a x + b y under a sun at azimuth (clockwise from
    north) / altitude in degrees."""
    n = np.array([-a, -b, 1.0]) / np.sqrt(1.0 + a * a + b * b)
    az, alt = np.radians(az_deg), np.radians(alt_deg)
    sun = np.array([np.sin(az) * np.cos(alt), np.cos(az) * np.cos(alt), np.sin(alt)])
    return float(np.clip(n @ sun, 0.0, 1.0))


@pytest.mark.parametrize(
    ("a", "b", "az", "alt"),
    [
        (0.0, 0.5, 180.0, 30.0),
        (0.0, 0.5, 0.0, 30.0),
        (0.7, -0.2, 315.0, 45.0),
        (2.0, 0.0, 270.0, 10.0),
    ],
)
def test_hillshade_of_a_plane_follows_lamberts_law(
    a: float, b: float, az: float, alt: float
) -> None:
    res = 0.5
    rows, cols = np.indices((20, 24), dtype=np.float64)
    z = a * (cols * res) + b * (rows * res)  # window order: rows along +y (north)
    shade = hillshade(z, res, azimuth_deg=az, altitude_deg=alt)
    np.testing.assert_allclose(shade, _lambert(a, b, az, alt), atol=1e-9)


def test_hillshade_faces_and_unknown_cells() -> None:
    rows = np.indices((16, 16), dtype=np.float64)[0]
    up_north = rows * 0.5  # rises north: faces south
    south_sun = hillshade(up_north, 1.0, azimuth_deg=180.0).mean()
    north_sun = hillshade(up_north, 1.0, azimuth_deg=0.0).mean()
    assert south_sun > north_sun + 0.3
    holed = up_north.copy()
    holed[8, 8] = np.nan
    shade = hillshade(holed, 1.0)
    assert shade[8, 8] == 1.0  # no value: unshaded
    far = np.ones((16, 16), bool)
    far[6:11, 6:11] = False
    np.testing.assert_allclose(shade[far], hillshade(up_north, 1.0)[far], atol=1e-12)


def test_elevation_pictures_are_hill_shaded() -> None:
    """Two mirror planes with one value range hold the same colours; only the shading differs,
    so the one facing the default sun (north-west) is the brighter picture."""
    lit, dark = _level(), _level()
    rows, cols = np.indices((64, 64), dtype=np.float64)
    lit.set_window("elevation", (cols + rows[::-1]).astype(np.float32))  # rises SE: faces NW
    dark.set_window("elevation", (cols[:, ::-1] + rows).astype(np.float32))  # rises NW: faces SE
    a = render_layer(lit, "elevation", value_range=(0.0, 126.0))[:-LEGEND_PX, 40:]
    b = render_layer(dark, "elevation", value_range=(0.0, 126.0))[:-LEGEND_PX, 40:]
    assert a.astype(float).mean() > 1.3 * b.astype(float).mean()
    flat = colourise(np.ones((4, 4)), 0.0, 2.0, cv2.COLORMAP_TURBO)
    assert flat.shape == (4, 4, 3)
