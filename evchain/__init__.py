"""evchain: event-based vision research in a jAER-style filter chain.

The facade: packets, the filter contract, the plugin hook marker, and running pipelines.
"""

from evchain.core.filter import Context, Filter, FilterParams
from evchain.core.packets import EventPacket, FlowPacket, FramePacket, Geometry, Packet
from evchain.errors import ConfigError, DataError, EvchainError, PluginError, WiringError
from evchain.hookspecs import hookimpl

__version__ = "0.1.0"

__all__ = [
    "ConfigError", "Context", "DataError", "EventPacket", "EvchainError", "Filter",
    "FilterParams", "FlowPacket", "FramePacket", "Geometry", "Packet", "PluginError",
    "WiringError", "hookimpl", "run",
]


def run(pipeline, overrides=(), out_dir="out", progress=False):
    """Run a pipeline file with ``--set``-style overrides; returns the report dict."""
    from evchain.core.chain import run_pipeline
    from evchain.core.config import load_pipeline
    from evchain.core.registry import make_registry

    registry = make_registry()
    spec = load_pipeline(pipeline, registry, list(overrides))
    return run_pipeline(spec, registry, out_dir, progress=progress).report
