"""The synthetic soccer scene: deterministic, randomly accessible, truthful."""

from __future__ import annotations

from collections.abc import Generator

import numpy as np
import pytest
from flowrt.nodes.scene import BALL, BLUE, MIN_VISIBLE_PIXELS, YELLOW, SceneTruth, SoccerScene

NAMES = ("ball", "blue_goal", "yellow_goal", "blue_post", "yellow_post", "obstacle", "lines")


def _near(frame: np.ndarray, colour: tuple[int, int, int], tol: int = 40) -> np.ndarray:
    """Pixels within `tol` of a BGR colour on every channel (the scene's noise is small)."""
    diff = np.abs(frame.astype(np.int16) - np.array(colour, dtype=np.int16))
    return np.all(diff <= tol, axis=-1)


def test_frame_shape_and_type() -> None:
    frame, truth = SoccerScene(320, 240).render(0)
    assert frame.shape == (240, 320, 3)
    assert frame.dtype == np.uint8
    assert isinstance(truth, SceneTruth)
    for name in NAMES:
        assert name in truth.objects


def test_deterministic_for_seed_and_index() -> None:
    a = SoccerScene(seed=4, clutter=0.5)
    b = SoccerScene(seed=4, clutter=0.5)
    for i in (0, 7, 300, 1234):
        fa, ta = a.render(i)
        fb, tb = b.render(i)
        assert np.array_equal(fa, fb)
        assert ta == tb


def test_random_access_matches_sequential() -> None:
    seq = SoccerScene(seed=2, clutter=0.3)
    frames = {i: seq.render(i) for i in range(0, 600)}
    jump = SoccerScene(seed=2, clutter=0.3)
    for i in (599, 17, 300, 256, 255):
        f, t = jump.render(i)
        assert np.array_equal(f, frames[i][0])
        assert t == frames[i][1]


def test_seeds_differ() -> None:
    assert not np.array_equal(SoccerScene(seed=0).render(50)[0], SoccerScene(seed=1).render(50)[0])


def test_invalid_arguments() -> None:
    with pytest.raises(ValueError, match="clutter"):
        SoccerScene(clutter=1.5)
    with pytest.raises(ValueError, match="index"):
        SoccerScene().render(-1)


@pytest.mark.slow  # over 1 s of CPU at 640x480
@pytest.mark.parametrize(("width", "height"), [(320, 240), (640, 480)])
def test_truth_is_consistent(width: int, height: int) -> None:
    scene = SoccerScene(width, height, seed=3, clutter=0.3)
    occluded_or_clipped = out_of_view = 0
    full_ball = None
    for i in range(0, 400, 2):
        frame, truth = scene.render(i)
        for name in NAMES:
            o = truth[name]
            assert o.visible == (o.pixels >= MIN_VISIBLE_PIXELS)
            if o.pixels == 0:
                assert o.centroid is None
                assert o.bbox is None
                continue
            x, y, w, h = o.bbox
            assert 0 <= x <= x + w <= width
            assert 0 <= y <= y + h <= height
            cx, cy = o.centroid
            assert x <= cx <= x + w - 1
            assert y <= cy <= y + h - 1
        # The pixels of the ball's colour are exactly its visible pixels (low noise, no
        # other orange in the scene), so the centroid is that of what a camera sees.
        ball = truth["ball"]
        orange = _near(frame, BALL)
        assert abs(int(orange.sum()) - ball.pixels) <= 2
        if ball.pixels:
            ys, xs = np.nonzero(orange)
            assert abs(xs.mean() - ball.centroid[0]) < 0.5
            assert abs(ys.mean() - ball.centroid[1]) < 0.5
            full_ball = max(full_ball or 0, ball.pixels)
            if ball.pixels < 0.9 * full_ball:
                occluded_or_clipped += 1
        else:
            out_of_view += 1
        for name, colour in (("blue_goal", BLUE), ("yellow_goal", YELLOW)):
            o = truth[name]
            x, y, w, h = o.bbox
            assert int(_near(frame[y : y + h, x : x + w], colour).sum()) == o.pixels
    # The dynamics do produce the hard cases.
    assert occluded_or_clipped > 0
    assert out_of_view > 0


def test_obstacle_is_the_most_visible_robot() -> None:
    truth = SoccerScene(seed=5).render(10)[1]
    robots = [truth[f"obstacle_{k}"] for k in range(3)]
    assert truth["obstacle"].pixels == max(r.pixels for r in robots)


def test_clutter_adds_noise_and_distractors() -> None:
    clean = SoccerScene(seed=1, clutter=0.0).render(0)[0].astype(np.int16)
    busy = SoccerScene(seed=1, clutter=1.0).render(0)[0].astype(np.int16)
    # Magenta/purple distractors: neither the ball's colour nor any class colour.
    magenta = _near(busy.astype(np.uint8), (200, 60, 200), tol=50)
    assert magenta.sum() > 20
    assert np.abs(busy - clean).mean() > 2


def test_same_game_at_every_resolution() -> None:
    small = SoccerScene(320, 240, seed=9)
    large = SoccerScene(640, 480, seed=9)
    compared = 0
    for i in range(0, 400, 20):
        a, b = small.render(i)[1]["ball"], large.render(i)[1]["ball"]
        if a.visible and b.visible:
            compared += 1
            assert abs(2 * a.centroid[0] - b.centroid[0]) <= 2.0
            assert abs(2 * a.centroid[1] - b.centroid[1]) <= 2.0
    assert compared > 5


def test_a_frame_shown_in_order_simulates_a_few_steps_at_most() -> None:
    """A chunk of the game is ~4 ms of Python: simulated a few frames per frame rendered
    (the next one while this one is shown), never at once on a camera's tick."""
    from flowrt.nodes import scene as sc

    s = SoccerScene(64, 48, seed=1)
    steps = 0
    original = s._chunk_steps

    def counted(chunk: int) -> Generator[None, None, np.ndarray]:
        nonlocal steps
        inner = original(chunk)
        while True:
            try:
                next(inner)
            except StopIteration as done:
                out: np.ndarray = done.value
                return out
            steps += 1
            yield

    s._chunk_steps = counted  # type: ignore[method-assign]
    worst = 0
    for i in range(3 * sc.CHUNK):
        before = steps
        s.render(i)
        worst = max(worst, steps - before)
    assert worst == sc.AHEAD_STEPS
    fresh = SoccerScene(64, 48, seed=1)  # the same game whichever way it was simulated
    for i in (0, sc.CHUNK - 1, sc.CHUNK, 2 * sc.CHUNK + 5):
        assert np.array_equal(s.render(i)[0], fresh.render(i)[0])
