"""Registers evchain's own filters through the same hook as third-party plugins.

Every module of ``evchain.filters`` and ``evchain.io`` is imported (they import no numba at
module level) and each :class:`Filter` subclass with a ``name`` defined there is registered.
"""

from __future__ import annotations

import importlib
import inspect
import pkgutil

from evchain.core.filter import Filter
from evchain.hookspecs import hookimpl

PACKAGES = ("evchain.filters", "evchain.io")


@hookimpl
def evchain_filters() -> list[type[Filter]]:
    found = []
    for package_name in PACKAGES:
        package = importlib.import_module(package_name)
        for info in pkgutil.iter_modules(package.__path__):
            if info.name.startswith("_"):
                continue
            module = importlib.import_module(f"{package_name}.{info.name}")
            for _, obj in inspect.getmembers(module, inspect.isclass):
                if issubclass(obj, Filter) and obj.__module__ == module.__name__ and obj.name:
                    found.append(obj)
    return found


@hookimpl
def evchain_bench_workloads() -> dict[str, object]:
    workloads = {}
    package = importlib.import_module("evchain.benchmarks")
    for info in pkgutil.iter_modules(package.__path__):
        module = importlib.import_module(f"evchain.benchmarks.{info.name}")
        workloads.update(getattr(module, "WORKLOADS", {}))
    return workloads
