"""ROS and Foxglove image messages into pixels: every documented encoding, row padding and
byte order (flowrt/recording/images.py), and an IDL schema decoded without ROS 2."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from mcap.records import Schema

from flowrt.recording.decoding import MessageDecoder
from flowrt.recording.images import pixels_of, stamp_ns

IMAGE = "sensor_msgs/msg/Image"


def _msg(encoding: str, px: np.ndarray, step: int | None = None, big: bool = False) -> dict:
    h, w = px.shape[:2]
    row = px.reshape(h, -1).view(np.uint8) if px.dtype != np.uint8 else px.reshape(h, -1)
    step = step or row.shape[1]
    data = np.zeros((h, step), np.uint8)
    data[:, : row.shape[1]] = row
    return {
        "header": {"stamp": {"sec": 5, "nanosec": 7}, "frame_id": "c"},
        "height": h,
        "width": w,
        "encoding": encoding,
        "is_bigendian": int(big),
        "step": step,
        "data": data.tobytes(),
    }


def test_direct_encodings_and_padded_rows() -> None:
    rng = np.random.default_rng(1)
    bgr = rng.integers(0, 255, (4, 5, 3), dtype=np.uint8)
    px, fmt = pixels_of(IMAGE, _msg("bgr8", bgr, step=20))  # 5 bytes of padding per row
    assert fmt == "BGR"
    assert np.array_equal(px, bgr)
    px, fmt = pixels_of(IMAGE, _msg("rgb8", bgr))
    assert (fmt, np.array_equal(px, bgr)) == ("RGB", True)
    rgba = rng.integers(0, 255, (4, 5, 4), dtype=np.uint8)
    px, fmt = pixels_of(IMAGE, _msg("rgba8", rgba))
    assert fmt == "RGB"
    assert np.array_equal(px, rgba[:, :, :3])
    grey = rng.integers(0, 255, (4, 5), dtype=np.uint8)
    assert np.array_equal(pixels_of(IMAGE, _msg("mono8", grey))[0], grey)


def test_mono16_in_either_byte_order() -> None:
    deep = np.array([[1, 256, 65535], [4, 5, 1000]], dtype=np.uint16)
    little = pixels_of(IMAGE, _msg("mono16", deep.astype("<u2")))
    big = pixels_of(IMAGE, _msg("16UC1", deep.astype(">u2"), big=True))
    for px, fmt in (little, big):
        assert fmt == "GRAY"
        assert px.dtype == np.uint16
        assert np.array_equal(px, deep)


def test_bayer_and_yuv_become_bgr() -> None:
    bgr = np.zeros((8, 8, 3), np.uint8)
    bgr[:, :, 2] = 200  # red
    mosaic = np.zeros((8, 8), np.uint8)
    mosaic[0::2, 0::2] = 200  # RGGB: red on even rows and columns
    px, fmt = pixels_of(IMAGE, _msg("bayer_rggb8", mosaic))
    assert fmt == "BGR"
    assert px[2:6, 2:6, 2].mean() > 150  # red, where the pattern says red
    assert px[2:6, 2:6, 0].mean() < 50
    yuv = cv2.cvtColor(bgr, cv2.COLOR_BGR2YUV)
    uyvy = np.zeros((8, 16), np.uint8)
    uyvy[:, 1::2] = yuv[:, :, 0]
    uyvy[:, 0::4] = yuv[:, 0::2, 1]
    uyvy[:, 2::4] = yuv[:, 0::2, 2]
    px, fmt = pixels_of(IMAGE, _msg("uyvy", uyvy.reshape(8, 8, 2)))
    assert fmt == "BGR"
    # OpenCV's UYVY decoding is studio-range: red comes back brighter, but red
    assert px[:, :, 2].min() > 150
    assert px[:, :, :2].max() < 30


def test_what_cannot_be_an_image_says_why() -> None:
    with pytest.raises(ValueError, match="unsupported image encoding '32FC1'"):
        pixels_of(IMAGE, _msg("32FC1", np.zeros((2, 2), np.uint8)))
    short = _msg("bgr8", np.zeros((4, 4, 3), np.uint8))
    short["data"] = short["data"][:10]
    with pytest.raises(ValueError, match="an image of 4 rows"):
        pixels_of(IMAGE, short)
    bad = {"format": "jpeg", "data": b"not a jpeg"}
    with pytest.raises(ValueError, match="cannot decode a 'jpeg' compressed image"):
        pixels_of("sensor_msgs/msg/CompressedImage", bad)


def test_stamps_of_every_family() -> None:
    assert stamp_ns({"header": {"stamp": {"sec": 2, "nanosec": 3}}}) == 2_000_000_003
    assert stamp_ns({"header": {"stamp": {"secs": 2, "nsecs": 3}}}) == 2_000_000_003
    assert stamp_ns({"timestamp": {"sec": 2, "nsec": 3}}) == 2_000_000_003
    assert stamp_ns({"header": {"stamp": {"sec": 0, "nanosec": 0}}}) is None
    assert stamp_ns({"data": b""}) is None


IDL = """module geometry_msgs {
  module msg {
    struct Point {
      double x;
      double y;
      double z;
    };
  };
};
"""


def test_an_idl_schema_decodes() -> None:
    schema = Schema(
        id=1,
        name="geometry_msgs/msg/Point",
        encoding="ros2idl",
        data=("=" * 80 + "\nIDL: geometry_msgs/msg/Point\n" + IDL).encode(),
    )
    data = b"\x00\x01\x00\x00" + np.array([1.0, 2.5, -3.0], "<f8").tobytes()
    assert MessageDecoder().decode("cdr", schema, data).value == {"x": 1.0, "y": 2.5, "z": -3.0}
