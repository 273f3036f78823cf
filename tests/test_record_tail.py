"""A recording killed mid-run has zeros, never stale bytes, after its last record (issue 26).

The direct-I/O writer reuses its 8 MiB buffer; its ``flush`` wrote the partial last block
with whatever the previous buffer held past the data, so a file killed after 8 MiB ended in
old records that stream readers (``McapStreamReader``, the Python stream reader) tried to
parse ("record content length ... too large") instead of seeing the end of a truncated file.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from flowrt.recording.directio import BUFFER, open_direct


@pytest.mark.parametrize("extra", [1, 100, 4095, 4097, 123_457])
def test_a_flushed_tail_after_a_buffer_wrap_is_zeros(tmp_path: Path, extra: int) -> None:
    f = open_direct(tmp_path / "x.mcap")
    if f is None:
        pytest.skip("no direct I/O on this file system")
    try:
        f.write(b"\xab" * BUFFER)  # one whole buffer of records: the buffer now holds 0xab
        f.write(b"\xcd" * extra)  # the next records, then a flush as the recorder does
        f.flush()
        data = (tmp_path / "x.mcap").read_bytes()
        end = BUFFER + extra
        assert data[BUFFER:end] == b"\xcd" * extra
        assert set(data[end:]) <= {0}, "stale bytes after the last record"
        assert len(data) - end < 4096
    finally:
        os.close(f.fileno())


@pytest.mark.slow
@pytest.mark.subprocess
@pytest.mark.node
def test_a_recording_killed_far_past_the_buffer_streams_through_mcap_core(
    tmp_path: Path,
) -> None:
    """``kill -9`` at ~5 s (tens of MiB, several buffers): @mcap/core's McapStreamReader and
    the Python stream reader read every complete record, and only padding is left."""
    import json
    import shutil
    import signal
    import subprocess
    import sys
    import time

    modules = os.environ.get("FLOWRT_NODE_MODULES")
    node = shutil.which("node")
    if not modules or node is None:
        pytest.skip("needs Node.js and FLOWRT_NODE_MODULES with @mcap/core (.ci/run installs)")
    repo = Path(__file__).resolve().parents[1]
    proc = subprocess.Popen(
        [sys.executable, "-m", "flowrt.cli", "record", "graphs/cambada.yaml", "-o",
         str(tmp_path), "--duration", "60", "--no-ui", "--no-display"],
        cwd=repo, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            files = list(tmp_path.glob("*/*.mcap"))
            if files and files[0].stat().st_size > 3 * BUFFER:
                break
            time.sleep(0.2)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    (path,) = tmp_path.glob("*/*.mcap")
    assert path.stat().st_size > 3 * BUFFER
    # ES modules resolve packages from the script's folder: run a copy beside node_modules
    script = Path(modules).parent / "mcap_stream.mjs"
    shutil.copyfile(repo / "tests" / "js" / "mcap_stream.mjs", script)
    r = subprocess.run(
        [node, str(script), str(path)],
        env=dict(os.environ, NODE_PATH=modules),
        cwd=Path(modules).parent,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0, r.stderr
    got = json.loads(r.stdout)
    assert got["messages"] > 100
    assert got["bytesRemaining"] < 4096  # only the zero padding of the last block

    from flowrt.recording.reader import scan

    info = scan(path)  # the Python stream reader, as flowrt info and replay read files
    assert not info.closed_cleanly
    assert info.messages >= got["messages"] - 50  # the same records, up to the last chunk
