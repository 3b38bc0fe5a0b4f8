"""What made a run: the contents of its input files and the code that ran.

``report.json`` records both (``inputs``: each input file's SHA-256; ``versions.source``: a hash
of the source files of evchain and of every plugin), so a sweep reuses a run only when the
pipeline, every input file and the code are the same as those of the run it finds.
"""

from __future__ import annotations

import hashlib
import importlib
import sys
from pathlib import Path
from typing import Any

_digests: dict[tuple[str, int, int], str] = {}


def file_digest(path: str | Path) -> str:
    """SHA-256 of a file's bytes (of a folder: of its files' relative names and bytes).
    Remembered per path, size and modification time, so a file is read once per process."""
    path = Path(path)
    st = path.stat()
    key = (str(path.resolve()), st.st_size, st.st_mtime_ns)
    if key not in _digests:
        h = hashlib.sha256()
        files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
        for f in files:
            if path.is_dir():
                h.update(f.relative_to(path).as_posix().encode() + b"\0")
            with open(f, "rb") as fh:
                while chunk := fh.read(1 << 22):
                    h.update(chunk)
        _digests[key] = h.hexdigest()
    return _digests[key]


def input_digests(spec) -> dict[str, dict[str, str]]:
    """``{"STAGE.PARAM": {"path": ..., "sha256": ...}}`` for every input file of ``spec``
    (its stages' ``input_paths``)."""
    from evchain.errors import DataError

    out = {}
    for stage in spec.stages:
        for key in stage.cls.input_paths:
            value = getattr(stage.params, key)
            if value is not None:
                try:
                    digest = file_digest(value)
                except OSError as exc:
                    raise DataError(f"{value}: cannot read input {stage.id}.{key}: "
                                    f"{exc.strerror}") from None
                out[f"{stage.id}.{key}"] = {"path": str(value), "sha256": digest}
    return out


def tree_stamp(folder: Path) -> str:
    """Short hash of the ``.py`` files under ``folder`` (relative names and bytes), as
    :func:`evchain.bench_cache.source_stamp` does for parts of evchain."""
    h = hashlib.sha256()
    for f in sorted(folder.rglob("*.py")):
        h.update(f.relative_to(folder).as_posix().encode())
        h.update(f.read_bytes())
    return h.hexdigest()[:10]


def source_stamps(registry) -> dict[str, Any]:
    """Hash of the source of evchain and of each plugin distribution that registers filters
    (the top-level packages its filters come from)."""
    packages: dict[str, set[str]] = {"evchain": {"evchain"}}
    for info in registry.filters.values():
        packages.setdefault(info.distribution, set()).add(info.cls.__module__.split(".")[0])
    out = {}
    for dist, tops in sorted(packages.items()):
        stamps = []
        for top in sorted(tops):
            module = sys.modules.get(top) or importlib.import_module(top)
            where, file = getattr(module, "__path__", None), getattr(module, "__file__", None)
            if where:
                stamps.append(tree_stamp(Path(list(where)[0])))
            elif file:
                stamps.append(hashlib.sha256(Path(file).read_bytes()).hexdigest()[:10])
            else:
                stamps.append("unknown")  # defined interactively: no source to hash
        out[dist] = "+".join(stamps)
    return out
