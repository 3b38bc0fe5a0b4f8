"""What machine a measurement ran on: cores, CPU model, load, software versions, commit."""

from __future__ import annotations

import os
import platform
import subprocess
from pathlib import Path
from typing import Any


def cpu_model() -> str:
    """The CPU's model name (from /proc/cpuinfo on Linux), else what ``platform`` says."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def available_memory_bytes() -> int | None:
    """Memory a new allocation can get without swapping (Linux ``MemAvailable``), else the
    physical memory; None when neither is known."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, ValueError, OSError):
        return None


def git_commit(path: Path | None = None) -> str | None:
    """Short commit of the checkout holding ``path`` (default: this package), with ``+`` when
    the working tree has changes; None outside a git checkout."""
    where = str(path or Path(__file__).resolve().parent)
    try:
        head = subprocess.run(["git", "-C", where, "rev-parse", "--short=10", "HEAD"],
                              capture_output=True, text=True, timeout=10)
        if head.returncode != 0:
            return None
        dirty = subprocess.run(["git", "-C", where, "status", "--porcelain",
                                "--untracked-files=no"], capture_output=True, text=True,
                               timeout=10)
        return head.stdout.strip() + ("+" if dirty.stdout.strip() else "")
    except (OSError, subprocess.SubprocessError):
        return None


def machine_info() -> dict[str, Any]:
    """Cores, CPU model, 1-minute load average, Python, numpy, numba and evchain versions and
    the commit: what a reader needs to judge a speed or to repeat a measurement."""
    import numpy as np

    from evchain import __version__

    try:
        from importlib.metadata import version

        numba = version("numba")
    except Exception:  # noqa: BLE001 - numba is a dependency; report rather than fail
        numba = None
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    return {"cores": os.cpu_count(), "cpu": cpu_model(), "load": load,
            "python": platform.python_version(), "numpy": np.__version__, "numba": numba,
            "evchain": __version__, "commit": git_commit()}
