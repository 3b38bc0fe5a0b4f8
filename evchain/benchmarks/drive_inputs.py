"""Cached inputs of the benchmarks on the simulated reference drive (:mod:`evchain.bench_cache`).

* :func:`drive_events`: the emulator output of a stretch of the drive, made by the ``scene`` and
  ``emulator`` stages of a pipeline file as configured there (``start_m`` and ``duration_s``
  set to the stretch; ``threads`` is left out of the hash: it does not change the frames).
* :func:`drive_flow`: the output of that pipeline's flow stage (``lk_flow`` or ``plane_flow``,
  as configured there) on those events; for a frame pipeline (``frame_flow``) on
  :func:`drive_aps`.
* :func:`drive_aps`: the frames of the ``scene`` and ``aps`` stages of a frame pipeline
  (pipelines/frames-reference.yaml) on a stretch of its drive.

Each takes ``overrides`` (``STAGE.PARAM=VALUE``, as ``evchain run --set``) for other drives
of the same pipeline. Loading gives the packets and a context with the scene's geometry and
exact ground truth (set up from the stored scene parameters; that renders nothing); where the
scene has an IMU (``imu_rate_hz`` > 0), event and flow packets carry its series ``imu`` over
their slices, the samples the scene source gives (each sample's noise depends only on the
seed, the stage id and its time, so they need not be stored).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from evchain.bench_cache import BenchInput
from evchain.core.filter import Context

ROOT = Path(__file__).resolve().parents[2]
PIPELINES = ROOT / "pipelines"
FLOW_STAGES = ("lk_flow", "plane_flow", "frame_flow")
#: the modules that make the drive's events, and its aps frames (they and all they import count
#: in an input's hash); a flow input adds its flow filter's module
EVENT_SOURCES = (__name__, "evchain.filters.scene", "evchain.filters.emulator")
APS_SOURCES = (__name__, "evchain.filters.scene", "evchain.filters.aps")
EVENT_COLUMNS = ("x", "y", "t", "p")
FLOW_COLUMNS = ("x", "y", "t", "p", "vx", "vy", "t_edge")


def relative(path: Path) -> str:
    """``path`` relative to the repository (``pipelines/reference-lk.yaml``) when inside it."""
    path = Path(path).resolve()
    try:
        return path.relative_to(ROOT).as_posix()
    except ValueError:
        return str(path)


def pipeline_spec(path: Path, start_m: float, duration_s: float, overrides: Sequence[str] = ()):
    """The pipeline file ``path``, loaded with ``overrides``, its scene set to the stretch."""
    from evchain.core.config import load_pipeline
    from evchain.core.registry import make_registry

    return load_pipeline(path, make_registry(), [*overrides, f"scene.start_m={start_m!r}",
                                                 f"scene.duration_s={duration_s!r}"])


def stretch_label(scene: dict[str, Any]) -> str:
    """``reference-drive T0-T1 s``: the stretch of the drive that ``scene``'s parameters set
    (with its dynamics when not constant, and its IMU's rate)."""
    t0 = scene["start_m"] / scene["speed_mps"] if scene["speed_mps"] else 0.0
    label = f"reference-drive {t0:g}-{t0 + scene['duration_s']:g} s"
    if scene.get("dynamics", "constant") != "constant":
        label += f", {scene['dynamics']}"
    if scene.get("imu_rate_hz"):
        label += f", IMU {scene['imu_rate_hz']:g} Hz"
    return label


def drive_events(pipeline: Path, start_m: float, duration_s: float,
                 overrides: Sequence[str] = ()) -> BenchInput:
    """Events of the drive of ``pipeline`` (its ``scene`` and ``emulator`` stages) from
    ``start_m`` for ``duration_s``."""
    spec = pipeline_spec(pipeline, start_m, duration_s, overrides)
    emulator = spec.stage("emulator")
    params = _scene_and(spec, "emulator")

    def make() -> dict[str, np.ndarray]:
        from evchain.core.packets import EventPacket

        outs = _through_scene(params, emulator, params["emulator_id"])
        ev = EventPacket.concat(outs)
        return {**{c: getattr(ev, c) for c in EVENT_COLUMNS}, "bounds": _bounds(outs)}

    return BenchInput("drive-events", stretch_label(params["scene"]), params, EVENT_SOURCES,
                      make)


def _scene_and(spec, name: str) -> dict:
    """The cache parameters of ``spec``'s ``scene`` (without its thread count) and of its stage
    ``name``: seed, both stages' parameters and ids."""
    scene, stage = spec.stage("scene"), spec.stage(name)
    scene_params = scene.params.model_dump(mode="json")
    scene_params.pop("threads")
    return {"seed": spec.seed, "scene": scene_params, "scene_id": scene.id,
            name: stage.params.model_dump(mode="json"), f"{name}_id": stage.id}


def _through_scene(params: dict, stage, stage_id: str) -> list:
    """The packets of ``stage`` (a pipeline stage spec) run on the scene of ``params``, its
    flush included."""
    ctx = Context(seed=params["seed"])
    source = _scene(params, ctx, threads=0)
    f = stage.cls()
    f.id = stage_id
    f.setup(stage.params, ctx)
    try:
        outs = [f.process(p) for p in source.packets()]
        last = f.flush()
    finally:
        source.close()
    return outs if last is None else [*outs, last]


def _bounds(outs: list) -> np.ndarray:
    """The packets' slice bounds: every start and the last end."""
    return np.array([o.t_start for o in outs] + [outs[-1].t_end], np.int64)


def drive_flow(pipeline: Path, start_m: float, duration_s: float,
               overrides: Sequence[str] = ()) -> BenchInput:
    """Output of the flow stage of ``pipeline`` on :func:`drive_events` of the same stretch
    (``frame_flow``: on :func:`drive_aps`)."""
    spec = pipeline_spec(pipeline, start_m, duration_s, overrides)
    stage = next((s for s in spec.stages if s.use in FLOW_STAGES), None)
    if stage is None:
        from evchain.errors import ConfigError

        raise ConfigError(f"no flow stage ({' or '.join(FLOW_STAGES)})", file=spec.file)
    frames = stage.use == "frame_flow"
    source = (drive_aps if frames else drive_events)(pipeline, start_m, duration_s, overrides)
    params = {"use": stage.use, "id": stage.id, "flow": stage.params.model_dump(mode="json")}

    def make() -> dict[str, np.ndarray]:
        packets, ctx = (load_aps if frames else load_events)(source)
        f = stage.cls()
        f.id = stage.id
        f.setup(stage.params, Context(seed=source.params["seed"], geometry=ctx.geometry,
                                      truth=ctx.truth))
        outs = [f.process(p) for p in packets]
        last = f.flush()
        if last is not None:
            outs.append(last)
        return {**{c: np.concatenate([getattr(o, c) for o in outs]) for c in FLOW_COLUMNS},
                "bounds": _bounds(outs)}

    label = f"{source.label}, {stage.use} of {Path(pipeline).name}"
    return BenchInput("drive-flow", label, params, (__name__, stage.cls.__module__), make,
                      (source,))


def drive_aps(pipeline: Path, start_m: float, duration_s: float,
              overrides: Sequence[str] = ()) -> BenchInput:
    """Frames of the ``aps`` stage of ``pipeline`` on its ``scene`` (as configured there) from
    ``start_m`` for ``duration_s``."""
    spec = pipeline_spec(pipeline, start_m, duration_s, overrides)
    aps = spec.stage("aps")
    params = _scene_and(spec, "aps")

    def make() -> dict[str, np.ndarray]:
        outs = _through_scene(params, aps, params["aps_id"])
        return {"frames": np.concatenate([o.frames for o in outs]),
                "t": np.concatenate([o.t for o in outs]),
                "t_exposure_start": np.concatenate([o.t_exposure_start for o in outs]),
                "bounds": _bounds(outs)}

    return BenchInput("drive-aps", f"{stretch_label(params['scene'])}, aps of "
                      f"{Path(pipeline).name}", params, APS_SOURCES, make)


def _scene(params: dict[str, Any], ctx: Context, threads: int = 1):
    """The scene source of a :func:`drive_events` or :func:`drive_aps` input, set up (sets
    the context's geometry and truth)."""
    from evchain.filters.scene import SceneSource

    scene = SceneSource()
    scene.id = params["scene_id"]
    scene.setup(SceneSource.Params(**params["scene"], threads=threads), ctx)
    return scene


def _loaded(cls, d: dict[str, np.ndarray], columns, params: dict[str, Any]
            ) -> tuple[list, Context]:
    """The stored packets of a drive whose scene has ``params`` (with the scene's IMU series
    where it has one), and a context with its geometry and truth (the scene is set up, which
    renders nothing, and closed)."""
    from evchain.core.series import IMU
    from evchain.sim.imu import noise_key

    ctx = Context(seed=params["seed"])
    scene = _scene(params, ctx)
    scene.close()
    b = d["bounds"]
    idx = np.searchsorted(d["t"], b)
    packets = [cls(geometry=ctx.geometry, t_start=int(b0), t_end=int(b1),
                   **{c: d[c][i:j] for c in columns})
               for b0, b1, i, j in zip(b[:-1], b[1:], idx[:-1], idx[1:], strict=True)]
    if scene.params.imu_rate_hz <= 0:
        return packets, ctx
    key = noise_key(ctx, scene.id)
    return [p.with_series(IMU.name, scene.params.imu_between(scene.scene, p.t_start, p.t_end,
                                                             key)) for p in packets], ctx


def load_events(inp: BenchInput) -> tuple[list, Context]:
    """(event packets as the emulator made them, context with geometry and truth)."""
    from evchain.core.packets import EventPacket

    return _loaded(EventPacket, inp.load(), EVENT_COLUMNS, inp.params)


def load_aps(inp: BenchInput) -> tuple[list, Context]:
    """(aps frame packets as the ``aps`` stage made them, context with geometry and truth)."""
    from evchain.core.packets import ApsFramePacket

    return _loaded(ApsFramePacket, inp.load(), ("frames", "t", "t_exposure_start"), inp.params)


def load_flow(inp: BenchInput) -> tuple[list, Context]:
    """(flow packets as the flow stage made them, context with geometry and truth)."""
    from evchain.core.packets import FlowPacket

    return _loaded(FlowPacket, inp.load(), FLOW_COLUMNS, inp.needs[0].params)
