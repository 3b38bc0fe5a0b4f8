"""Sink ``imu_rate_plot``: the rotation rate the flow shows against the gyro's, as a PNG."""

from __future__ import annotations

import numpy as np
from pydantic import Field

from evchain.core.filter import Filter, FilterParams
from evchain.core.packets import EventPacket
from evchain.core.series import IMU_RATE


class ImuRatePlot(Filter):
    """Plots ``imu_truth``'s series ``imu_rate`` at the end: per camera axis the gyro's rate and
    the rate fitted to the measured normal flow over time, bins without truth shaded.

    What a researcher checks first on a recording scored against its gyro: whether the flow
    turns with the gyro (sign, scale, timing). Passes packets on unchanged.
    """

    name = "imu_rate_plot"
    consumes = EventPacket
    produces = None
    needs_series = (IMU_RATE,)
    output_paths = ("path",)

    class Params(FilterParams):
        path: str = Field("imu_rate.png", description="PNG written at the end (relative to "
                                                      "the output folder)")
        title: str = Field("", description="plot title")

    def reset(self) -> None:
        self._rows: list[np.ndarray] = []

    def process(self, packet: EventPacket) -> EventPacket:
        rows = packet.series.get(IMU_RATE.name)
        if rows is not None and len(rows):
            self._rows.append(rows)
        return packet

    def flush(self) -> None:
        from evchain.report.imu_rate import plot_imu_rate

        rows = (np.concatenate(self._rows) if self._rows else np.zeros(0, IMU_RATE.dtype))
        plot_imu_rate(rows, self.context.output_path(self.params.path),
                      title=self.params.title or "rotation rate: gyro and flow")
        self.context.metrics[self.metrics_key("imu_rate_plot")] = {
            "path": str(self.context.output_path(self.params.path)), "bins": len(rows)}
        return None
