"""msg_adapters.camera: Image and CameraInfo <-> numpy, in both message kits, through CDR and back (issue 21)."""

from __future__ import annotations

import sys

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import CameraInfo, Image

from msg_adapters import (
    RCLPY,
    ROSBAGS,
    TYPESTORE,
    camera_info_calibration,
    camera_info_msg,
    image_array,
    image_msg,
    stamp_to_ns,
)
from msg_adapters.camera import CAMERA_INFO, IMAGE

RNG = np.random.default_rng(3)


@pytest.mark.parametrize("encoding, shape, dtype", [
    ("mono8", (4, 5), np.uint8), ("bgr8", (4, 5, 3), np.uint8), ("rgb8", (3, 7, 3), np.uint8),
    ("rgba8", (2, 3, 4), np.uint8), ("mono16", (4, 5), np.uint16),
])
@pytest.mark.parametrize("kit", [ROSBAGS, RCLPY], ids=["rosbags", "rclpy"])
def test_images_round_trip_through_cdr(kit, encoding, shape, dtype) -> None:
    image = RNG.integers(0, np.iinfo(dtype).max, size=shape, dtype=dtype)
    msg = image_msg(image, encoding, 1_500_000_000_123, "cam", kit)
    if kit is RCLPY:
        msg = deserialize_message(serialize_message(msg), Image)
    else:
        msg = TYPESTORE.deserialize_cdr(TYPESTORE.serialize_cdr(msg, IMAGE), IMAGE)
    got = image_array(msg)
    assert got.dtype == dtype and got.shape == shape and np.array_equal(got, image)
    assert stamp_to_ns(msg.header.stamp) == 1_500_000_000_123 and msg.header.frame_id == "cam"


def test_padded_rows_and_views_are_read_as_they_are() -> None:
    image = RNG.integers(0, 255, size=(6, 8, 3), dtype=np.uint8)
    msg = image_msg(image[:, ::-1], "bgr8", 1, "", RCLPY)  # a flipped view is packed
    padded = np.zeros((6, 32), np.uint8)
    padded[:, :24] = image.reshape(6, 24)
    msg.step, msg.data = 32, padded.tobytes()
    assert np.array_equal(image_array(msg), image)


@pytest.mark.parametrize("change, message", [
    ({"encoding": "yuv422"}, "encoding 'yuv422'"),
    ({"step": 10}, "shorter than a row"),
    ({"height": 5}, "expected step 24 x height 5"),
    ({"width": 0}, "empty"),
    ({"width": 100_000}, "over"),
])
def test_images_whose_fields_describe_no_image_are_refused(change, message) -> None:
    msg = image_msg(np.zeros((4, 8, 3), np.uint8), "bgr8", 1, "", RCLPY)
    for key, value in change.items():
        setattr(msg, key, value)
    with pytest.raises(ValueError, match=message):
        image_array(msg)


def test_wide_pixels_of_the_other_byte_order_and_mismatched_arrays_are_refused() -> None:
    msg = image_msg(np.zeros((2, 2), np.uint16), "mono16", 1, "", RCLPY)
    msg.is_bigendian = int(sys.byteorder == "little")
    with pytest.raises(ValueError, match="other byte order"):
        image_array(msg)
    with pytest.raises(ValueError, match="is not 'rgb8'"):
        image_msg(np.zeros((2, 2), np.uint8), "rgb8", 1, "")
    with pytest.raises(ValueError, match="is not 'mono8'"):
        image_msg(np.zeros((2, 2), np.float32), "mono8", 1, "")


@pytest.mark.parametrize("kit", [ROSBAGS, RCLPY], ids=["rosbags", "rclpy"])
def test_camera_infos_round_trip_through_cdr(kit) -> None:
    k = np.array([[500.0, 0, 319.5], [0, 501.0, 239.5], [0, 0, 1]])
    msg = camera_info_msg(640, 480, k, [0.1, -0.2, 0.001, 0.002, 0.03], 7, "cam", kit=kit)
    if kit is RCLPY:
        msg = deserialize_message(serialize_message(msg), CameraInfo)
    else:
        msg = TYPESTORE.deserialize_cdr(TYPESTORE.serialize_cdr(msg, CAMERA_INFO), CAMERA_INFO)
    got = camera_info_calibration(msg)
    assert (got.width, got.height, got.distortion_model) == (640, 480, "plumb_bob")
    np.testing.assert_array_equal(got.k, k)
    np.testing.assert_array_equal(got.d, [0.1, -0.2, 0.001, 0.002, 0.03])
    np.testing.assert_array_equal(np.asarray(msg.p).reshape(3, 4)[:, :3], k)
    np.testing.assert_array_equal(np.asarray(msg.r), np.eye(3).reshape(-1))
    assert camera_info_msg(640, 480, k, np.zeros(8), 7, "cam").distortion_model == "rational_polynomial"
    with pytest.raises(ValueError, match="9 values"):
        camera_info_msg(640, 480, np.eye(2), [], 7, "cam")
