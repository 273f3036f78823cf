"""The ``capture`` node kind: cameras, files and synthetic scenes into the frame pool."""

from .node import Capture as Capture
