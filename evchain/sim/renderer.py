"""Frames of a simulated drive at any time, for picture sinks (``context.renderer``).

The ``scene`` source hands sinks a :class:`SceneRenderer` (an
:class:`evchain.core.renderer.FrameRenderer`), apart from its ground truth: a sink that
pictures the drive renders through it, never through the truth. Each call renders with
scratch of its own, so a sink may render while the source renders frames ahead on other
threads.
"""

from __future__ import annotations

import numpy as np

from evchain.sim.drive import Scene
from evchain.sim.truth import SceneTruth


class SceneRenderer:
    """Renders a :class:`~evchain.sim.drive.Scene` at any time; ``name`` is its scenario."""

    def __init__(self, scene: Scene):
        self._scene = scene
        self.name: str = scene.cfg.scenario
        #: the latest time the route supports (the drive may stop earlier)
        self.max_time_s: float = scene.max_time_s
        #: the drive's length
        self.duration_s: float = scene.duration_s

    def render(self, t_us: float) -> np.ndarray:
        """The frame (float32 [H, W], linear intensity) at t_us (a new array)."""
        return self._scene.render(float(t_us) * 1e-6)[0]

    def with_scenario(self, scenario: str) -> tuple[SceneRenderer, SceneTruth]:
        """The same camera and speed in another scenario, from the start of its route to its
        end (dynamics adapted: curves for the curves scenario): its renderer and its truth."""
        from evchain.sim.config import SceneConfig, make_config

        values = self._scene.cfg.model_dump()
        values = {k: values[k] for k in SceneConfig.model_fields}
        values["scenario"] = scenario
        values["route_m"] = None
        if scenario == "curves":
            values["dynamics"] = "curves"
        elif values["dynamics"] == "curves":
            values["dynamics"] = "constant"
        values["duration_s"] = None
        values["start_m"] = 0.0
        scene = Scene(make_config(SceneConfig, **values))
        return SceneRenderer(scene), SceneTruth(scene)
