"""Summaries of the statistics rings (issue 31): the same numbers, made once per change.

``rt.stats()`` summarises three rings per node and one per edge on the loop; with 1000 nodes
that cost 39 ms a call (the live table asks 4 times a second), so a ring whose samples did not
change gives back the summary made last time."""

from __future__ import annotations

import numpy as np
import pytest

from flowrt.stats import Running, Summary


def test_a_summary_is_remade_only_when_samples_change() -> None:
    r = Running()
    assert r.summary() == Summary()
    samples = np.random.default_rng(3).exponential(0.01, 5000)
    for x in samples[:100]:
        r.add(float(x))
    first = r.summary()
    assert r.summary() is first  # nothing new: the same snapshot
    assert r.summary(scale=1.0) is not first  # another unit: made again
    r.add(0.5)
    again = r.summary()
    assert again is not first
    assert again.count == 101
    assert again.max == pytest.approx(500.0)


def test_the_figures_are_those_of_the_samples() -> None:
    r = Running()
    samples = np.random.default_rng(4).exponential(0.01, 1000)
    for x in samples:
        r.add(float(x))
    s = r.summary()
    assert s.count == 1000
    assert s.mean == pytest.approx(samples.mean() * 1000)
    assert s.std == pytest.approx(samples.std(ddof=1) * 1000)
    assert s.min == pytest.approx(samples.min() * 1000)
    ordered = np.sort(samples)
    assert s.p50 == pytest.approx(ordered[500] * 1000)
    assert s.p99 == pytest.approx(ordered[990] * 1000)
    assert Summary.model_validate(s.model_dump()) == s
