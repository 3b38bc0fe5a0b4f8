"""Hooks a plugin implements; these docstrings are the plugin author's reference.

A plugin is a module or object registered under the entry-point group ``evchain``::

    # pyproject.toml of your distribution
    [project.entry-points.evchain]
    my_filters = "my_package.plugin"

    # my_package/plugin.py
    import evchain

    @evchain.hookimpl
    def evchain_filters():
        return [MyFilter]

Hooks only register things; none runs per event.
"""

from __future__ import annotations

import pluggy

hookspec = pluggy.HookspecMarker("evchain")
hookimpl = pluggy.HookimplMarker("evchain")


@hookspec
def evchain_filters() -> list[type]:
    """Return the :class:`evchain.Filter` subclasses this plugin provides.

    Each class needs a unique ``name`` (the ``use:`` key in pipelines), ``consumes`` and
    ``produces`` packet types and a nested pydantic ``Params`` model; the series it needs, reads
    if present and adds are tuples of :class:`evchain.core.series.SeriesDef` in
    ``needs_series``, ``optional_series`` and ``adds_series`` (empty by default). A stage that
    reads the ground truth declares it (``needs_truth``, ``uses_truth``; protocols of
    :mod:`evchain.core.truth`), and a source that sets ``context.truth`` declares
    ``provides_truth``. Two plugins claiming one name is an error that names both
    distributions.
    """


@hookspec
def evchain_bench_workloads() -> dict[str, object]:
    """Return benchmark workloads ``{name: function(quick: bool) -> list[BenchRow]}`` for
    ``evchain bench``. Names start with the stage's prefix (e.g. ``flow-``). Every row sets
    ``data`` (what it ran on). A workload that reads cached inputs is an
    :class:`evchain.bench_cache.Workload` listing them, so that ``evchain bench --prepare``
    makes them."""
