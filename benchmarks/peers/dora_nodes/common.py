"""Shared helpers of the dora-rs side of the peer benchmark (run by ``dora run``)."""

import json
import os

import numpy as np

STAMP = np.dtype("<f8")


def write(path, data):
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        json.dump(data, f)
    os.replace(tmp, path)


def stamp_of(value):
    """The f8 in the first 8 bytes of a UInt8 arrow array (a zero-copy numpy view)."""
    return float(value.to_numpy(zero_copy_only=True)[:8].view(STAMP)[0])
