"""Recording and replay: MCAP sessions that Foxglove and the ``mcap`` tools open.

- :mod:`.encoding`: values to messages and back (foxglove RawImage/CompressedImage, JSON)
- :mod:`.writer`: the writer (a :class:`Writer`): its threads and per-stream counters, and
  the same writer in a process of its own (the recorder's default), laid out like ``workers/``
- :mod:`.split`: when a recording starts a new file (``--split-size``, ``--split-duration``)
- :mod:`.session`: session folders and the metadata a recording carries
- :mod:`.report`: the per-stream table after a recording
- :mod:`.reader`: ``info``, damage-tolerant reading and the replay message stream; :mod:`.repair`:
  a damaged file rewritten whole (``flowrt info --repair``)
- :mod:`.decoding`: every MCAP encoding back into values (:mod:`.images` for image messages of
  ROS and Foxglove, :mod:`.plain` for the rest), whoever wrote the file
- :mod:`.rosbag2`: rosbag2 folders (MCAP or SQLite3 storage) read like sessions, and their
  ``metadata.yaml`` written; :mod:`.ros2_profile`: values as ROS 2 messages (``--profile ros2``)

The runtime never imports this package; the ``recorder`` and ``replay`` nodes and the CLI do.
"""

from .encoding import Decoder as Decoder
from .report import RecordingReport as RecordingReport
from .report import StreamReport as StreamReport
from .report import build_report as build_report
from .report import nominal_rates as nominal_rates
from .report import report_table as report_table
from .session import check_writable as check_writable
from .session import new_session as new_session
from .split import SplitPolicy as SplitPolicy
from .split import parse_duration as parse_duration
from .split import parse_size as parse_size
from .writer import ProcessRecordingWriter as ProcessRecordingWriter
from .writer import RecordingWriter as RecordingWriter
from .writer import StreamCounters as StreamCounters
from .writer import Writer as Writer

__all__ = [
    "Decoder",
    "ProcessRecordingWriter",
    "RecordingReport",
    "RecordingWriter",
    "SplitPolicy",
    "StreamCounters",
    "StreamReport",
    "Writer",
    "build_report",
    "check_writable",
    "new_session",
    "nominal_rates",
    "parse_duration",
    "parse_size",
    "report_table",
]
