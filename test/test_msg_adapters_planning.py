"""msg_adapters.planning: goals and predicted paths in metres on the wire, bit-exact mm round trips, clear refusals."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from test_msg_adapters import F32, PAIRS, STAMPS, same_bits, through_cdr  # noqa: E402  (the shared round-trip helpers)

import msg_adapters as ma
from t42_transfer.conventions import CONTROL_PERIOD_NS, FRAME_ID


@given(xy=PAIRS, stamp=STAMPS)
def test_goal_round_trip_is_bit_exact(xy, stamp):
    msg = through_cdr(ma.goal_msg(xy, stamp))
    assert msg.__msgtype__ == ma.POINT_STAMPED and msg.header.frame_id == FRAME_ID
    assert same_bits(ma.goal_xy_mm(msg), xy)
    assert ma.stamp_to_ns(msg.header.stamp) == stamp


def test_goal_is_si_metres():
    msg = ma.goal_msg([12.5, -80.0], 7)
    assert (msg.point.x, msg.point.y, msg.point.z) == (0.0125, -0.08, 0.0)


@pytest.mark.parametrize("field", ["x", "y", "z"])
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_goal_refuses_non_finite_coordinates(field, bad):
    msg = ma.goal_msg([1.0, 2.0], 0)
    setattr(msg.point, field, bad)
    with pytest.raises(ValueError, match="non-finite"):
        ma.goal_xy_mm(msg)


@pytest.mark.parametrize("frame_id, x, match", [("map", 1.0, "frame 'map'"), (FRAME_ID, 1e300, "float32 range")])
def test_goal_refuses_other_frames_and_float32_overflow(frame_id, x, match):
    msg = ma.goal_msg([1.0, 2.0], 0)
    msg.header.frame_id, msg.point.x = frame_id, x
    with pytest.raises(ValueError, match=match):
        ma.goal_xy_mm(msg)


@given(xy=arrays(np.float32, st.tuples(st.integers(0, 8), st.just(2)), elements=F32),
       start=st.integers(0, 2**31 * 10**9 - 10**10), period=st.integers(1, 10**9))
def test_path_round_trip_is_bit_exact_with_stamps_one_period_apart(xy, start, period):
    msg = through_cdr(ma.path_msg(xy, start, period))
    assert msg.__msgtype__ == ma.PATH and msg.header.frame_id == FRAME_ID
    out = ma.path_xy_mm(msg)
    assert out.shape == xy.shape and same_bits(out, xy)
    assert ma.stamp_to_ns(msg.header.stamp) == start
    assert [ma.stamp_to_ns(p.header.stamp) for p in msg.poses] == [start + k * period for k in range(len(xy))]
    assert all(p.header.frame_id == FRAME_ID for p in msg.poses)


def test_path_defaults_to_the_control_period_and_metres():
    msg = ma.path_msg(np.array([[1000.0, 0.0], [0.0, 2000.0]]), 0)
    assert ma.stamp_to_ns(msg.poses[1].header.stamp) == CONTROL_PERIOD_NS
    assert (msg.poses[0].pose.position.x, msg.poses[1].pose.position.y) == (1.0, 2.0)


def test_path_refuses_bad_shapes_values_periods_and_frames():
    with pytest.raises(ValueError, match=r"\[N, 2\]"):
        ma.path_msg(np.zeros((3, 4)), 0)
    with pytest.raises(ValueError, match="non-finite"):
        ma.path_msg(np.array([[0.0, math.nan]]), 0)
    with pytest.raises(ValueError, match="period"):
        ma.path_msg(np.zeros((2, 2)), 0, 0)
    msg = ma.path_msg(np.zeros((2, 2)), 0)
    msg.header.frame_id = "map"
    with pytest.raises(ValueError, match="path is in frame 'map'"):
        ma.path_xy_mm(msg)
    msg.header.frame_id = FRAME_ID
    msg.poses[1].header.frame_id = "map"
    with pytest.raises(ValueError, match="object pose is in frame 'map'"):
        ma.path_xy_mm(msg)
