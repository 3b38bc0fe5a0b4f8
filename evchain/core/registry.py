"""The plugin registry: built-in and third-party filters through one pluggy hook.

Use :func:`make_registry`; ``discover=False`` skips installed entry points (for tests).
"""

from __future__ import annotations

import difflib
import importlib.metadata
from dataclasses import dataclass

import pluggy

from evchain import hookspecs
from evchain.core.filter import Filter, FilterParams
from evchain.core.series import SeriesDef
from evchain.errors import ConfigError, PluginError

BUILTIN = "evchain"


@dataclass(frozen=True)
class FilterInfo:
    """A registered filter class and the distribution that provides it."""

    cls: type[Filter]
    distribution: str
    version: str


class Registry:
    """Filters by name, plugin distributions, and bench workloads."""

    def __init__(self, pm: pluggy.PluginManager):
        self.pm = pm
        self.filters: dict[str, FilterInfo] = {}
        self.workloads: dict[str, object] = {}
        self.distributions: dict[str, str] = {BUILTIN: _version(BUILTIN)}
        for plugin in pm.get_plugins():
            dist, version = self._distribution_of(plugin)
            self.distributions.setdefault(dist, version)
            impl = getattr(plugin, "evchain_filters", None)
            for cls in _call(impl, dist) or []:
                self._add(cls, dist, version)
            impl = getattr(plugin, "evchain_bench_workloads", None)
            self.workloads.update(_call(impl, dist) or {})

    def _distribution_of(self, plugin) -> tuple[str, str]:
        for p, dist in self.pm.list_plugin_distinfo():
            if p is plugin:
                return dist.metadata["name"], dist.version
        name = self.pm.get_name(plugin) or BUILTIN
        return (BUILTIN, _version(BUILTIN)) if name.startswith("evchain.") else (name, "")

    def _add(self, cls, dist: str, version: str) -> None:
        if not (isinstance(cls, type) and issubclass(cls, Filter) and cls.name):
            raise PluginError(f"plugin {dist!r} registered {cls!r}, which is not a Filter "
                              "subclass with a name")
        if not (isinstance(cls.Params, type) and issubclass(cls.Params, FilterParams)):
            raise PluginError(f"filter {cls.name!r} of {dist!r}: Params must subclass "
                              "evchain.FilterParams")
        for attr in ("needs_series", "optional_series", "adds_series"):
            value = getattr(cls, attr)
            if not (isinstance(value, tuple) and all(isinstance(v, SeriesDef) for v in value)):
                raise PluginError(f"filter {cls.name!r} of {dist!r}: {attr} must be a tuple of "
                                  f"evchain.core.series.SeriesDef, got {value!r}")
        for attr in ("input_paths", "output_paths"):
            value = getattr(cls, attr)
            if not (isinstance(value, tuple) and set(value) <= set(cls.Params.model_fields)):
                raise PluginError(f"filter {cls.name!r} of {dist!r}: {attr} must be a tuple of "
                                  f"names of its parameters, got {value!r}")
        if cls.name in self.filters:
            other = self.filters[cls.name].distribution
            raise PluginError(f"filter name {cls.name!r} is claimed by both {other!r} and "
                              f"{dist!r}; uninstall one or rename the filter")
        self.filters[cls.name] = FilterInfo(cls, dist, version)

    def adders(self, series: str) -> list[str]:
        """The filters that declare they add the series called ``series``, sorted."""
        return sorted(n for n, info in self.filters.items()
                      if any(a.name == series for a in info.cls.adds_series))

    def get(self, name: str) -> type[Filter]:
        """The filter class called ``name``; unknown names suggest close matches."""
        try:
            return self.filters[name].cls
        except KeyError:
            raise ConfigError(unknown_filter_message(name, self.filters)) from None


def unknown_filter_message(name: str, known) -> str:
    close = difflib.get_close_matches(name, list(known), n=3)
    hint = f"did you mean {', '.join(map(repr, close))}? " if close else ""
    return f"unknown filter {name!r}; {hint}known filters: {', '.join(sorted(known))}"


def _call(impl, dist: str):
    if impl is None:
        return None
    try:
        return impl()
    except Exception as exc:  # a broken plugin must not take everything down silently
        raise PluginError(f"plugin distribution {dist!r} failed in {impl.__name__}: "
                          f"{type(exc).__name__}: {exc}") from exc


def _version(dist: str) -> str:
    try:
        return importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def make_registry(discover: bool = True, plugins: tuple = ()) -> Registry:
    """Build a registry with the built-ins, ``plugins`` and (if ``discover``) entry points."""
    from evchain.filters import _builtin

    pm = pluggy.PluginManager("evchain")
    pm.add_hookspecs(hookspecs)
    pm.register(_builtin, name="evchain.builtin")
    for plugin in plugins:
        pm.register(plugin)
    if discover:
        try:
            pm.load_setuptools_entrypoints("evchain")
        except Exception as exc:
            dist = _failing_distribution(exc)
            raise PluginError(f"plugin {dist} could not be loaded: {type(exc).__name__}: {exc}; "
                              "reinstall or uninstall it") from exc
    try:
        pm.check_pending()
    except pluggy.PluginValidationError as exc:
        raise PluginError(f"plugin implements an unknown hook: {exc}") from exc
    return Registry(pm)


def _failing_distribution(exc: Exception) -> str:
    """Best effort: the entry point of group ``evchain`` whose module is in the traceback."""
    tb = exc.__traceback__
    files = []
    while tb is not None:
        files.append(tb.tb_frame.f_code.co_filename)
        tb = tb.tb_next
    for ep in importlib.metadata.entry_points(group="evchain"):
        module = ep.value.split(":")[0].split(".")[0]
        if any(f"/{module}/" in f or f.endswith(f"/{module}.py") for f in files):
            return repr(ep.dist.name if ep.dist else ep.name)
    return "(unknown distribution)"
