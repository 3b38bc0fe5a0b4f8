"""Cached benchmark inputs: named after the code and parameters that make them, never
substituted, made by ``evchain bench --prepare``."""

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

import evchain.bench_cache as cache
import evchain.cli as cli
from evchain.bench import BenchRow
from evchain.bench_cache import BenchInput, Workload
from evchain.errors import MissingBenchInput
from evchain.provenance import import_closure, modules_stamp


@pytest.fixture(autouse=True)
def cache_dir(tmp_path, monkeypatch):
    folder = tmp_path / "cache"
    monkeypatch.setenv("EVCHAIN_CACHE", str(folder))
    return folder


def test_modules_stamp_follows_what_they_import(tmp_path, monkeypatch):
    """An input's code hash covers its modules and all they import: an edit there gives
    another hash, an edit of a module they do not import does not."""
    pkg = tmp_path / "pkgy"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "maker.py").write_text("def make():\n    from pkgy import kernel\n    return kernel.k\n")
    (pkg / "kernel.py").write_text("k = 1\n")
    (pkg / "other.py").write_text("o = 1\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    before = modules_stamp(["pkgy.maker"], "pkgy")
    assert len(before) == 10 and before == modules_stamp(["pkgy.maker"], "pkgy")
    (pkg / "other.py").write_text("o = 2\n")
    assert modules_stamp(["pkgy.maker"], "pkgy") == before
    (pkg / "kernel.py").write_text("k = 2\n")
    assert modules_stamp(["pkgy.maker"], "pkgy") != before


def test_drive_inputs_cover_the_kernels_that_make_them():
    """The drive's events depend on the renderer's and emulator's kernels; a flow input on its
    flow's (checked on the modules' import closure that the hashes cover)."""
    from evchain.benchmarks.drive_inputs import EVENT_SOURCES

    files = {f.relative_to(Path(cache.__file__).parent).as_posix()
             for f in import_closure(EVENT_SOURCES)}
    assert {"kernels/scene_render.py", "kernels/scene_bands.py", "kernels/emulator.py",
            "kernels/veclog.py", "sim/drive.py"} <= files
    assert "kernels/lk_flow.py" not in files


def test_cache_folder_is_evchain_cache(cache_dir, monkeypatch):
    assert cache.cache_dir() == cache_dir
    monkeypatch.delenv("EVCHAIN_CACHE")
    assert cache.cache_dir().name.lower() == "evchain"


def fake_input(n: int, made: list, sources=("evchain.bench_cache",), needs=()) -> BenchInput:
    def make():
        made.append(n)
        return {"values": np.arange(n)}
    return BenchInput("fake", f"fake input of {n}", {"n": n}, sources, make, needs)


def test_the_hash_covers_parameters_code_and_needs(tmp_path, monkeypatch):
    made: list = []
    a = fake_input(3, made)
    assert a.key == fake_input(3, made).key
    assert a.key != fake_input(4, made).key                                  # parameters
    assert a.key != fake_input(3, made, sources=("evchain.bench",)).key           # code
    assert a.key != fake_input(3, made, needs=(fake_input(1, made),)).key    # inputs
    assert a.path.name == f"fake-{a.key}.npz" and a.describe().endswith(f"@{a.key}")


def test_prepare_writes_atomically_and_once(cache_dir):
    made: list = []
    base = fake_input(2, made)
    top = fake_input(5, made, needs=(base,))
    with pytest.raises(MissingBenchInput, match="--prepare"):
        top.load()
    assert top.prepare(echo=lambda s: None) is True
    assert made == [2, 5]                                      # what it needs comes first
    assert top.prepare(echo=lambda s: None) is False and made == [2, 5]
    assert np.array_equal(top.load()["values"], np.arange(5))
    assert sorted(p.name for p in cache_dir.iterdir()) == sorted([base.path.name, top.path.name])


def test_a_failed_make_leaves_no_entry(cache_dir):
    def make():
        raise RuntimeError("boom")
    inp = BenchInput("fake", "fails", {}, ("evchain.bench_cache",), make)
    with pytest.raises(RuntimeError):
        inp.prepare(echo=lambda s: None)
    assert not inp.exists()


class _Unwritable:
    def __array__(self, *_args, **_kwargs):
        raise RuntimeError("cannot convert")


def test_a_failed_write_leaves_only_the_partial_file(cache_dir):
    inp = BenchInput("fake", "unwritable", {}, ("evchain.bench_cache",),
                     lambda: {"values": _Unwritable()})
    with pytest.raises(RuntimeError, match="cannot convert"):
        inp.prepare(echo=lambda s: None)
    assert not inp.exists()
    assert inp.path.with_name(inp.path.name + ".partial").exists()


def _workloads(made: list):
    """``fake-input`` reads a cached input (3 values, 2 with quick); ``fake-plain`` reads none."""
    def inputs(quick):
        return [fake_input(2 if quick else 3, made)]

    def rows(quick):
        inp = inputs(quick)[0]
        values = inp.load()["values"]
        return [BenchRow("fake-input", "fake", float(len(values)), "values/s",
                         data=inp.describe())]

    def plain(quick):
        return [BenchRow("fake-plain", "fake", 1.0, "1/s", data="nothing")]

    return {"fake-input": Workload(rows, inputs), "fake-plain": plain}


@pytest.fixture
def fake_cli(monkeypatch):
    made: list = []
    monkeypatch.setattr(cli, "_registry", lambda: SimpleNamespace(workloads=_workloads(made)))
    return made


def test_missing_input_exits_2_naming_prepare(fake_cli, tmp_path, capsys):
    out = tmp_path / "out.json"
    assert cli.main(["bench", "fake", "--json", str(out)]) == 2
    cap = capsys.readouterr()
    assert "evchain bench --prepare fake\n" in cap.err + "\n"
    assert "fake-input needs fake input of 3 @" in cap.err
    assert "fake-plain" not in cap.out                         # nothing ran
    assert not out.exists() and fake_cli == []


def test_prepare_then_run_reports_the_hash(fake_cli, tmp_path, capsys, cache_dir):
    assert cli.main(["bench", "--prepare", "fake-input"]) == 0
    assert fake_cli == [3]
    assert "run the rows with: evchain bench fake-input" in capsys.readouterr().out
    out = tmp_path / "out.json"
    assert cli.main(["bench", "fake", "--json", str(out), "--repeat", "2"]) == 0
    rows = json.loads(out.read_text())
    key = fake_input(3, []).key
    assert [(r["workload"], r["repeat"]) for r in rows] == [
        ("fake-input", 0), ("fake-plain", 0), ("fake-input", 1), ("fake-plain", 1)]
    got = rows[0]
    assert got["data"] == f"fake input of 3 @{key}" and got["throughput"] == 3.0
    assert got["command"] == "evchain bench --exact fake-input" and got["params_from"] is None
    assert rows[1]["command"] == "evchain bench --exact fake-plain"
    assert f"@{key}" in capsys.readouterr().out                 # shown in the table too
    assert fake_cli == [3]                                     # running made nothing


def test_quick_and_full_inputs_do_not_stand_in_for_each_other(fake_cli, capsys):
    assert cli.main(["bench", "--prepare", "fake-input", "--quick"]) == 0
    assert cli.main(["bench", "fake-input"]) == 2
    assert "evchain bench --prepare fake-input\n" in capsys.readouterr().err + "\n"
    assert cli.main(["bench", "fake-input", "--quick"]) == 0
    assert "fake input of 2 @" in capsys.readouterr().out


def test_exact_names_select_one_workload(fake_cli, tmp_path, capsys):
    """``fake`` starts both names; ``--exact fake-plain`` (a row's ``command``) runs one."""
    out = tmp_path / "out.json"
    assert cli.main(["bench", "--exact", "fake-plain", "--json", str(out)]) == 0
    [row] = json.loads(out.read_text())
    assert row["workload"] == "fake-plain" and row["command"] == "evchain bench --exact fake-plain"
    assert cli.main(["bench", "--exact", "fake"]) == 2
    assert "no benchmark workload is ['fake']" in capsys.readouterr().err
    assert cli.main(["bench", "--exact", "fake-input"]) == 2
    assert "evchain bench --prepare --exact fake-input\n" in capsys.readouterr().err + "\n"


def test_prepare_writes_no_json_and_repeat_must_count(fake_cli, tmp_path, capsys):
    assert cli.main(["bench", "--prepare", "fake", "--json", str(tmp_path / "o.json")]) == 2
    assert cli.main(["bench", "fake-plain", "--repeat", "0"]) == 2
    assert "--repeat 0" in capsys.readouterr().err


def test_rows_must_say_what_they_ran_on(monkeypatch):
    from evchain import bench

    silent = {"silent": lambda quick: [BenchRow("silent", "x", 1.0, "1/s")]}
    with pytest.raises(ValueError, match="BenchRow.data"):
        bench.run(silent, echo=lambda s: None)


def test_extra_keys_cannot_shadow_fields():
    row = BenchRow("w", "s", 1.0, "1/s", extra={"data": "elsewhere"}, data="here")
    with pytest.raises(ValueError, match="clash"):
        row.as_dict()


def test_the_reference_rows_never_run_on_something_else(cache_dir, capsys):
    """An empty cache, or one holding other drives, stops ``flow-lk-reference`` before any row
    (there once was a synthetic stand-in under that name)."""
    cache_dir.mkdir()
    np.savez(cache_dir / "drive-events-0123456789.npz", x=np.zeros(1))
    assert cli.main(["bench", "flow-lk-reference", "--quick"]) == 2
    cap = capsys.readouterr()
    assert "flow-lk-" not in cap.out
    assert "evchain bench --prepare flow-lk-reference --quick" in cap.err
    assert "reference-drive 0-2 s @" in cap.err
