"""Series as CSV files, streamed: ``OUT/series/NAME.csv`` grows packet by packet.

One file per series, a header row of the field names, then one row per entry: integers as
``str``, floats as ``repr`` (the shortest text that reads back to the same double). Each file is
an :class:`~evchain.io.atomic.AtomicFile`: rows are appended to ``NAME.csv.partial`` as the
packets come, and the file is renamed to ``NAME.csv`` only when the run succeeds, so memory does
not grow with the recording's length and a failed run leaves no complete-looking series.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from evchain.io.atomic import AtomicFile


def csv_rows(entries: np.ndarray) -> str:
    """The rows of a structured array as CSV text (no header), each ending in a newline."""
    names = entries.dtype.names
    if not len(entries):
        return ""
    text = [repr if entries.dtype[n].kind == "f" else str for n in names]
    cols = [list(map(fmt, entries[n].tolist())) for fmt, n in zip(text, names, strict=True)]
    return "".join(",".join(row) + "\n" for row in zip(*cols, strict=True))


class SeriesCsvWriter:
    """Appends each packet's series to ``folder/NAME.csv.partial``; :meth:`commit` renames them
    all, :meth:`abort` leaves the partial files. ``counts``: entries written per series."""

    def __init__(self, folder: Path):
        self.folder = Path(folder)
        self.counts: dict[str, int] = {}
        self._files: dict[str, AtomicFile] = {}

    def append(self, series: dict[str, np.ndarray]) -> None:
        for name, entries in series.items():
            out = self._files.get(name)
            if out is None:
                out = self._files[name] = AtomicFile(self.folder / f"{name}.csv")
                out.write((",".join(entries.dtype.names) + "\n").encode())
                self.counts[name] = 0
            out.write(csv_rows(entries).encode())
            self.counts[name] += len(entries)

    def commit(self) -> None:
        for out in self._files.values():
            out.commit()

    def abort(self) -> None:
        for out in self._files.values():
            out.abort()


def remove_series(folder: Path) -> None:
    """Remove every series file (complete or partial) an earlier run left in ``folder``."""
    if folder.is_dir():
        for path in folder.iterdir():
            if path.is_file() and (path.suffix == ".csv" or path.name.endswith(".csv.partial")):
                path.unlink()

