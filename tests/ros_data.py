"""Test data in other tools' formats, written by their own libraries (not by flowrt).

- :func:`write_bag`: a rosbag2 by ``rosbags``' ``Writer`` (MCAP or SQLite3 storage) with
  ``sensor_msgs/msg/Image`` (bgr8 and mono8), ``CompressedImage`` (jpeg) and
  ``geometry_msgs/msg/Twist``.
- :func:`clip_frames`: the first frames of the repository's rendered clip, and the clip
  file they were read from (for ``capture file:``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

SAMPLE = Path(__file__).resolve().parents[1] / "graphs" / "sample.avi"
T0 = 1_700_000_000_000_000_000  # ns: the bag's first log time
STAMP_LEAD = 5_000_000  # ns: each image's header.stamp is this much before its log time


def clip_frames(folder: Path, n: int, source: Path = SAMPLE) -> tuple[Path, list[np.ndarray]]:
    """The first ``n`` frames of ``source`` (graphs/sample.avi) written as a clip of their
    own (MJPG), and the frames as that clip reads back (what ``capture file:`` sees)."""
    import cv2

    src = cv2.VideoCapture(str(source))
    frames = []
    while len(frames) < n:
        ok, img = src.read()
        assert ok, f"{source} is shorter than the test needs"
        frames.append(img)
    src.release()
    clip = folder / "clip.avi"
    h, w = frames[0].shape[:2]
    out = cv2.VideoWriter(str(clip), cv2.VideoWriter_fourcc(*"MJPG"), 25, (w, h))
    for img in frames:
        out.write(img)
    out.release()
    back = cv2.VideoCapture(str(clip))
    read = []
    while True:
        ok, img = back.read()
        if not ok:
            break
        read.append(img)
    back.release()
    assert len(read) == n
    return clip, read


def write_bag(
    path: Path,
    storage: str,
    frames: list[np.ndarray],
    fps: float = 25.0,
    image_topic: str = "/camera/image_raw",
) -> Path:
    """A rosbag2 folder at ``path`` (``storage``: mcap | sqlite3) written by rosbags."""
    import cv2
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    image = ts.types["sensor_msgs/msg/Image"]
    compressed = ts.types["sensor_msgs/msg/CompressedImage"]
    header = ts.types["std_msgs/msg/Header"]
    time = ts.types["builtin_interfaces/msg/Time"]
    twist = ts.types["geometry_msgs/msg/Twist"]
    vector = ts.types["geometry_msgs/msg/Vector3"]
    plugin = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}[storage]
    with Writer(path, version=9, storage_plugin=plugin) as w:
        c_bgr = w.add_connection(image_topic, image.__msgtype__, typestore=ts)
        c_mono = w.add_connection("/camera/mono", image.__msgtype__, typestore=ts)
        c_jpeg = w.add_connection("/camera/compressed", compressed.__msgtype__, typestore=ts)
        c_cmd = w.add_connection("/cmd_vel", twist.__msgtype__, typestore=ts)
        for i, img in enumerate(frames):
            t = T0 + round(i * 1e9 / fps)
            s = t - STAMP_LEAD
            hd = header(stamp=time(sec=s // 10**9, nanosec=s % 10**9), frame_id="camera")
            h, wd = img.shape[:2]
            bgr = image(hd, h, wd, "bgr8", 0, wd * 3, np.ascontiguousarray(img).reshape(-1))
            w.write(c_bgr, t, ts.serialize_cdr(bgr, image.__msgtype__))
            grey = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
            mono = image(hd, h, wd, "mono8", 0, wd, grey.reshape(-1))
            w.write(c_mono, t, ts.serialize_cdr(mono, image.__msgtype__))
            ok, buf = cv2.imencode(".jpg", img)
            assert ok
            jpeg = compressed(hd, "jpeg", buf.reshape(-1))
            w.write(c_jpeg, t, ts.serialize_cdr(jpeg, compressed.__msgtype__))
            cmd = twist(vector(0.1 * i, 0.0, 0.0), vector(0.0, 0.0, -0.5))
            w.write(c_cmd, t, ts.serialize_cdr(cmd, twist.__msgtype__))
    return path
