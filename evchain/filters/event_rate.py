"""Sink ``event_rate_plot``: event rate at one pixel column over time (thesis Fig. 4.3)."""

from __future__ import annotations

import numpy as np
from pydantic import Field

from evchain.core.filter import Filter, FilterParams
from evchain.core.packets import EventPacket
from evchain.core.series import EVENT_RATE


class EventRatePlot(Filter):
    """Event rate at one pixel column in bins: series ``event_rate`` and a PNG plot at the end.

    Counts the events with ``x == column`` (all rows) in bins ``[k*bin_us, (k+1)*bin_us)``. A
    bin's series entry has ``t`` = the bin's last µs (``t_bin_end - 1``; for the partial last
    bin, emitted at flush, the last µs of the input); fields ``t_bin_start``, ``t_bin_end``,
    ``rate_eps`` (events per second), ``on``, ``off``. Passes events (and other series) on
    unchanged, with output slices lagging the input by 1 µs: each input packet's last µs leaves
    with the next output (flush emits the rest), so every entry lies inside its packet's slice.
    """

    name = "event_rate_plot"
    consumes = EventPacket
    produces = None
    adds_series = (EVENT_RATE,)
    output_paths = ("path",)

    class Params(FilterParams):
        column: int = Field(0, ge=0, description="pixel column x to observe")
        bin_us: int = Field(10_000, ge=1, description="bin width")
        series: str = Field("event_rate", description="name of the emitted series")
        path: str | None = Field("event_rate.png", description="PNG written at the end "
                                 "(relative to the output folder); null for none")
        title: str = Field("", description="plot title")

    @classmethod
    def series_added(cls, params):
        """``event_rate``, or the name given by the parameter ``series``."""
        return (EVENT_RATE.renamed(params.series),)

    def reset(self) -> None:
        self._bin = None          # index of the open bin
        self._on = 0
        self._off = 0
        self._rows: list[tuple[int, int, int]] = []
        self._last_end = None
        self._pend = None         # input of [cut, last t_end) held back for the next output

    def _close_bins(self, upto_bin: int) -> np.ndarray:
        b = self.params.bin_us
        out = []
        while self._bin is not None and self._bin < upto_bin:
            s, e = self._bin * b, (self._bin + 1) * b
            out.append((e - 1, s, e, (self._on + self._off) * 1e6 / b, self._on, self._off))
            self._rows.append(out[-1])
            self._bin += 1
            self._on = self._off = 0
        return np.array(out, dtype=EVENT_RATE.dtype)

    def process(self, packet: EventPacket) -> EventPacket:
        b = self.params.bin_us
        if self._bin is None:
            self._bin = packet.t_start // b
        self._last_end = packet.t_end
        sel = packet.x == self.params.column
        t = packet.t[sel]
        p = packet.p[sel]
        entries = []
        if len(t):
            bins = t // b
            for k in np.unique(bins):
                entries.append(self._close_bins(int(k)))
                m = bins == k
                self._on += int((p[m] > 0).sum())
                self._off += int((p[m] < 0).sum())
        entries.append(self._close_bins(packet.t_end // b))   # bins ending <= t_end
        done = np.concatenate(entries)
        if len(done):
            packet = packet.with_series(self.params.series, done)
        joined = self._join(packet)
        out, self._pend = _split(joined, max(packet.t_end - 1, joined.t_start))
        return out

    def _join(self, packet):
        """The held-back part and ``packet`` as one packet (copies only when needed)."""
        pend = self._pend
        if pend is None:
            return packet
        if len(pend) == 0 and not any(len(v) for v in pend.series.values()):
            return packet.replace(t_start=pend.t_start)
        return type(packet).concat([pend, packet])

    def flush(self) -> EventPacket | None:
        from evchain.report.event_rate import plot_event_rate

        if self._bin is None or self._pend is None:
            return None
        b = self.params.bin_us
        last = self._last_end
        tail = np.zeros(0, EVENT_RATE.dtype)
        if self._on + self._off > 0 or (last % b):
            # the partial last bin, rate over the covered part
            s = self._bin * b
            span = max(last - s, 1)
            tail = np.array([(max(last - 1, s), s, last, (self._on + self._off) * 1e6 / span,
                              self._on, self._off)], EVENT_RATE.dtype)
            self._rows.append(tuple(tail[0]))
            self._on = self._off = 0
        if self.params.path:
            allrows = np.array(self._rows, dtype=EVENT_RATE.dtype)
            plot_event_rate(allrows, self.context.output_path(self.params.path),
                            title=self.params.title or f"event rate at column "
                            f"{self.params.column}")
        out, self._pend = self._pend, None
        # tail t = last - 1 (or the bin start) lies in the held-back slice [cut, last)
        return out.with_series(self.params.series, tail) if len(tail) else out


def _split(packet, cut: int):
    """``packet`` cut at ``cut`` into the parts ``[t_start, cut)`` and ``[cut, t_end)``."""
    m = packet.t < cut
    if m.all():
        before = packet
        after = packet.select(np.zeros(0, np.int64))
    else:
        before = packet.select(m)
        after = packet.select(~m)
    sa = {k: v[v["t"] < cut] for k, v in packet.series.items()}
    sb = {k: v[v["t"] >= cut] for k, v in packet.series.items()}
    return (before.replace(t_end=cut, series=sa),
            after.replace(t_start=cut, series=sb))
