"""The code a run can execute (provenance.import_closure) and the source hashes built on it."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from evchain.core.config import load_pipeline
from evchain.provenance import import_closure, run_source_stamp, source_stamps

ROOT = Path(__file__).resolve().parents[2]


def test_closure_follows_imports_anywhere_and_nothing_else(tmp_path, monkeypatch):
    """Imports at the top and inside functions, absolute and relative, of modules and of names
    from them, through a cycle; a module nobody imports stays out, and so does anything
    outside the package."""
    pkg = tmp_path / "pkgx"
    (pkg / "sub").mkdir(parents=True)
    files = {
        "__init__.py": "",
        "a.py": "import json\n\ndef f():\n    from pkgx.sub import b\n    return b.g()\n",
        "sub/__init__.py": "",
        "sub/b.py": "from . import c\nfrom ..d import X\n\ndef g():\n    return X\n",
        "sub/c.py": "import pkgx.a\n",
        "d.py": "X = 1\n",
        "unused.py": "import pkgx.d\n",
    }
    for name, text in files.items():
        (pkg / name).write_text(text)
    monkeypatch.syspath_prepend(str(tmp_path))
    got = {f.relative_to(pkg).as_posix() for f in import_closure(["pkgx.a"], "pkgx")}
    assert got == {"__init__.py", "a.py", "sub/__init__.py", "sub/b.py", "sub/c.py", "d.py"}
    assert {f.name for f in import_closure(["pkgx.d"], "pkgx")} == {"__init__.py", "d.py"}


def _closure(spec):
    files = import_closure(["evchain.core.chain", *[s.cls.__module__ for s in spec.stages]])
    return {f.relative_to(ROOT / "evchain").as_posix() for f in files}


def test_a_recording_and_a_flow_chain_depend_on_their_own_code(registry):
    record = load_pipeline(ROOT / "pipelines/reference.yaml", registry, [])
    lk = load_pipeline(ROOT / "pipelines/reference-lk.yaml", registry, [])
    rec_files, lk_files = _closure(record), _closure(lk)
    assert {"kernels/emulator.py", "kernels/scene_render.py", "filters/scene.py",
            "core/chain.py", "kernels/aedat2.py"} <= rec_files
    assert not {"kernels/lk_flow.py", "kernels/ttc.py", "kernels/plane_flow.py",
                "filters/ttc.py", "filters/foe_fit.py"} & rec_files
    assert {"kernels/lk_flow.py", "kernels/ttc.py", "kernels/foe_fit.py"} <= lk_files
    assert "kernels/plane_flow.py" not in lk_files
    assert run_source_stamp(record) != run_source_stamp(lk)
    assert source_stamps(registry, record)["evchain"] == run_source_stamp(record)
    assert source_stamps(registry)["evchain"] != run_source_stamp(record)   # the whole tree


SCRIPT = """
import sys, tempfile
from pathlib import Path
from evchain.core.chain import run_pipeline
from evchain.core.config import load_pipeline
from evchain.core.registry import make_registry
from evchain.provenance import import_closure
registry = make_registry()
before = {m for m in sys.modules if m.startswith("evchain")}
spec = load_pipeline(Path(sys.argv[1]), registry, sys.argv[2:])
with tempfile.TemporaryDirectory() as tmp:
    run_pipeline(spec, registry, Path(tmp) / "run")
closure = {str(f) for f in import_closure(
    ["evchain.core.chain", *[s.cls.__module__ for s in spec.stages]])}
loaded = {m for m in sys.modules if m.startswith("evchain")} - before
print(sorted(m for m in loaded if getattr(sys.modules[m], "__file__", None) not in closure))
"""


@pytest.mark.parametrize("pipeline", ["reference-lk.yaml", "reference-plane.yaml"])
def test_every_module_a_run_loads_is_in_its_closure(pipeline):
    """In a fresh interpreter: the evchain modules a short run loads beyond the registry's
    (lazy imports inside the filters and kernels, the scorers' plots) are all in the static
    closure, so no code the run executed escapes its source hash."""
    out = subprocess.run(
        [sys.executable, "-c", SCRIPT, str(ROOT / "pipelines" / pipeline),
         "scene.duration_s=0.05"], capture_output=True, text=True, check=True, cwd=ROOT)
    assert out.stdout.strip().splitlines()[-1] == "[]"
