"""The ingest fast path (exact-symmetry shortcut, column-major copies, one contiguous Arrow
table per flush) refuses and keeps exactly what the plain definitions say."""

from __future__ import annotations

import numpy as np
import pytest

from kd_store import KDError, StateBatch
from kd_store.covariance import pack_checked, unpack_covariance
from kd_store.states import check_batch, rows_to_arrow


def _spd(rng: np.random.Generator, n: int) -> np.ndarray:
    A = rng.normal(size=(n, 6, 3))
    return A @ A.transpose(0, 2, 1) + 0.1 * np.eye(6)


def _batch(rng: np.random.Generator, n: int, frame: str = "world", **kw: object) -> StateBatch:
    q = rng.normal(size=(n, 4))
    fields: dict[str, object] = {
        "orientation_xyzw": q / np.linalg.norm(q, axis=1, keepdims=True),
        "velocity_xyz": rng.normal(size=(n, 3)),
        "covariance": _spd(rng, n),
        "orientation_var_rpy": rng.uniform(0, 1, (n, 3)),
    }
    fields.update(kw)
    return StateBatch(
        np.arange(n, dtype=np.int64), np.arange(n, dtype=np.int64) * 10, frame,
        rng.normal(size=(n, 3)), **fields,  # type: ignore[arg-type]
    )  # fmt: skip


def test_pack_checked_matches_definition() -> None:
    rng = np.random.default_rng(1)
    cov = _spd(rng, 50)
    cov[7, 4, 1] += 1e-12  # within tolerance: symmetric, not exactly
    cov21, scale, sym = pack_checked(cov.reshape(50, 36), 1e-9)
    assert sym
    np.testing.assert_array_equal(cov21, cov[:, *np.triu_indices(6)])
    np.testing.assert_allclose(unpack_covariance(cov21), cov, atol=1e-11)
    np.testing.assert_array_equal(scale, np.maximum(1.0, cov.diagonal(axis1=1, axis2=2).max(1)))
    cov[7, 4, 1] += 1e-3  # beyond tolerance
    assert not pack_checked(cov.reshape(50, 36), 1e-9)[2]


@pytest.mark.parametrize("value", [np.nan, np.inf])
def test_non_finite_lower_triangle_only_is_refused_as_not_finite(value: float) -> None:
    rng = np.random.default_rng(2)
    cov = _spd(rng, 20)
    cov[13, 5, 2] = value  # the packed upper triangle stays finite
    with pytest.raises(KDError, match=r"entity 13 at t_ns=130: covariance is not finite"):
        check_batch(_batch(rng, 20, covariance=cov), "test")


def test_checked_columns_are_copies_and_round_trip() -> None:
    rng = np.random.default_rng(3)
    b = _batch(rng, 30)
    c = check_batch(b, "test")
    for mine, theirs in (
        (c.position_xyz, b.position_xyz),
        (c.orientation_xyzw, b.orientation_xyzw),
        (c.velocity_xyz, b.velocity_xyz),
        (c.orientation_var_rpy, b.orientation_var_rpy),
        (c.cov21, b.covariance),
        (c.entity_id, b.entity_id),
    ):
        assert not np.shares_memory(mine, theirs)
    np.testing.assert_array_equal(c.position_xyz, b.position_xyz)
    np.testing.assert_array_equal(unpack_covariance(c.cov21), b.covariance)
    defaults = check_batch(StateBatch(b.entity_id, b.t_ns, "world", b.position_xyz), "test")
    np.testing.assert_array_equal(defaults.orientation_xyzw, np.tile([0.0, 0, 0, 1], (30, 1)))
    assert not defaults.cov21.any() and not defaults.velocity_xyz.any()


def test_rows_to_arrow_is_the_rows_of_every_chunk_in_order() -> None:
    rng = np.random.default_rng(4)
    sizes = ((5, "world"), (7, "odom"))
    chunks = [check_batch(_batch(rng, n, frame), "test") for n, frame in sizes]
    chunks.append(chunks[0].take(np.array([4, 0])))  # a gathered (row-major) chunk too
    table = rows_to_arrow(chunks)
    assert table.num_rows == 14
    assert table.column("frame").to_pylist() == ["world"] * 5 + ["odom"] * 7 + ["world"] * 2
    for col, name, k in (("x", "position_xyz", 0), ("qw", "orientation_xyzw", 3)):
        want = np.concatenate([getattr(c, name)[:, k] for c in chunks])
        np.testing.assert_array_equal(table.column(col).to_numpy(), want)
    back = chunks[0].from_arrow(table)
    assert [c.frame for c in back] == ["world", "odom"]
    np.testing.assert_array_equal(back[0].cov21, np.concatenate([chunks[0].cov21, chunks[2].cov21]))
    np.testing.assert_array_equal(back[1].orientation_var_rpy, chunks[1].orientation_var_rpy)


def test_finite_values_whose_sum_overflows_are_kept() -> None:
    pos = np.array([[1e308, 1e308, -1e308], [0.0, 1.0, 2.0]])
    c = check_batch(StateBatch(np.arange(2), np.arange(2), "world", pos), "test")
    np.testing.assert_array_equal(c.position_xyz, pos)
    pos[1, 2] = np.inf
    with pytest.raises(KDError, match=r"entity 1 at t_ns=1: position_xyz is not finite"):
        check_batch(StateBatch(np.arange(2), np.arange(2), "world", pos), "test")
