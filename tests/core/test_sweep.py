import pytest

from evchain import ConfigError
from evchain.sweep import load_sweep, run_sweep

BASE = "chain:\n  - use: toy_source\n  - use: toy_writer\n"


def write(tmp_path, sweep_text):
    (tmp_path / "base.yaml").write_text(BASE)
    p = tmp_path / "s.yaml"
    p.write_text(sweep_text)
    return p


def test_one_at_a_time_and_cache(tmp_path, registry):
    p = write(tmp_path, "base: base.yaml\nset: [toy_source.packets=2]\nvary:\n"
                        "  toy_source.events_per_packet: [5, 7]\n  toy_source.width: [40]\n"
                        "report: [toy.count, toy.missing]\n")
    sweep = load_sweep(p)
    assert [v.label for v in sweep.variations] == [
        "toy_source.events_per_packet=5", "toy_source.events_per_packet=7", "toy_source.width=40"]
    rows = run_sweep(sweep, tmp_path / "out", workers=1, registry=registry, echo=lambda s: None)
    assert [r["toy.count"] for r in rows] == [10, 14, 200]
    assert all(r["toy.missing"] is None and not r["cached"] for r in rows)
    again = run_sweep(sweep, tmp_path / "out", workers=1, registry=registry, echo=lambda s: None)
    assert all(r["cached"] for r in again)
    assert (tmp_path / "out" / "sweep.md").read_text().startswith("| variation |")


def test_grid(tmp_path):
    p = write(tmp_path, "base: base.yaml\nmode: grid\nvary:\n  a.x: [1, 2]\n  b.y: [3, 4, 5]\n")
    assert len(load_sweep(p).variations) == 6


@pytest.mark.parametrize("text, pattern", [
    ("base: base.yaml\n", "needs 'base'"),
    ("base: base.yaml\nvary: {a.b: []}\n", r"s.yaml:2:7: vary: must map"),
    ("base: base.yaml\nvary: {a.b: [1]}\nmode: all\n", "mode: must be"),
    ("base: base.yaml\nvary: {a.b: [1]}\nvarry: 1\n", "varry: unknown key"),
])
def test_sweep_errors(tmp_path, text, pattern):
    with pytest.raises(ConfigError, match=pattern):
        load_sweep(write(tmp_path, text))


def test_bad_variation_fails_before_running(tmp_path, registry):
    p = write(tmp_path, "base: base.yaml\nvary:\n  toy_source.packets: [1, -3]\n")
    with pytest.raises(ConfigError, match="toy_source.packets"):
        run_sweep(load_sweep(p), tmp_path / "out", workers=1, registry=registry)
    assert not (tmp_path / "out").exists()


def test_joint_keys(tmp_path, registry):
    p = write(tmp_path, "base: base.yaml\nvary:\n  toy_source.packets,toy_source.width: "
                        "[[1, 20], [2, 30]]\nreport: [toy.count]\n")
    sweep = load_sweep(p)
    assert sweep.variations[1].overrides == ["toy_source.packets=2", "toy_source.width=30"]
    rows = run_sweep(sweep, tmp_path / "out", workers=1, registry=registry, echo=lambda s: None)
    assert [r["toy.count"] for r in rows] == [100, 200]
    import csv  # the joint key's label holds commas: the CSV must still read back

    table = list(csv.DictReader((tmp_path / "out" / "sweep.csv").open()))
    assert [r["variation"] for r in table] == [v.label for v in sweep.variations]
    assert [int(r["toy.count"]) for r in table] == [100, 200]
    bad = write(tmp_path, "base: base.yaml\nvary:\n  a.b,c.d: [[1]]\n")
    with pytest.raises(ConfigError, match="list of 2 values"):
        load_sweep(bad)
