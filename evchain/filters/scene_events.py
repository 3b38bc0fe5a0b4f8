"""Source ``scene_events``: the events of an earlier simulator run, replayed with exact truth."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from pathlib import Path

import yaml
from pydantic import Field

from evchain.core.filter import Context, Filter
from evchain.core.packets import EventPacket
from evchain.core.series import IMU
from evchain.core.truth import (
    DepthTruth,
    FlowTruth,
    FoeTruth,
    ObjectTruth,
    RotationTruth,
    TtcTruth,
)
from evchain.errors import DataError
from evchain.sim.config import ImuParams, SceneConfig


class SceneEvents(Filter):
    """Replays an AEDAT file written by a ``scene`` -> ``emulator`` run with the scene's exact
    ground truth, so flow, FOE and TTC experiments on a drive need not render it again.

    Give the scene parameters of the run that wrote the file (see its
    ``pipeline.resolved.yaml``): the truth (flow, depth, FOE, rotation, TTC) is computed from
    them, not read from the file. Sets ``context.geometry`` (with f, cx, cy) and
    ``context.truth`` (flow, FOE, camera rotation, TTC, depth, object ids). Packets cover the
    file's events in ``packet_us`` slices from the first; a file without events gives empty
    slices over the drive's duration. With ``imu_rate_hz`` the packets carry the simulated
    IMU as the ``scene`` source's do (series ``imu``: the true readings at the same sample
    times, bias and noise keyed by the seed and the stage id as the ``scene`` source's, each
    sample's noise a function of the key and its time: a replay under the recording's scene id
    and seed has its IMU, whatever the packets; ``--replay`` gives it that id): the IMU does
    not change the events, so it can be added to a replay of a recording made without one.
    """

    name = "scene_events"
    consumes = None
    produces = EventPacket
    provides_truth = (FlowTruth, FoeTruth, RotationTruth, TtcTruth, DepthTruth,
                      ObjectTruth)
    input_paths = ("path",)
    adds_series = (IMU,)

    class Params(SceneConfig, ImuParams):
        path: str = Field(description="AEDAT 2.0 file written by a run of this scene")
        packet_us: int = Field(10_000, ge=1, description="duration of one output slice in µs")

    def setup(self, params, context) -> None:
        from evchain.io.aedat2 import AedatSource
        from evchain.sim.drive import Scene
        from evchain.sim.truth import SceneTruth

        scene = Scene(params)
        self.scene = scene
        self.reader = AedatSource()
        self.reader.id = f"{self.id}.reader"
        self.reader.setup(AedatSource.Params(path=params.path, packet_us=params.packet_us),
                          Context(seed=context.seed, out_dir=context.out_dir,
                                  metrics=context.metrics, warnings=context.warnings))
        chip = self.reader.chip.geometry
        self.geometry = scene.geometry
        if (chip.width, chip.height) != (self.geometry.width, self.geometry.height):
            raise DataError(f"{params.path}: the sensor is {chip.width}x{chip.height} but the "
                            f"scene's camera is {self.geometry.width}x{self.geometry.height}: "
                            "give the width and height of the run that wrote the file")
        context.geometry = self.geometry
        context.truth = SceneTruth(scene)
        self.duration_us = int(round(scene.duration_s * 1e6))
        super().setup(params, context)

    def time_span_us(self) -> tuple[int, int] | None:
        return self.reader.time_span_us()

    @classmethod
    def series_added(cls, params):
        """``imu`` when ``imu_rate_hz`` > 0."""
        return (IMU,) if params.imu_rate_hz > 0 else ()

    def packets(self) -> Iterator[EventPacket]:
        p = self.params
        from evchain.sim.imu import noise_key

        key = noise_key(self.context, self.id)

        def with_imu(packet: EventPacket) -> EventPacket:
            imu = p.imu_between(self.scene, packet.t_start, packet.t_end, key)
            return packet if imu is None else packet.with_series(IMU.name, imu)

        empty = True
        for packet in self.reader.packets():
            empty = False
            yield with_imu(packet.replace(geometry=self.geometry))
        if empty:  # a drive without events (e.g. a uniform scene): its time still passes
            P = p.packet_us
            for t in range(0, self.duration_us, P):
                yield with_imu(EventPacket.empty(self.geometry, t, min(t + P, self.duration_us)))

    def close(self) -> None:
        reader = getattr(self, "reader", None)
        if reader is not None:
            reader.close()


#: scene parameters that change how fast frames render or only the IMU series beside the
#: events, not which events the emulator emits
RENDER_ONLY = ("threads", "max_frames_per_packet", "packet_us", *ImuParams.model_fields)


def replay_spec(spec, events_path: str | Path, check_recording: bool = True):
    """``spec`` with its leading ``scene`` -> ``emulator`` stages replaced by ``scene_events``
    reading ``events_path``, the events of an earlier run (``evchain run ... --replay``).

    That run's ``pipeline.resolved.yaml`` (beside the file) must show the same scene and
    emulator parameters, else the events would not be the ones this pipeline makes (a
    parameter the recording does not name, one added since, counts with its default).
    ``check_recording`` False skips that check, for a recording still to be made. The path is
    made absolute (relative to the current folder). The replay keeps the scene stage's id, so
    its IMU noise (seeded by the id) is the recording's."""
    import os

    from evchain.core.config import StageSpec
    from evchain.errors import ConfigError

    stages = spec.stages
    if len(stages) < 2 or (stages[0].use, stages[1].use) != ("scene", "emulator"):
        raise ConfigError("--replay needs a pipeline that starts with scene -> emulator",
                          file=spec.file)
    events_path = Path(os.path.abspath(events_path))
    recorded = events_path.parent / "pipeline.resolved.yaml"
    if check_recording:
        if not events_path.is_file():
            raise ConfigError(f"recording not found: {events_path}", file=spec.file)
        _check_recording(spec, recorded)
    scene = stages[0].params
    params = SceneEvents.Params(path=str(events_path), packet_us=scene.packet_us,
                                **{k: getattr(scene, k) for k in (*SceneConfig.model_fields,
                                                                  *ImuParams.model_fields)})
    first = StageSpec(use=SceneEvents.name, id=stages[0].id, cls=SceneEvents,
                      params=params, mark=stages[0].mark)
    return dataclasses.replace(spec, stages=[first, *stages[2:]])


def _check_recording(spec, recorded: Path) -> None:
    """The recorded run's resolved pipeline has this pipeline's scene and emulator."""
    from evchain.errors import ConfigError

    stages = spec.stages
    if not recorded.is_file():
        raise ConfigError(f"{recorded} not found: --replay takes the events file of a run "
                          "folder (written with its pipeline.resolved.yaml)", file=spec.file)
    chain = yaml.safe_load(recorded.read_text(encoding="utf-8")).get("chain", [])
    for i, stage in enumerate(stages[:2]):
        theirs = chain[i] if i < len(chain) else {}
        mine = {k: v for k, v in stage.params.model_dump(mode="json").items()
                if k not in RENDER_ONLY}
        # a parameter added since the recording was made had its default's effect there
        defaults = type(stage.params)().model_dump(mode="json")
        differ = sorted(k for k, v in mine.items() if theirs.get(k, defaults.get(k)) != v)
        if theirs.get("use") != stage.use or differ:
            shown = ", ".join(f"{k}: {theirs.get(k)!r} there, {mine[k]!r} here" for k in differ)
            raise ConfigError(f"the recorded run ({recorded}) is not this pipeline's "
                              f"{stage.use}: {shown or 'other stages'}", file=spec.file)
