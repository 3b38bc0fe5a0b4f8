"""A picture sink renders through ``context.renderer`` while the ``scene`` source renders
ahead on other threads: neither disturbs the other."""

from __future__ import annotations

import numpy as np

from evchain.core.renderer import FrameRenderer
from evchain.filters.scene import SceneSource
from evchain.sim.drive import Scene
from evchain.testing.contract import make_context

# adaptive steps change at almost every frame, so the source thread renders most frames itself
# with rows spread over the pool (Scene.render), the path a preview render shares
PARAMS = dict(width=48, height=36, supersample=1, start_m=200.0, duration_s=0.05,
              packet_us=1000, max_frames_per_packet=2)


def test_preview_renders_while_the_source_renders_ahead():
    single = SceneSource()
    single.setup(SceneSource.Params(**PARAMS), make_context(None))
    want = list(single.packets())
    reference = Scene(SceneSource.Params(**PARAMS))       # one thread, for the previews

    src = SceneSource()
    ctx = make_context(None)
    src.setup(SceneSource.Params(**dict(PARAMS, threads=2)), ctx)
    assert isinstance(ctx.renderer, FrameRenderer) and ctx.renderer.name == "high-rise"
    times = iter(np.random.default_rng(5).uniform(0, 50_000, 10_000))
    got, previews = [], []
    for packet in src.packets():     # the background thread renders the next packets now
        got.append(packet)
        for _ in range(3):
            t_us = next(times)
            previews.append((t_us, ctx.renderer.render(t_us)))

    assert len(got) == len(want) > 20
    for p, q in zip(want, got, strict=True):
        assert (p.t_start, p.t_end) == (q.t_start, q.t_end)
        np.testing.assert_array_equal(p.t, q.t)
        np.testing.assert_array_equal(p.frames, q.frames)
    for t_us, frame in previews:
        np.testing.assert_array_equal(frame, reference.render(t_us * 1e-6)[0])
