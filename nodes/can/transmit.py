"""What the CAN node sends: an input value checked and kept, a message encoded into its bytes.

Pure steps over one message's :class:`~.state.MessageState`; the node decides when (its cycle
grid) and says what went wrong (its log and alerts)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from flowrt.analysis.can_frames import fd_payload_length

from .dbc import EncodeProblem, checksum, encode_signals
from .state import MessageState
from .values import CanMessage


def take(st: MessageState, value: Any) -> str:
    """Keep ``value`` (a mapping of signals, or a ``CanMessage``) as the message's next value;
    the problem in words (counted in ``bad_inputs``, the value not kept), or "" when kept."""
    signals = value.signals if isinstance(value, CanMessage) else value
    problem = ""
    if not isinstance(signals, Mapping):
        problem = f"expected a mapping of signal values, got {type(value).__name__}"
    else:
        if not st.signal_names:
            st.signal_names = frozenset(s.name for s in st.dbc.signals)
        unknown = sorted(set(signals) - st.signal_names)
        if unknown:
            problem = f"no signal {', '.join(map(repr, unknown))}"
    if problem:
        st.bad_inputs += 1
        return problem
    if not st.have_value:
        st.value = {s.name: (s.initial if s.initial is not None else 0) for s in st.dbc.signals}
    st.value.update(signals)
    st.encoded = None
    st.have_value = True
    st.fresh = True
    return ""


def encode(st: MessageState, fd_enabled: bool) -> bytes | bytearray:
    """The frame's payload for the message's value, its counter advanced and its checksum set;
    raises :class:`EncodeProblem` (the value does not fit, or an FD message on a classic
    node). A message without counter or checksum keeps its bytes until the value changes."""
    if st.encoded is not None:
        return st.encoded
    opts = st.opts
    values = st.value
    if opts.counter is not None:
        sig = st.dbc.get_signal_by_name(opts.counter)
        values = {**values, opts.counter: st.counter * sig.scale + sig.offset}
        st.counter = (st.counter + 1) % (1 << sig.length)
    if opts.checksum is not None:
        values = {**values, opts.checksum: 0}
    if st.fd and not fd_enabled:
        raise EncodeProblem(
            "a CAN FD message on a node without fd: true",
            f"{st.dbc.length}-byte CAN FD message; set fd: true to send it",
        )
    data = bytearray(encode_signals(st.dbc, values))
    idx = st.checksum_byte
    if idx is not None:
        data[idx] = checksum(opts.checksum_kind, bytes(data), idx)
    if st.fd:
        data += bytes(fd_payload_length(len(data)) - len(data))
    if opts.counter is None and opts.checksum is None:
        st.encoded = bytes(data)
    return data
