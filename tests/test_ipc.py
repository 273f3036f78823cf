"""The process wire (flowrt/ipc.py), on a real socketpair: what workers and the recording
writer process rely on. No process: both ends live in this one."""

from __future__ import annotations

import pickle
import socket
from collections.abc import Iterator

import pytest

from flowrt.ipc import PICKLE, BlockingConn, Framer, frame, pack


@pytest.fixture
def pair() -> Iterator[tuple[socket.socket, socket.socket]]:
    a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
    yield a, b
    a.close()
    b.close()


def test_messages_split_anywhere_come_out_whole_and_in_order() -> None:
    msgs = [("open", {"path": "x"}), ("msg", 1, b"\0" * 70000), ("close",)]
    data = b"".join(pack(m) for m in msgs)
    framer = Framer()
    out: list[bytes] = []
    for i in range(0, len(data), 7):  # every message cut across many reads
        out += framer.feed(data[i : i + 7])
    assert [pickle.loads(m) for m in out] == msgs
    assert framer.rest() == b""


def test_a_framer_hands_a_partial_message_to_a_blocking_reader(
    pair: tuple[socket.socket, socket.socket],
) -> None:
    """The recorder reads on the loop, then its closer thread takes the socket over."""
    a, b = pair
    data = pack(("acks", [1], [], None)) + pack(("drained",))
    framer = Framer()
    first = framer.feed(data[:-3])
    assert [pickle.loads(m) for m in first] == [("acks", [1], [], None)]
    a.sendall(data[-3:])
    conn = BlockingConn(b, framer.rest())
    assert conn.recv_message() == ("drained",)


def test_blocking_conn_round_trip_and_the_end_of_file(
    pair: tuple[socket.socket, socket.socket],
) -> None:
    a, b = pair
    child, parent = BlockingConn(a), BlockingConn(b)
    assert parent.send_message(("call", 7, {"x": 1}))
    assert parent.send(pickle.dumps(("exit",), PICKLE))
    assert child.recv_message() == ("call", 7, {"x": 1})
    assert child.complete()  # the second is buffered already: no read needed
    assert child.recv_message() == ("exit",)
    b.close()
    assert child.recv() is None  # the other side is gone: None, not an exception
    assert not child.send_message(("late",))  # and a send says False


def test_frame_is_the_length_then_the_pickle() -> None:
    payload = pickle.dumps(("x",), PICKLE)
    assert frame(payload) == len(payload).to_bytes(4, "little") + payload
    assert pack(("x",)) == frame(payload)
