"""Numpy oracles of the fast ROS message decoding of :mod:`logs.ros_decode` (tests only).

:func:`decode_pointcloud2_reference` is the straightforward form of
:func:`logs.ros_decode.decode_pointcloud2` (copy the points, stack the fields, cast), and
:func:`boxes_reference` of ``FrameAssembler._boxes`` (an array per box). The engine's forms
must give the same frames (see ``tests/test_logs_decode_speed.py``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from logs.ros_decode import (
    FrameAssembler,
    _cloud_layout,
    _scan_of,
    _velocities_returns,
    _xyz,
    stamp_ns,
)
from logs.types import LadarScan, ObjectBoxes, ReadStats


def decode_pointcloud2_reference(msg: Any, topic: str, stats: ReadStats) -> LadarScan:
    """The straightforward form of :func:`logs.ros_decode.decode_pointcloud2` (copy, stack,
    cast), the reference its frames are compared with.

    Per-point time from a field ``t`` or ``offset_time`` (integer ns after the stamp) or
    ``time`` (float seconds after the stamp); ring from ``ring`` (or ``laser_number``).
    """
    fields, dtype, points = _cloud_layout(msg)
    cloud = points.copy().view(dtype).reshape(-1)
    xyz = np.stack([cloud["x"], cloud["y"], cloud["z"]], axis=1).astype(np.float32)
    finite = np.isfinite(xyz).all(axis=1)
    n_bad = int(finite.size - finite.sum())
    if n_bad:
        stats.dropped_nonfinite_points += n_bad
        cloud, xyz = cloud[finite], xyz[finite]
    return _scan_of(msg, topic, cloud, xyz, fields)


def boxes_reference(self: FrameAssembler, msg: Any, topic: str) -> ObjectBoxes:
    """:meth:`FrameAssembler._boxes` as it was, with an array per box (a method: tests put it
    in place of ``_boxes`` on the class)."""
    dets = msg.detections
    m = len(dets)
    quats = np.array(
        [[d.bbox.center.orientation.__getattribute__(c) for c in "xyzw"] for d in dets]
    ).reshape(m, 4)
    x, y, z, w = quats.T
    velocities, n_returns = _velocities_returns(self._velocities.pop(topic, None), m)
    return ObjectBoxes(
        t_ns=stamp_ns(msg.header),
        frame_id=msg.header.frame_id,
        ids=np.array([self._track_id(d.id) for d in dets], dtype=np.int64),
        classes=[d.results[0].hypothesis.class_id if d.results else "" for d in dets],
        centers=np.array([_xyz(d.bbox.center.position) for d in dets]).reshape(m, 3),
        sizes=np.array([_xyz(d.bbox.size) for d in dets]).reshape(m, 3),
        yaws=np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z)),
        velocities=velocities,
        topic=topic,
        n_returns=n_returns,
    )
