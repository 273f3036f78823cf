"""The edge buffers' accounting, as a property: every value published is delivered, dropped
with its reason, unread or still held, and the reasons add up to the drops (a burst behind a
queue of 8 was counted with no reason)."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from flowrt.edges import EMPTY, QUEUE_FULL, make_buffer

# a step: put a value, take one, or end (the stop's discard)
STEPS = st.lists(st.sampled_from(["put", "put", "take"]), max_size=60)


@given(policy=st.sampled_from(["queue", "latest"]), size=st.integers(1, 8), steps=STEPS)
def test_every_drop_has_its_reason(policy: str, size: int, steps: list[str]) -> None:
    buf = make_buffer(policy, "a.out->b.in", size, lambda: 0.0)
    for n, step in enumerate(steps):
        if step == "put":
            buf.put(n, 0.0)
        else:
            buf.take_new() if policy == "latest" else buf.take()  # type: ignore[attr-defined]
    held = buf.pending()
    assert buf.published == buf.delivered + buf.dropped + buf.unread + held
    assert sum(buf.drop_reasons.values()) == buf.dropped
    buf.discard("stop")
    assert sum(buf.drop_reasons.values()) == buf.dropped
    assert buf.published == buf.delivered + buf.dropped + buf.unread


def test_a_full_queue_says_why() -> None:
    buf = make_buffer("queue", "a.out->b.in", 2, lambda: 0.0)
    for v in range(5):
        buf.put(v, 0.0)
    assert buf.drop_reasons == {QUEUE_FULL: 3}
    assert buf.take() == 3  # type: ignore[attr-defined]
    assert buf.take() == 4  # type: ignore[attr-defined]
    assert buf.take() is EMPTY  # type: ignore[attr-defined]
