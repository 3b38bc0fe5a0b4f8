import pytest

from evchain import ConfigError, EventPacket, Filter, WiringError, hookimpl
from evchain.core.config import pipeline_from_text
from evchain.core.registry import make_registry
from evchain.core.series import SeriesDef
from evchain.errors import PluginError
from tests.core import toy_filters


def load(text, registry, overrides=()):
    return pipeline_from_text(text, "p.yaml", registry, list(overrides))


GOOD = """\
name: demo
seed: 3
chain:
  - use: toy_source
    packets: 2
  - use: toy_flow
    gain: 2.0
"""


def test_good_pipeline_resolves_defaults(registry):
    spec = load(GOOD, registry)
    r = spec.resolved()
    assert r["seed"] == 3
    assert r["chain"][0] == {"use": "toy_source", "packets": 2, "events_per_packet": 100,
                             "fail_at_packet": None, "width": 32}
    assert r["chain"][1]["mode"] == "a"


@pytest.mark.parametrize("text, pattern", [
    ("chain:\n  - use: toy_sorce\n", r"p.yaml:2:\d+: toy_sorce.use: unknown filter 'toy_sorce'; "
                                    r"did you mean 'toy_source'"),
    ("chain:\n  - use: toy_source\n    pakets: 2\n",
     r"p.yaml:3:\d+: toy_source.pakets: unknown parameter .*did you mean 'packets'"),
    ("chain:\n  - use: toy_source\n    packets: many\n",
     r"p.yaml:3:14: toy_source.packets: .*integer.*expected int"),
    ("chain:\n  - use: toy_source\n  - use: toy_flow\n    gain: 20\n",
     r"p.yaml:4:\d+: toy_flow.gain: .*less than or equal to 10.*<= 10"),
    ("chain:\n  - use: toy_source\n  - use: toy_flow\n    mode: c\n",
     r"p.yaml:4:\d+: toy_flow.mode: .*'a' or 'b'"),
    ("chian: []\n", r"p.yaml:1:1: chian: unknown key; allowed: name"),
    ("name: x\n", r"missing key 'chain'"),
    ("chain: [\n", r"p.yaml:\d+:\d+: not valid YAML"),
    ("chain:\n  - packets: 2\n", r"p.yaml:2:\d+: chain\[0\]: missing key 'use'"),
    ("seed: abc\nchain:\n  - use: toy_source\n", r"p.yaml:1:7: seed: must be an integer"),
    ("chain: !!python/object:os.system {}\n", r"not valid YAML"),
])
def test_config_errors_name_place(registry, text, pattern):
    with pytest.raises(ConfigError, match=pattern):
        load(text, registry)


def test_every_problem_reported_at_once(registry):
    """A user fixes all mistakes in one round: each is listed with its own line."""
    text = ("chain:\n  - use: toy_source\n    packets: many\n    pakets: 2\n"
            "  - use: toy_flow\n    gain: 20\n  - use: toy_flwo\n")
    with pytest.raises(ConfigError) as info:
        load(text, registry)
    lines = str(info.value).splitlines()
    assert lines[0] == "4 problems:"
    assert [line.split(": ")[0].strip() for line in lines[1:]] == [
        "p.yaml:3:14", "p.yaml:4:13", "p.yaml:6:11", "p.yaml:7:10"]
    assert (info.value.line, info.value.key) == (3, "toy_source.packets")


@pytest.mark.parametrize("text, pattern", [
    ("chain:\n  - use: toy_flow\n", "first stage must be a source"),
    ("chain:\n  - use: toy_frames\n  - use: toy_flow\n",
     "'toy_flow' consumes EventPacket but 'toy_frames' before it produces FramePacket"),
    ("chain:\n  - use: toy_source\n  - use: toy_source\n", "can only be the first stage"),
])
def test_wiring_errors(registry, text, pattern):
    with pytest.raises(WiringError, match=pattern):
        load(text, registry)


def test_pass_through_keeps_type(registry):
    text = "chain:\n  - use: toy_source\n  - use: toy_writer\n  - use: toy_flow\n"
    assert [s.use for s in load(text, registry).stages][-1] == "toy_flow"


def test_overrides(registry):
    spec = load(GOOD, registry, ["toy_flow.gain=3.5", "toy_source.packets=5", "seed=9"])
    assert spec.stage("toy_flow").params.gain == 3.5
    assert spec.stage("toy_source").params.packets == 5
    assert spec.seed == 9


def test_override_adds_to_the_value_set_before(registry):
    """``STAGE.PARAM+=NUMBER`` adds to the pipeline's value or an earlier override's (a sweep's
    repeat shifting each cell's own value); without a number set before, or with a value that
    is not a number, it says so."""
    spec = load(GOOD, registry, ["toy_flow.gain+=0.25", "seed+=2"])
    assert spec.stage("toy_flow").params.gain == 2.25
    assert spec.seed == 5
    spec = load(GOOD, registry, ["toy_source.width=40", "toy_source.width+=-8"])
    assert spec.stage("toy_source").params.width == 32
    spec = load(GOOD, registry, ["toy_flow.gain=1e-3", "toy_flow.gain+=2e-3"])  # YAML strings
    assert spec.stage("toy_flow").params.gain == pytest.approx(3e-3)
    with pytest.raises(ConfigError, match=r"toy_source.width is not set"):
        load(GOOD, registry, ["toy_source.width+=1"])
    with pytest.raises(ConfigError, match=r"adds a number, got 'x'"):
        load(GOOD, registry, ["toy_flow.gain+=x"])
    with pytest.raises(ConfigError, match=r"toy_source.fail_at_packet is None"):
        load(GOOD, registry, ["toy_source.fail_at_packet=null", "toy_source.fail_at_packet+=1"])


def test_override_by_id_and_errors(registry):
    text = ("chain:\n  - use: toy_source\n  - use: toy_writer\n    id: a\n"
            "  - use: toy_writer\n    id: b\n")
    spec = load(text, registry, ["b.path=other.txt"])
    assert spec.stage("b").params.path == "other.txt"
    assert spec.stage("a").params.path == "count.txt"
    with pytest.raises(ConfigError, match="2 stages use 'toy_writer'"):
        load(text, registry, ["toy_writer.path=x"])
    with pytest.raises(ConfigError, match="no stage 'nope'"):
        load(GOOD, registry, ["nope.x=1"])
    with pytest.raises(ConfigError, match=r"--set toy_flow.gain=-1.*toy_flow.gain"):
        load(GOOD, registry, ["toy_flow.gain=-1"])
    with pytest.raises(ConfigError, match="STAGE.PARAM=VALUE"):
        load(GOOD, registry, ["gain"])


def test_unmet_series_need_names_stage_series_and_adders(registry):
    text = "chain:\n  - use: toy_source\n  - use: toy_writer\n  - use: toy_foe_reader\n"
    with pytest.raises(WiringError) as info:
        load(text, registry)
    assert str(info.value) == (
        "p.yaml:4:5: stage 'toy_foe_reader' needs series 'foe' (added by foe_fit or foe_lines or "
        "foe_map or toy_foe) but no stage before it adds it")
    assert info.value.line == 4


def test_series_need_met_upstream(registry):
    text = "chain:\n  - use: toy_source\n  - use: toy_foe\n  - use: toy_foe_reader\n"
    assert [s.use for s in load(text, registry).stages][-1] == "toy_foe_reader"
    # a stage after the reader does not count
    text = "chain:\n  - use: toy_source\n  - use: toy_foe_reader\n  - use: toy_foe\n"
    with pytest.raises(WiringError, match="p.yaml:3:5: stage 'toy_foe_reader' needs series"):
        load(text, registry)


class _OtherFoe(Filter):
    """Adds a 'foe' series of another dtype."""

    name = "toy_other_foe"
    consumes = EventPacket
    adds_series = (SeriesDef("foe", [("t", "i8"), ("x", "f8")]),)


class _Plugin:
    @hookimpl
    def evchain_filters(self):
        return [_OtherFoe]


def test_series_of_another_dtype_is_a_wiring_error():
    registry = make_registry(discover=False, plugins=(toy_filters, _Plugin()))
    text = "chain:\n  - use: toy_source\n  - use: toy_other_foe\n  - use: toy_foe_reader\n"
    with pytest.raises(WiringError, match=r"p.yaml:4:5: stage 'toy_foe_reader' reads series "
                                          r"'foe' with fields \(t, x, y, support, total, "
                                          r"wx_deg_s, wy_deg_s, wz_deg_s, rotation\) but stage "
                                          r"'toy_other_foe' \(line 3\) adds it with "
                                          r"fields \(t, x\)"):
        load(text, registry)


def test_series_declarations_must_be_series_definitions():
    class Bad(Filter):
        name = "toy_bad_series"
        consumes = EventPacket
        adds_series = ("foe",)

    class Plugin:
        @hookimpl
        def evchain_filters(self):
            return [Bad]

    with pytest.raises(PluginError, match="toy_bad_series.*adds_series must be a tuple of"):
        make_registry(discover=False, plugins=(Plugin(),))


def test_two_stages_of_one_filter_need_ids(registry):
    text = ("chain:\n  - use: toy_source\n  - use: toy_scorer\n  - use: toy_flow\n"
            "  - use: toy_scorer\n")
    with pytest.raises(ConfigError) as info:
        load(text, registry)
    assert str(info.value) == (
        "p.yaml:5:5: toy_scorer: a second stage of filter 'toy_scorer' (the first is at line 3); "
        "give each its own 'id:' (e.g. id: toy_scorer_2) so that overrides and metrics can tell "
        "them apart")
    text = text.replace("  - use: toy_flow\n", "  - use: toy_flow\n    id: toy_scorer\n")
    with pytest.raises(ConfigError, match=r"p.yaml:4:5: toy_scorer.id: id 'toy_scorer' is used "
                                          r"twice \(first at line 3\)"):
        load(text, registry)
    ok = text.replace("id: toy_scorer\n", "id: flow\n") + "    id: second\n"
    assert [s.id for s in load(ok, registry).stages] == [
        "toy_source", "toy_scorer", "flow", "second"]


def _laughs() -> str:
    lines, item = [], '"lol"'
    for name in "abcdefghi":
        lines.append(f"{name}: &{name} [{', '.join([item] * 9)}]")
        item = f"*{name}"
    return "\n".join([*lines, "chain: [{use: x, y: *i}]", ""])


BILLION_LAUGHS = _laughs()


def test_yaml_aliases_are_refused(registry):
    """Nested aliases expand a few hundred bytes into gigabytes: aliases are refused while the
    file is parsed, before any value is built."""
    assert len(BILLION_LAUGHS) < 600
    with pytest.raises(ConfigError, match=r"p.yaml:2:\d+: YAML alias \*a: aliases are not "
                                          "allowed"):
        load(BILLION_LAUGHS, registry)


def test_billion_laughs_fails_fast_on_the_command_line(tmp_path):
    import subprocess
    import sys

    p = tmp_path / "lol.yaml"
    p.write_text(BILLION_LAUGHS)
    # the timeout only guards the suite against the old hang; it measures nothing
    proc = subprocess.run([sys.executable, "-m", "evchain", "validate", str(p)],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "aliases are not allowed" in proc.stderr


def test_duplicate_key_is_an_error(registry):
    text = "chain:\n  - use: toy_source\n    packets: 2\n    packets: 3\n"
    with pytest.raises(ConfigError, match=r"p.yaml:4:5: packets: given twice \(first on line 3\)"):
        load(text, registry)
    with pytest.raises(ConfigError, match=r"p.yaml:2:1: seed: given twice"):
        load("seed: 1\nseed: 2\nchain:\n  - use: toy_source\n", registry)


@pytest.mark.parametrize("value", [".inf", "-.inf", ".nan"])
def test_non_finite_parameters_are_errors(value):
    text = f"chain:\n  - use: scene\n  - use: emulator\n    threshold_on: {value}\n"
    with pytest.raises(ConfigError, match=r"p.yaml:4:\d+: emulator.threshold_on: .*finite"):
        load(text, make_registry())


def test_input_files_are_relative_to_the_pipeline_file_and_must_exist(tmp_path, monkeypatch):
    from evchain.core.config import load_pipeline
    from evchain.io.aedat2 import write_aedat2
    from evchain.testing.synthetic import random_events

    (tmp_path / "data").mkdir()
    (tmp_path / "pipes").mkdir()
    write_aedat2(tmp_path / "data" / "ev.aedat", random_events(10, seed=1), chip="davis240")
    p = tmp_path / "pipes" / "p.yaml"
    p.write_text("chain:\n  - use: aedat\n    path: ../data/ev.aedat\n")
    monkeypatch.chdir(tmp_path / "data")  # another folder: the file's folder counts
    spec = load_pipeline(p, make_registry())
    assert spec.stages[0].params.path == str(tmp_path / "data" / "ev.aedat")
    assert spec.resolved()["chain"][0]["path"] == str(tmp_path / "data" / "ev.aedat")
    # --set values are relative to the current folder
    spec = load_pipeline(p, make_registry(), ["aedat.path=ev.aedat"])
    assert spec.stages[0].params.path == str(tmp_path / "data" / "ev.aedat")
    p.write_text("chain:\n  - use: aedat\n    path: ev.aedat\n")
    with pytest.raises(ConfigError, match=r"p.yaml:3:11: aedat.path: input not found: "
                                          rf"{tmp_path}/pipes/ev.aedat \(relative to the folder"):
        load_pipeline(p, make_registry())
    with pytest.raises(ConfigError, match=r"--set aedat.path=nope.aedat: aedat.path: input not "
                                          r"found: .*nope.aedat \(relative to the current"):
        load_pipeline(p, make_registry(), ["aedat.path=nope.aedat"])


def test_validate_reports_a_missing_input_file(tmp_path, capsys):
    from evchain import cli

    p = tmp_path / "p.yaml"
    p.write_text("chain:\n  - use: aedat\n    path: missing.aedat\n  - use: lk_flow\n"
                 "  - use: flow_scorer\n    ground_truth: gt.mat\n")
    assert cli.main(["validate", str(p)]) == 2
    err = capsys.readouterr().err
    assert "2 problems" in err and "aedat.path: input not found" in err
    assert "flow_scorer.ground_truth: input not found" in err


@pytest.mark.parametrize("path", ["../../escape.aedat", "/tmp/abs.aedat", "..", "."])
def test_outputs_must_stay_inside_the_run_folder(path):
    text = f"chain:\n  - use: scene\n  - use: emulator\n  - use: aedat_writer\n    path: {path}\n"
    with pytest.raises(ConfigError, match=r"p.yaml:5:11: aedat_writer.path: .* must name a file "
                                          "or folder inside the run folder"):
        load(text, make_registry())
    ok = text.replace(f"path: {path}", "path: a/../b.aedat")
    assert load(ok, make_registry()).stages[2].params.path == "a/../b.aedat"


def test_path_declarations_name_parameters():
    class Bad(Filter):
        name = "bad_paths"
        produces = EventPacket
        input_paths = ("file",)

    class Plugin:
        @hookimpl
        def evchain_filters(self):
            return [Bad]

    with pytest.raises(PluginError, match="input_paths must be a tuple of names of its"):
        make_registry(discover=False, plugins=(Plugin(),))
