"""Cached benchmark inputs are named after the code that made them."""

import evchain.bench as bench


def test_source_stamp_follows_the_sources(tmp_path, monkeypatch):
    (tmp_path / "sim").mkdir()
    (tmp_path / "sim" / "a.py").write_text("x = 1\n")
    (tmp_path / "k.py").write_text("y = 2\n")
    monkeypatch.setattr(bench, "_PACKAGE", tmp_path)
    before = bench.source_stamp("sim", "k.py")
    assert before == bench.source_stamp("sim", "k.py")          # deterministic
    assert before != bench.source_stamp("sim")                   # every source counts
    (tmp_path / "sim" / "a.py").write_text("x = 3\n")            # an edit inside a folder
    assert bench.source_stamp("sim", "k.py") != before
    (tmp_path / "sim" / "a.py").write_text("x = 1\n")
    assert bench.source_stamp("sim", "k.py") == before
    (tmp_path / "sim" / "b.py").write_text("")                   # a new module
    assert bench.source_stamp("sim", "k.py") != before


def test_simulator_sources_exist():
    for rel in bench.SIMULATOR_SOURCES:
        assert (bench._PACKAGE / rel).exists(), rel
    assert len(bench.source_stamp(*bench.SIMULATOR_SOURCES)) == 10
