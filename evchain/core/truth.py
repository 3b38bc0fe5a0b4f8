"""Ground truth as small protocols: what a source knows exactly, and what a stage needs of it.

A source that knows the truth sets ``context.truth`` in its ``setup()`` to a provider object
(not precomputed arrays) and lists in ``provides_truth`` which of these protocols it
implements (a stage may do the same for the stages after it, as ``imu_truth`` does with the
gyro's flow on recordings); a scorer lists in ``needs_truth`` the ones it cannot work without and in
``uses_truth`` the ones it uses when present. The base :class:`~evchain.core.filter.Filter`
checks them in ``setup()``: a stage whose truth lacks a needed part fails with a
:class:`~evchain.errors.ConfigError` naming the stage, the part and the sources that provide it.
Algorithm filters (flow, FOE, TTC) never read the truth.

Conventions of every protocol:

* ``x``, ``y``: pixel positions (float allowed), x to the right and y down, with the origin at
  the top-left pixel's centre (as :class:`~evchain.core.packets.Geometry`);
* ``t_us``: times in µs (float allowed);
* arguments are scalars or numpy arrays that broadcast against each other; each result has
  the broadcast shape (a scalar, or a 0-d array, for scalar arguments), float64 unless said;
* a value that is undefined there and then is NaN (e.g. the FOE while not moving forward); a
  part that a provider cannot answer at all is not there (no method), so ``isinstance``
  tells.

A provider implements the protocols structurally (no base class needed)::

    class MyTruth:
        def flow(self, x, y, t_us):
            return vx, vy

    isinstance(MyTruth(), FlowTruth)    # True
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Protocol, runtime_checkable

import numpy as np

from evchain.errors import ConfigError


@runtime_checkable
class FlowTruth(Protocol):
    """The motion field."""

    def flow(self, x, y, t_us) -> tuple[np.ndarray, np.ndarray]:
        """(vx, vy): the image velocity in px/s of the surface seen at (x, y) at ``t_us``;
        NaN where unknown."""
        ...


@runtime_checkable
class FoeTruth(Protocol):
    """The focus of expansion."""

    def foe(self, t_us) -> tuple[np.ndarray, np.ndarray]:
        """(x, y): the focus of expansion in pixels at ``t_us``: the projection of the camera's
        translation (thesis eq. 3.5), i.e. its heading; a rotating camera's flow does not
        vanish there. NaN unless the camera moves forward."""
        ...


@runtime_checkable
class RotationTruth(Protocol):
    """The camera's rotation."""

    def angular_velocity(self, t_us) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(wx, wy, wz): the camera's angular velocity in rad/s at ``t_us`` about its own axes
        (x right, y down, z forward; right-handed: ``wx > 0`` tilts it up, so the image moves
        down; ``wy > 0`` pans it right; ``wz > 0`` rolls it clockwise as seen from behind).
        The rotational part of the motion field at normalised coordinates
        ``X = (x - cx) / f``, ``Y = (y - cy) / f`` is then
        ``u = f (X Y wx - (1 + X^2) wy + Y wz)``, ``v = f ((1 + Y^2) wx - X Y wy - X wz)``
        px/s, whatever the depth (Longuet-Higgins and Prazdny 1980)."""
        ...


@runtime_checkable
class TtcTruth(Protocol):
    """The time to contact."""

    def ttc(self, t_us) -> np.ndarray:
        """Time to contact with the obstacle in s at ``t_us`` (thesis eq. 3.6); NaN without an
        obstacle, at rest, or once passed."""
        ...


@runtime_checkable
class DepthTruth(Protocol):
    """The depth of what is seen."""

    def depth(self, x, y, t_us) -> np.ndarray:
        """Depth Z in m (along the optical axis) of the surface seen at (x, y) at ``t_us``;
        inf where nothing is (sky)."""
        ...


@runtime_checkable
class ObjectTruth(Protocol):
    """Which object is seen where."""

    #: ids (int64, 1-D) of the obstacle's parts, as ``object_id`` returns them; empty without
    #: an obstacle
    obstacle_ids: np.ndarray

    def object_id(self, x, y, t_us) -> np.ndarray:
        """Id (int64) of the object seen at (x, y) at ``t_us``: provider-defined integers, the
        obstacle's among ``obstacle_ids``."""
        ...


#: every protocol, in the order messages list them
PROTOCOLS: tuple[type, ...] = (FlowTruth, FoeTruth, RotationTruth, TtcTruth, DepthTruth,
                               ObjectTruth)

#: what each protocol is, in words
KIND: dict[type, str] = {FlowTruth: "flow", FoeTruth: "FOE", RotationTruth: "camera rotation",
                         TtcTruth: "TTC", DepthTruth: "depth", ObjectTruth: "object ids"}

#: what ``context.truth`` holds: a provider of one or more of the protocols, or None
Truth = FlowTruth | FoeTruth | RotationTruth | TtcTruth | DepthTruth | ObjectTruth


def describe(protocols: Iterable[type]) -> str:
    """``flow (FlowTruth), FOE (FoeTruth)``: the protocols in words and by name."""
    return ", ".join(f"{KIND.get(p, p.__name__)} ({p.__name__})" for p in protocols)


def missing(truth: object | None, protocols: Iterable[type]) -> tuple[type, ...]:
    """The protocols that ``truth`` (None: no truth) does not implement."""
    return tuple(p for p in protocols if truth is None or not isinstance(truth, p))


def require(stage: str, needs: Iterable[type], truth: object | None, hint: str = "") -> None:
    """Raise a ConfigError naming ``stage`` (e.g. ``'scorer' (flow_scorer)``), what it needs,
    what it has, and the sources that provide it (then ``hint``, another way to give it) unless
    ``truth`` implements ``needs``."""
    needs = tuple(needs)
    lack = missing(truth, needs)
    if not lack:
        return
    have = ("the source provides no ground truth" if truth is None else
            f"the ground truth ({type(truth).__name__}) has no {describe(lack)}")
    sources = truth_sources(needs)
    stages = truth_sources(needs, sources=False)
    where = (f"sources that provide it: {', '.join(sources)}" if sources
             else "no installed source provides it")
    if stages:
        where += f"; stages that provide it to the stages after them: {', '.join(stages)}"
    raise ConfigError(f"stage {stage} needs ground truth with {describe(needs)}, but {have}; "
                      f"{where}" + (f"; {hint}" if hint else ""))


def not_scored(what: Iterable[str], truth: object, protocol: type) -> str:
    """The sentence a scorer puts into its metrics (``not_scored``) for what it could not score
    because ``truth`` lacks the optional ``protocol``."""
    return (f"{', '.join(what)}: the ground truth ({type(truth).__name__}) has no "
            f"{describe([protocol])}")


def truth_sources(needs: Iterable[type], sources: bool = True) -> list[str]:
    """Names of the installed sources (``sources``; else of the other stages, e.g. ``imu_truth``)
    whose ``provides_truth`` covers ``needs``."""
    from evchain.core.registry import make_registry
    from evchain.errors import PluginError

    try:
        registry = make_registry()
    except PluginError:     # a broken plugin: still name the built-in sources
        registry = make_registry(discover=False)
    needs = set(needs)
    return sorted(name for name, info in registry.filters.items()
                  if info.cls.is_source() == sources and info.cls.provides_truth
                  and needs <= set(info.cls.provides_truth))
