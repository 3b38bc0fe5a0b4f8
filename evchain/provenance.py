"""What made a run: the contents of its input files and the code that ran.

``report.json`` records both (``inputs``: each input file's SHA-256; ``versions.source``: a hash
of the source files of evchain that the run can execute and of the plugins whose filters it
uses), so a sweep reuses a run only when the pipeline, every input file and the code are the
same as those of the run it finds.
"""

from __future__ import annotations

import ast
import hashlib
import importlib
import sys
from collections.abc import Iterable
from pathlib import Path
from typing import Any

_digests: dict[tuple[str, int, int], str] = {}
_imports: dict[tuple[str, str, int, int], frozenset[str]] = {}


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
    """Short hash of the ``.py`` files under ``folder`` (relative names and bytes)."""
    return files_stamp(folder.rglob("*.py"), folder)


def _module_file(name: str, root: Path) -> Path | None:
    """The source file of module ``name`` of the package in folder ``root`` (None: not a
    module of it, e.g. a class imported by name)."""
    base = root.joinpath(*name.split(".")[1:])
    if (base / "__init__.py").is_file():
        return base / "__init__.py"
    return base.with_suffix(".py") if base.with_suffix(".py").is_file() else None


def _imported(file: Path, name: str, package: str) -> frozenset[str]:
    """The modules of ``package`` that module ``name`` (source ``file``) may import anywhere
    in its code, with their parent packages (whose ``__init__`` runs first). Remembered per
    file, size and modification time, so a sweep parses each source once per process."""
    st = file.stat()
    key = (str(file), package, st.st_size, st.st_mtime_ns)
    if key not in _imports:
        _imports[key] = frozenset(_parse_imports(file, name, package))
    return _imports[key]


def _parse_imports(file: Path, name: str, package: str) -> set[str]:
    """:func:`_imported`, read from the source."""
    here = name if file.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(file.read_bytes(), str(file))):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = here.rsplit(".", node.level - 1)[0]
                module = f"{base}.{node.module}" if node.module else base
            else:
                module = node.module or ""
            found.add(module)
            found.update(f"{module}.{a.name}" for a in node.names)  # submodules by name
    out = set()
    for module in found:
        if module == package or module.startswith(package + "."):
            parts = module.split(".")
            out.update(".".join(parts[:i]) for i in range(1, len(parts) + 1))
    return out


def import_closure(modules: Iterable[str], package: str = "evchain") -> list[Path]:
    """The source files of ``modules`` (of ``package``) and of every module of ``package``
    they import, directly or through others, at the top or inside functions: what running
    them can execute of ``package``. Read from the sources (``modules`` are not imported); an
    import by a name computed at run time is not seen, so the modules given must be all that
    is called by name."""
    root = Path(importlib.import_module(package).__file__).parent
    todo = [".".join(m.split(".")[:i]) for m in modules
            if m == package or m.startswith(package + ".") for i in range(1, m.count(".") + 2)]
    seen: set[str] = set()
    files: set[Path] = set()
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        seen.add(name)
        file = _module_file(name, root)
        if file is not None:
            files.add(file)
            todo.extend(_imported(file, name, package) - seen)
    return sorted(files)


def files_stamp(files: Iterable[Path], folder: Path) -> str:
    """Short hash of ``files`` (their names relative to ``folder`` and bytes)."""
    h = hashlib.sha256()
    for f in sorted(files):
        h.update(f.relative_to(folder).as_posix().encode())
        h.update(f.read_bytes())
    return h.hexdigest()[:10]


def modules_stamp(modules: Iterable[str], package: str = "evchain") -> str:
    """Short hash of the source files of ``modules`` of ``package`` and of all they import
    (:func:`import_closure`)."""
    root = Path(importlib.import_module(package).__file__).parent
    return files_stamp(import_closure(modules, package), root)


def run_source_stamp(spec) -> str:
    """Hash of the evchain source files a run of ``spec`` can execute: the chain runner and
    its stages' filters with everything they import (:func:`import_closure`). With a filter
    from a plugin, every source file of evchain (a plugin may call into any of it)."""
    modules = [s.cls.__module__ for s in spec.stages]
    if not all(m.startswith("evchain.") for m in modules):
        return tree_stamp(Path(importlib.import_module("evchain").__file__).parent)
    return modules_stamp(["evchain.core.chain", *modules])


def source_stamps(registry, spec=None) -> dict[str, Any]:
    """Hash of the source of evchain and of each plugin distribution that registers filters
    (the top-level packages its filters come from). With ``spec``: evchain's hash covers the
    files a run of it can execute (:func:`run_source_stamp`), and only the plugins whose
    filters it uses count."""
    packages: dict[str, set[str]] = {"evchain": {"evchain"}}
    used = None if spec is None else {s.use for s in spec.stages}
    for name, info in registry.filters.items():
        if used is None or name in used:
            packages.setdefault(info.distribution, set()).add(
                info.cls.__module__.split(".")[0])
    out = {}
    for dist, tops in sorted(packages.items()):
        if dist == "evchain" and spec is not None:
            out[dist] = run_source_stamp(spec)
            continue
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
