"""Sweeps on Dask: a LocalCluster, and a scheduler with two workers started by hand in another
folder, give the same table as the local process pool (needs ``evchain[dask]``)."""

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytest.importorskip("dask.distributed")

from evchain.sweep import load_sweep, run_sweep  # noqa: E402
from tests.core.test_sweep import file_sweep  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
SAME = ("variation", "run", "status", "aedat_writer.events")  # all but timing and cache


def table(rows):
    return [{k: r[k] for k in SAME} for r in rows]


@pytest.fixture
def sweep(tmp_path):
    p = file_sweep(tmp_path)
    p.write_text("base: ../pipes/p.yaml\nvary:\n  refractory.period_us: [100, 3000, 1000000]\n"
                 "report: [aedat_writer.events]\n")
    return load_sweep(p)


@pytest.fixture
def local_table(sweep, tmp_path):
    rows = run_sweep(sweep, tmp_path / "pool", workers=2, echo=lambda s: None)
    assert [r["status"] for r in rows] == ["ok"] * 3
    return table(rows)


def _env():
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), *filter(None, [env.get("PYTHONPATH")])])
    return env


def test_local_cluster_gives_the_local_table(sweep, local_table, tmp_path):
    from dask.distributed import LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                      dashboard_address=None) as cluster:
        rows = run_sweep(sweep, tmp_path / "cluster", scheduler=cluster.scheduler_address,
                         echo=lambda s: None)
    assert table(rows) == local_table
    assert all((tmp_path / "cluster" / r["run"] / "kept.aedat").is_file() for r in rows)


def test_scheduler_and_two_workers_started_by_hand(sweep, local_table, tmp_path, monkeypatch):
    """``dask scheduler`` and two ``dask worker`` processes on localhost, the workers in a
    folder of their own: paths reach them absolute, and the run folders land in --out."""
    from dask.distributed import Client

    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    info = tmp_path / "scheduler.json"
    dask = [sys.executable, "-m", "dask"]
    procs = [subprocess.Popen([*dask, "scheduler", "--host", "127.0.0.1", "--port", "0",
                               "--no-dashboard", "--scheduler-file", str(info)],
                              cwd=elsewhere, env=_env(), stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL)]
    try:
        deadline = time.monotonic() + 60
        while not info.exists() and time.monotonic() < deadline:
            time.sleep(0.1)
        assert info.exists(), "the scheduler did not start"
        for _ in range(2):
            procs.append(subprocess.Popen(
                [*dask, "worker", "--scheduler-file", str(info), "--nworkers", "1",
                 "--nthreads", "1", "--no-dashboard", "--local-directory", str(elsewhere)],
                cwd=elsewhere, env=_env(), stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL))
        with Client(scheduler_file=str(info), timeout=60) as client:
            client.wait_for_workers(2, timeout=120)
            address = client.scheduler.address
        lines = []
        monkeypatch.chdir(tmp_path)  # a relative --out is made absolute before work is sent
        rows = run_sweep(sweep, "by-hand", scheduler=address, echo=lines.append)
    finally:
        for proc in reversed(procs):
            proc.terminate()
        for proc in procs:
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
    assert table(rows) == local_table
    assert len(lines) == 3 and all(line.lstrip().startswith("[") for line in lines)
    assert all((tmp_path / "by-hand" / r["run"] / "report.json").is_file() for r in rows)
    assert not list(elsewhere.rglob("report.json"))  # nothing landed in the workers' folder
