"""The built-in driving-scene simulator (docs/explanation/scene.md).

``config`` (parameters), ``camera``, ``route`` (driving lines), ``world`` and ``scenarios`` (what
is there), ``drive`` (the drive: :class:`~evchain.sim.drive.Scene` renders it at any time),
``truth`` (exact depth, flow, FOE, TTC, object ids), ``renderer`` (frames for picture sinks),
``preview`` (PNG pictures). Importing this package does not import numba; kernels load on
first use.
"""
