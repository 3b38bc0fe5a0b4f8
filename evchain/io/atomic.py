"""Atomic outputs: write under ``NAME.partial``, rename to ``NAME`` only when complete.

A run that fails leaves ``NAME.partial`` (clearly incomplete), never a truncated ``NAME``. Every
writer goes through :class:`AtomicFile`: bytes written piece by piece, or a file (or folder)
that a library writes under the temporary name.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import BinaryIO


def partial_path(path: Path) -> Path:
    return path.with_name(path.name + ".partial")


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    with AtomicFile(path) as out:
        out.write(data)


def atomic_write_text(path: str | Path, text: str) -> None:
    atomic_write_bytes(path, text.encode("utf-8"))


class AtomicFile:
    """One output written under a temporary name, then ``commit()`` or ``abort()``.

    ``AtomicFile(path)`` opens ``NAME.partial`` for ``write()`` (``file`` is the binary file
    object, for libraries that write to one); ``AtomicFile.reserve(path, tmp)`` only names the
    temporary file or folder (default ``NAME.partial``) for a library that creates it itself.
    ``commit`` renames it to ``NAME``; ``abort`` leaves it for inspection and makes sure no
    stale ``NAME`` file from an earlier run suggests success (a stale folder is the caller's to
    remove). Both do nothing once either has run. As a context manager: commit on success,
    abort on an exception.
    """

    def __init__(self, path: str | Path):
        self._name(path, None)
        self._fh: BinaryIO | None = open(self.tmp, "wb")

    @classmethod
    def reserve(cls, path: str | Path, tmp: str | Path | None = None) -> AtomicFile:
        """An output that a library writes at ``tmp`` (default ``NAME.partial``)."""
        out = cls.__new__(cls)
        out._name(path, tmp)
        out._fh = None
        return out

    def _name(self, path, tmp) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.tmp = partial_path(self.path) if tmp is None else Path(tmp)
        self.done = False

    @property
    def file(self) -> BinaryIO:
        if self._fh is None:
            raise ValueError(f"{self.tmp}: no open file (committed, aborted, or written by a "
                             "library)")
        return self._fh

    def write(self, data) -> None:
        self.file.write(data)

    def commit(self) -> None:
        if self._finish():
            os.replace(self.tmp, self.path)

    def abort(self) -> None:
        if self._finish() and (self.path.is_file() or self.path.is_symlink()):
            self.path.unlink()

    def _finish(self) -> bool:
        """Close the file; False if already committed or aborted."""
        if self.done:
            return False
        self.done = True
        if self._fh is not None:
            self._fh.close()
            self._fh = None
        return True

    def __enter__(self) -> AtomicFile:
        return self

    def __exit__(self, kind, value, traceback) -> None:
        if kind is None:
            self.commit()
        else:
            self.abort()
