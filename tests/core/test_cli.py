import subprocess
import sys

import pytest

from evchain import cli
from evchain.errors import ConfigError


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
    assert "## `hdf5_writer`" in filters
    assert "| `compression` | Literal['blosc', 'gzip', 'none'] | `'blosc'` |" in filters
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
    assert ("series:\n  needs foe (t, x, y, support, total, wx_deg_s, wy_deg_s, wz_deg_s, "
            "rotation)\n"
            "  adds ttc (t, tau_s, cluster, x, y, support)\n"
            "  adds ttc_clusters (t, cluster, x, y, size_px, tau_s, support, ground_ratio)\n"
            in out)


def test_debug_after_the_subcommand(pipeline, capsys):
    assert cli.main(["validate", str(pipeline), "--debug"]) == 2
    assert "Traceback" in capsys.readouterr().err
    assert cli.main(["validate", "--debug", str(pipeline)]) == 2
    assert "Traceback" in capsys.readouterr().err


def test_version_and_python_m_evchain():
    from evchain import __version__

    for cmd in (["-m", "evchain", "--version"], ["-m", "evchain.cli", "--version"]):
        out = subprocess.run([sys.executable, *cmd], capture_output=True, text=True, check=True)
        assert out.stdout.strip() == f"evchain {__version__}"
    out = subprocess.run([sys.executable, "-m", "evchain", "plugins"], capture_output=True,
                         text=True, check=True).stdout
    assert out.startswith("evchain")


def test_closed_stdout_is_no_traceback():
    """`evchain filters | head -1`: the reader went away; no BrokenPipe traceback."""
    import os

    read, write = os.pipe()
    os.close(read)  # every write to the pipe fails with EPIPE
    try:
        proc = subprocess.run([sys.executable, "-m", "evchain", "filters"], stdout=write,
                              stderr=subprocess.PIPE, text=True)
    finally:
        os.close(write)
    assert proc.stderr == "" and proc.returncode == 141


def test_package_ships_license_and_py_typed():
    from pathlib import Path

    import evchain

    assert (Path(evchain.__file__).parent / "py.typed").is_file()
    text = (Path(evchain.__file__).parents[1] / "LICENSE").read_text()
    assert text.startswith("MIT License") and "evchain developers" in text


def _aedat_pipeline(tmp_path):
    from evchain.io.aedat2 import write_aedat2
    from evchain.testing.synthetic import random_events

    write_aedat2(tmp_path / "ev.aedat", random_events(50, seed=1), chip="davis240")
    p = tmp_path / "p.yaml"
    p.write_text("chain:\n  - use: aedat\n    path: ev.aedat\n  - use: aedat_writer\n")
    return p


def test_out_that_is_a_file_is_a_user_error(tmp_path, capsys):
    p = _aedat_pipeline(tmp_path)
    (tmp_path / "taken").write_text("x")
    assert cli.main(["run", str(p), "--out", str(tmp_path / "taken"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert f"--out: {tmp_path / 'taken'} exists and is not a folder" in err
    assert "Traceback" not in err and "bug" not in err
    assert cli.main(["run", str(p), "--out", str(tmp_path / "taken" / "sub"),
                     "--no-progress"]) == 2
    assert "cannot create the run folder" in capsys.readouterr().err


@pytest.mark.skipif(not hasattr(__import__("os"), "geteuid") or __import__("os").geteuid() == 0,
                    reason="permissions do not stop root")
def test_unwritable_out_and_unreadable_input_are_user_errors(tmp_path, capsys):
    p = _aedat_pipeline(tmp_path)
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o500)
    assert cli.main(["run", str(p), "--out", str(locked), "--no-progress"]) == 2
    assert "cannot write into the run folder" in capsys.readouterr().err
    (tmp_path / "ev.aedat").chmod(0)
    assert cli.main(["validate", str(p)]) == 2
    assert "input not readable" in capsys.readouterr().err


def test_unreadable_input_in_a_filter_is_a_user_error(tmp_path, capsys, monkeypatch):
    """An OSError about a file (e.g. permission denied while the source opens it) names the
    file and exits 2; it is no bug."""
    import evchain.io.aedat2 as aedat2

    p = _aedat_pipeline(tmp_path)

    def refuse(path, *args, **kwargs):
        raise PermissionError(13, "Permission denied", str(path))

    monkeypatch.setattr(aedat2, "open", refuse, raising=False)
    assert cli.main(["run", str(p), "--out", str(tmp_path / "run"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert (f"filter 'aedat' (aedat) failed in setup: {tmp_path / 'ev.aedat'}: Permission denied"
            in err)
    assert "bug" not in err and "Traceback" not in err


def test_too_large_a_camera_is_refused_before_rendering(tmp_path, capsys, monkeypatch):
    import evchain.machine
    from evchain.filters.scene import SceneSource, check_memory

    monkeypatch.setattr(evchain.machine, "available_memory_bytes", lambda: 24 * 2**30)
    p = tmp_path / "big.yaml"
    p.write_text("chain:\n  - use: scene\n    width: 8192\n    height: 8192\n"
                 "  - use: emulator\n")
    assert cli.main(["run", str(p), "--out", str(tmp_path / "run"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert ("scene.width: a 8192x8192 camera needs about 32.0 GiB for the frames of one packet "
            "(max_frames_per_packet 64 float32 frames, rendered and stacked), more than the "
            "24.0 GiB of memory available" in err)
    assert "bug" not in err
    fits = SceneSource.Params(width=8192, height=8192, max_frames_per_packet=16)
    check_memory(fits)  # 8 GiB: accepted
    with pytest.raises(ConfigError, match="x4 for the packets rendered ahead"):
        check_memory(SceneSource.Params(width=8192, height=8192, max_frames_per_packet=16,
                                        threads=0))
