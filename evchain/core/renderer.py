"""What a frame source offers picture sinks besides its packets: frames at any time.

A source that can render its stream at any time (the ``scene`` simulator) sets
``context.renderer`` in its ``setup()``; picture sinks (``scene_preview``) read it there, never
through the ground truth. Without one, a sink pictures the frames it is given.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class FrameRenderer(Protocol):
    """Frames of the source's stream at any time."""

    #: what is pictured (e.g. the scenario), for file names
    name: str
    #: the latest time in s it can render
    max_time_s: float

    def render(self, t_us: float) -> np.ndarray:
        """The frame (float32 [H, W], linear intensity) at ``t_us`` (µs, float allowed): a new
        array, safe to call from any thread while the source streams."""
        ...
