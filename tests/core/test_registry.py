import types

import pytest

from evchain import Filter, PluginError, hookimpl
from evchain.core.registry import make_registry
from tests.core import toy_filters


def test_builtins_and_plugin_module(registry):
    assert "toy_source" in registry.filters
    assert registry.filters["toy_source"].distribution != "evchain"


def _plugin(name, fn):
    mod = types.ModuleType(name)
    mod.evchain_filters = hookimpl(fn)
    return mod


def test_duplicate_name_names_both():
    dup = _plugin("other_dist", lambda: [toy_filters.ToySource])
    with pytest.raises(PluginError, match="claimed by both"):
        make_registry(discover=False, plugins=(toy_filters, dup))


def test_broken_plugin_named():
    def broken():
        raise ImportError("needs libfoo")

    with pytest.raises(PluginError, match="broken_dist.*needs libfoo"):
        make_registry(discover=False, plugins=(_plugin("broken_dist", broken),))


def test_not_a_filter():
    class NoName(Filter):
        pass

    with pytest.raises(PluginError, match="not a Filter"):
        make_registry(discover=False, plugins=(_plugin("bad", lambda: [NoName]),))


def test_misspelled_hook_caught():
    mod = types.ModuleType("typo")
    mod.evchain_filterz = hookimpl(lambda: [])
    with pytest.raises(PluginError, match="unknown hook"):
        make_registry(discover=False, plugins=(mod,))


def test_listing_filters_imports_no_numba():
    import subprocess
    import sys

    code = ("import sys; from evchain.core.registry import make_registry; make_registry(); "
            "print([m for m in ('numba', 'matplotlib', 'scipy', 'h5py') if m in sys.modules])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
