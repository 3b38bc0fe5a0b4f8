import subprocess
import sys

import pytest

from evchain import cli


@pytest.fixture
def pipeline(tmp_path):
    p = tmp_path / "p.yaml"
    p.write_text("chain:\n  - use: aedat_readerr\n")
    return p


def test_user_mistake_exits_2_without_traceback(pipeline, capsys):
    assert cli.main(["validate", str(pipeline)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("evchain: error: ") and f"{pipeline}:2:" in err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_debug_shows_traceback(pipeline, capsys):
    assert cli.main(["--debug", "validate", str(pipeline)]) == 2
    assert "Traceback" in capsys.readouterr().err


def test_missing_pipeline_file(tmp_path, capsys):
    assert cli.main(["run", str(tmp_path / "nope.yaml")]) == 2
    assert "pipeline file not found" in capsys.readouterr().err


def test_unknown_filter_in_filters_command(capsys):
    assert cli.main(["filters", "no_such_filter"]) == 2


def test_console_script_entry():
    out = subprocess.run([sys.executable, "-m", "evchain.cli", "plugins"], capture_output=True,
                         text=True, check=True).stdout
    assert out.startswith("evchain")


def test_docs_generated(tmp_path, capsys):
    assert cli.main(["docs", "--out", str(tmp_path)]) == 0
    filters = (tmp_path / "filters.md").read_text()
    assert "## `hdf5_writer`" in filters and "| `compression` | bool | `True` |" in filters
    assert "## `evchain_filters()" in (tmp_path / "hooks.md").read_text()


def test_filters_lists_and_describes(capsys):
    assert cli.main(["filters"]) == 0
    assert "hdf5_writer" in capsys.readouterr().out
    assert cli.main(["filters", "hdf5"]) == 0
    out = capsys.readouterr().out
    assert "packet_us: int = 10000  [>= 1]" in out and "slice duration" in out


def test_validate_rejects_ttc_without_foe(tmp_path, capsys):
    p = tmp_path / "x.yaml"
    p.write_text("chain:\n  - use: scene\n  - use: emulator\n  - use: lk_flow\n"
                 "  - use: ttc\n  - use: foe_ttc_scorer\n")
    assert cli.main(["validate", str(p)]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (f"evchain: error: {p}:5:5: stage 'ttc' needs series 'foe' (added by foe_fit "
                   "or foe_lines or foe_map) but no stage before it adds it")
    p.write_text(p.read_text().replace("  - use: ttc\n", "  - use: foe_map\n  - use: ttc\n"))
    assert cli.main(["validate", str(p)]) == 0
    assert "ok (6 stages" in capsys.readouterr().out


def test_filters_shows_series(capsys):
    assert cli.main(["filters", "ttc"]) == 0
    out = capsys.readouterr().out
    assert ("series:\n  needs foe (t, x, y, support, total)\n"
            "  adds ttc (t, tau_s, cluster, x, y, support)\n"
            "  adds ttc_clusters (t, cluster, x, y, size_px, tau_s, support, ground_ratio)\n"
            in out)
