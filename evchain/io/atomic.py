"""Atomic outputs: write under ``NAME.partial``, rename to ``NAME`` only when complete.

A run that fails leaves ``NAME.partial`` (clearly incomplete), never a truncated ``NAME``.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import BinaryIO


def partial_path(path: Path) -> Path:
    return path.with_name(path.name + ".partial")


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = partial_path(path)
    with open(tmp, "wb") as fh:
        fh.write(data)
    os.replace(tmp, path)


def atomic_write_text(path: str | Path, text: str) -> None:
    atomic_write_bytes(path, text.encode("utf-8"))


class AtomicFile:
    """A binary file written in pieces: ``write()`` ..., then ``commit()`` or ``abort()``.

    ``commit`` renames ``NAME.partial`` to ``NAME``; ``abort`` leaves the ``.partial`` file for
    inspection and makes sure no stale ``NAME`` from an earlier run suggests success.
    """

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.tmp = partial_path(self.path)
        self._fh: BinaryIO | None = open(self.tmp, "wb")

    def write(self, data) -> None:
        self._fh.write(data)

    def commit(self) -> None:
        if self._fh is None:
            return
        self._fh.close()
        self._fh = None
        os.replace(self.tmp, self.path)

    def abort(self) -> None:
        if self._fh is None:
            return
        self._fh.close()
        self._fh = None
        if self.path.exists():
            self.path.unlink()
