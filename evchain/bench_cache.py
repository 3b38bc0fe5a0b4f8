"""Cached inputs of ``evchain bench``: data that takes long to make (rendered drive events, flow
computed from them), made once by ``evchain bench --prepare`` and read by the timed rows.

An input is the file ``KIND-HASH.npz`` in the cache folder (``$EVCHAIN_CACHE``, default the
user cache folder of ``evchain``, platformdirs). HASH covers the source files that make it (the
modules that make it and everything they import, ``provenance.modules_stamp``), the
parameters that make it and the hashes of the inputs it is made from: other code or other
parameters look for another file, never reuse this one. Nothing substitutes a missing input:
:meth:`BenchInput.load` raises :class:`~evchain.errors.MissingBenchInput`. Files are written
under ``NAME.partial`` and renamed when complete.

A workload with inputs is a :class:`Workload`: its rows and, separately, the inputs they read,
so that ``evchain bench`` can check them before running anything and ``--prepare`` can make them
without running the rows.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from evchain.errors import MissingBenchInput
from evchain.io.atomic import AtomicFile
from evchain.provenance import modules_stamp

#: layout of the stored arrays; part of every hash
FORMAT = 1


def cache_dir() -> Path:
    """``$EVCHAIN_CACHE``, else the user cache folder of ``evchain``."""
    env = os.environ.get("EVCHAIN_CACHE")
    if env:
        return Path(env)
    import platformdirs

    return Path(platformdirs.user_cache_dir("evchain"))


@dataclass(frozen=True, eq=False)
class BenchInput:
    """One cached input.

    ``kind`` names the file; ``label`` says what it is (e.g. ``reference-drive 0-2 s``);
    ``params`` (JSON-able) and ``sources`` (evchain modules; they and all they import count)
    are what makes it, with the inputs in ``needs``; ``make()`` returns the arrays to store (it
    may :meth:`load` the inputs in ``needs``, which :meth:`prepare` makes first).
    """

    kind: str
    label: str
    params: Mapping[str, Any]
    sources: tuple[str, ...]
    make: Callable[[], dict[str, np.ndarray]]
    needs: tuple[BenchInput, ...] = field(default=())

    @cached_property
    def recipe(self) -> dict[str, Any]:
        """Everything the hash covers (stored in the file as ``recipe``)."""
        return {"kind": self.kind, "format": FORMAT, "params": self.params,
                "code": modules_stamp(self.sources),
                "needs": [n.key for n in self.needs]}

    @cached_property
    def key(self) -> str:
        text = json.dumps(self.recipe, sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(text.encode()).hexdigest()[:10]

    @property
    def path(self) -> Path:
        return cache_dir() / f"{self.kind}-{self.key}.npz"

    def describe(self) -> str:
        """``label @hash``: what a row ran on."""
        return f"{self.label} @{self.key}"

    def exists(self) -> bool:
        return self.path.is_file()

    def load(self) -> dict[str, np.ndarray]:
        path = self.path
        if not path.is_file():
            raise MissingBenchInput(
                f"benchmark input {self.describe()} is not in the cache ({path}); make it with "
                f"`evchain bench --prepare PREFIX` for the workloads that need it")
        with np.load(path) as f:  # every f[key] reads the array again: once each
            return {k: f[k] for k in f.files if k != "recipe"}

    def prepare(self, echo: Callable[[str], object] = print) -> bool:
        """Make the input (and those it needs) unless cached; True if it was made now."""
        for need in self.needs:
            need.prepare(echo)
        if self.exists():
            return False
        echo(f"making {self.describe()} ...")
        t0 = time.perf_counter()
        arrays = self.make()
        path = self.path
        with AtomicFile(path) as out:  # a file object: np.savez adds no ".npz" to its name
            np.savez(out.file, recipe=np.array(json.dumps(self.recipe, sort_keys=True)),
                     **arrays)
        echo(f"made {self.describe()} in {time.perf_counter() - t0:.1f} s: {path}")
        return True


@dataclass(frozen=True)
class Workload:
    """A benchmark workload whose rows read cached inputs: ``rows(quick)`` makes the rows,
    ``inputs(quick)`` lists the inputs they read. Callable like a plain workload."""

    rows: Callable[[bool], list]
    inputs: Callable[[bool], list[BenchInput]]

    def __call__(self, quick: bool) -> list:
        return self.rows(quick)


def inputs_of(workload: Callable, quick: bool) -> list[BenchInput]:
    """The cached inputs ``workload`` reads (none for plain functions)."""
    inputs = getattr(workload, "inputs", None)
    return list(inputs(quick)) if inputs is not None else []
