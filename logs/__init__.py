"""Sensor logs: the log message data model (:mod:`logs.types`), readers and writers.

``open_log(path)`` reads any supported log as time-ordered frames (:mod:`logs.source`);
``McapLogWriter`` writes frames as an MCAP file of ROS 2 messages (:mod:`logs.mcap_log`).
"""

from logs.mcap_log import Compression, McapLogSource, McapLogWriter, McapWriterConfig
from logs.source import (
    SUPPORTED_FORMATS,
    LogInfo,
    LogSource,
    TopicInfo,
    format_log_info,
    open_log,
)
from logs.types import (
    CameraFrame,
    Frame,  # deprecated alias of LogMessage, for users' code
    GroundTruthPose,
    ImuFrame,
    LadarScan,
    LogError,
    LogMessage,
    ObjectBoxes,
    OdometryFrame,
    ReadStats,
    TransformFrame,
)

__all__ = [
    "SUPPORTED_FORMATS",
    "CameraFrame",
    "Compression",
    "Frame",
    "GroundTruthPose",
    "ImuFrame",
    "LadarScan",
    "LogError",
    "LogInfo",
    "LogMessage",
    "LogSource",
    "McapLogSource",
    "McapLogWriter",
    "McapWriterConfig",
    "ObjectBoxes",
    "OdometryFrame",
    "ReadStats",
    "TopicInfo",
    "TransformFrame",
    "format_log_info",
    "open_log",
]
