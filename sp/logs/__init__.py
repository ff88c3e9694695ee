"""Sensor logs: the frame data model (:mod:`sp.logs.types`), readers and writers."""

from sp.logs.types import (
    CameraFrame,
    Frame,
    GroundTruthPose,
    ImuFrame,
    LadarScan,
    LogError,
    ObjectBoxes,
    OdometryFrame,
    ReadStats,
    TransformFrame,
)

__all__ = [
    "CameraFrame",
    "Frame",
    "GroundTruthPose",
    "ImuFrame",
    "LadarScan",
    "LogError",
    "ObjectBoxes",
    "OdometryFrame",
    "ReadStats",
    "TransformFrame",
]
