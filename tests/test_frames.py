"""Geometry shared by all floors: poses, quaternions, interpolation, time."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from core import geometry as F

angles = st.floats(-np.pi, np.pi, allow_nan=False)


@given(angles, st.floats(-1.5, 1.5), angles)
def test_rpy_round_trip(roll, pitch, yaw):
    R = F.rpy_to_matrix(roll, pitch, yaw)
    assert np.allclose(F.rpy_to_matrix(*F.matrix_to_rpy(R)), R, atol=1e-9)


@given(angles, st.floats(-1.5, 1.5), angles)
def test_quaternion_round_trip(roll, pitch, yaw):
    R = F.rpy_to_matrix(roll, pitch, yaw)
    q = F.matrix_to_quat(R)
    assert q[3] >= 0 and np.isclose(np.linalg.norm(q), 1.0)
    assert np.allclose(F.quat_to_matrix(q), R, atol=1e-9)


def test_inverse_and_transform():
    T = F.se3(F.rpy_to_matrix(0.1, -0.2, 1.3), [1.0, -2.0, 0.5])
    assert np.allclose(F.se3_inverse(T) @ T, np.eye(4))
    p = np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 3.0]])
    back = F.transform_points(F.se3_inverse(T), F.transform_points(T, p))
    assert np.allclose(back, p)


def test_interpolate_pose_ends_and_middle():
    T0 = F.se3(F.rot_z(0.0), [0, 0, 0])
    T1 = F.se3(F.rot_z(1.0), [2, 0, 0])
    mid = F.interpolate_pose(T0, T1, 0.5)
    assert np.isclose(F.yaw_of(mid), 0.5) and np.allclose(mid[:3, 3], [1, 0, 0])
    many = F.interpolate_pose(T0, T1, np.array([0.0, 1.0]))
    assert np.allclose(many[0], T0) and np.allclose(many[1], T1)


def test_bad_inputs_are_named():
    with pytest.raises(F.GeometryError, match="quaternion"):
        F.quat_to_matrix([0, 0, 0, 0])
    bad = np.eye(4)
    bad[0, 0] = 2.0
    with pytest.raises(F.GeometryError, match="T_world_body"):
        F.check_pose(bad, "T_world_body")


def test_time_conversions():
    assert F.seconds_to_ns(1.5) == 1_500_000_000
    assert F.ns_to_seconds(2_000_000_000) == 2.0


@given(angles, st.floats(-1.5, 1.5), angles)
def test_rotvec_round_trip(roll, pitch, yaw):
    R = F.rpy_to_matrix(roll, pitch, yaw)
    rv = F.rotvec_of(R)
    assert np.linalg.norm(rv) <= np.pi + 1e-9
    assert np.allclose(F.rotvec_to_matrix(rv), R, atol=1e-8)


def test_rotvec_known_values_and_half_turn():
    assert np.allclose(F.rotvec_of(F.rot_z(0.3)), [0.0, 0.0, 0.3])
    assert np.allclose(F.rotvec_of(np.eye(3)), 0.0)
    half = F.rotvec_of(F.rot_x(np.pi))
    assert np.isclose(np.linalg.norm(half), np.pi) and np.allclose(np.abs(half), [np.pi, 0, 0])
