"""The filter contract suite: properties every filter must have, for built-in and third-party
filters alike.

* cutting the same input stream into packets at different places gives the same output;
* ``reset()`` and a replay give the same output;
* empty packets flow: each input packet gives one output packet, and output slices are
  consecutive, ordered and valid (a filter that holds data back may lag, never overlap);
* inputs are not mutated;
* the output carries the series the filter declares it adds (``adds_series``), with the
  declared dtype, and no series it does not declare (a declared series may be missing only
  when the input lacks one of the series the filter needs or reads).
* a stage that declares no ground truth (``needs_truth``, ``uses_truth``) never reads
  ``context.truth``; a source's ``context.truth`` implements exactly its ``provides_truth``.

Use :func:`check_filter` and :func:`check_source` directly, or the ``filter_contract`` fixture of
the pytest plugin (``evchain.testing.pytest_plugin``, active once evchain is installed).
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from evchain.core.filter import Context, Filter
from evchain.core.packets import Packet
from evchain.core.truth import PROTOCOLS, describe


class ContractError(AssertionError):
    """A filter breaks the contract (says which property and where)."""


def slice_packet(packet: Packet, t_start: int, t_end: int) -> Packet:
    """The part of ``packet`` inside ``[t_start, t_end)``, series included."""
    keep = (packet.t >= t_start) & (packet.t < t_end)
    cols = {name: getattr(packet, name)[keep] for name in packet.columns}
    series = {k: v[(v["t"] >= t_start) & (v["t"] < t_end)] for k, v in packet.series.items()}
    return packet.replace(t_start=t_start, t_end=t_end, series=series, **cols)


def recut(packets: list[Packet], boundaries: list[int]) -> list[Packet]:
    """The same stream cut at ``boundaries`` (times strictly inside the stream's span)."""
    whole = type(packets[0]).concat(packets)
    edges = [whole.t_start, *sorted(b for b in boundaries if whole.t_start < b < whole.t_end),
             whole.t_end]
    return [slice_packet(whole, a, b) for a, b in zip(edges[:-1], edges[1:], strict=True)]


def standard_cuts(packets: list[Packet]) -> dict[str, list[Packet]]:
    """Several cuttings of one stream: whole, many small, with empty slices, at event times."""
    whole = type(packets[0]).concat(packets)
    t0, t1 = whole.t_start, whole.t_end
    span = max(t1 - t0, 1)
    cuts = {"whole": recut(packets, []),
            "eleven": recut(packets, [t0 + span * k // 11 for k in range(1, 11)]),
            "uneven": recut(packets, [t0 + span // 97, t0 + span // 3, t0 + span // 3 + 1,
                                      t0 + span * 4 // 5])}
    if len(whole):
        t = whole.t
        at_events = [int(t[len(t) // 4]), int(t[len(t) // 2]), int(t[len(t) // 2]) + 1]
        cuts["at_events"] = recut(packets, at_events)
    empties = []
    for p in cuts["eleven"]:
        mid = (p.t_start + p.t_end) // 2
        empty = slice_packet(p, p.t_start, p.t_start)  # zero-length slice
        empties += [empty, *recut([p], [mid])] if p.t_end - p.t_start > 1 else [p]
    cuts["with_empties"] = empties
    return cuts


def _snapshot(packets: list[Packet]) -> list[dict[str, np.ndarray]]:
    return [{**{n: getattr(p, n).copy() for n in p.columns},
             **{f"series:{k}": v.copy() for k, v in p.series.items()}} for p in packets]


def _equal(a: np.ndarray, b: np.ndarray) -> bool:
    """Same dtype, shape and values, NaN equal to NaN (a series may hold NaN for undefined)."""
    if a.dtype != b.dtype or a.shape != b.shape:
        return False
    if a.dtype.names:
        return all(_equal(a[name], b[name]) for name in a.dtype.names)
    return bool(np.array_equal(a, b, equal_nan=a.dtype.kind in "fc"))


def _same_arrays(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> list[str]:
    if a.keys() != b.keys():
        return [f"keys {sorted(a)} vs {sorted(b)}"]
    return [k for k in a if not _equal(a[k], b[k])]


#: folders of contexts made without ``out_dir``; removed when the interpreter exits
_TEMPORARY: list[tempfile.TemporaryDirectory] = []


def make_context(geometry, truth=None, out_dir: Path | None = None, seed: int = 0) -> Context:
    """A checking context (``debug``) writing into ``out_dir``, else into a temporary folder
    removed when the interpreter exits."""
    if out_dir is None:
        _TEMPORARY.append(tempfile.TemporaryDirectory(prefix="evchain-contract-"))
        out_dir = _TEMPORARY[-1].name
    return Context(seed=seed, out_dir=Path(out_dir), geometry=geometry, truth=truth, debug=True)


def run_filter(f: Filter, packets: list[Packet], check: bool = True) -> list[Packet]:
    """Process ``packets`` then flush; returns every output packet (checked if ``check``)."""
    outs = []
    for i, p in enumerate(packets):
        out = f.process(p)
        if out is None:
            raise ContractError(f"{f.name}: process() returned None for input packet {i}; "
                                "return an (empty) packet")
        outs.append(out)
    last = f.flush()
    if last is not None:
        outs.append(last)
    if check:
        for i, out in enumerate(outs):
            out.validate(f"{f.name} output packet {i}")
            if i and out.t_start != outs[i - 1].t_end:
                raise ContractError(f"{f.name}: output slices not consecutive: packet {i} starts "
                                    f"at {out.t_start} us, the previous ended at "
                                    f"{outs[i - 1].t_end} us")
    return outs


def run_source(cls: type[Filter], params: dict[str, Any], out_dir: Path,
               stage_id: str | None = None) -> tuple[list[Packet], Context]:
    """Every packet of the source ``cls`` with ``params`` (stage id ``stage_id``, default its
    name), and the context it filled in."""
    src = cls()
    src.id = stage_id or cls.name
    context = Context(out_dir=Path(out_dir))
    src.setup(cls.Params(**params), context)
    try:
        return list(src.packets()), context
    finally:
        src.close()


def run_sink(cls: type[Filter], params: dict[str, Any], packets: list[Packet],
             out_dir: Path) -> Context:
    """``packets`` through the filter ``cls`` (typically a writer), flushed and closed."""
    f = cls()
    f.id = cls.name
    context = Context(out_dir=Path(out_dir), geometry=packets[0].geometry)
    f.setup(cls.Params(**params), context)
    try:
        run_filter(f, packets, check=False)
    finally:
        f.close()
    return context


def flatten(outs: list[Packet]) -> dict[str, np.ndarray]:
    """Output columns and series of a list of packets, concatenated."""
    whole = type(outs[0]).concat(outs)
    d = {n: getattr(whole, n) for n in whole.columns}
    d.update({f"series:{k}": v for k, v in whole.series.items()})
    return d


def check_filter(cls: type[Filter], params: dict[str, Any], packets: list[Packet],
                 truth=None, out_dir: Path | None = None, seed: int = 0) -> dict[str, np.ndarray]:
    """Check the contract for ``cls`` with ``params`` on the stream ``packets``.

    Files go to ``out_dir``, else to a temporary directory removed afterwards. Returns the
    reference output (columns and series, concatenated) for further checks. A filter that
    declares no ground truth gets ``truth`` behind a guard that fails on any read.
    """
    if not packets:
        raise ValueError("check_filter needs a non-empty input stream")
    if out_dir is None:
        with tempfile.TemporaryDirectory(prefix="evchain-contract-") as tmp:
            return check_filter(cls, params, packets, truth, Path(tmp), seed)
    if truth is not None and not (cls.needs_truth or cls.uses_truth):
        truth = UnreadableTruth(cls.name)
    geometry = packets[0].geometry
    p = cls.Params(**params)

    def fresh() -> Filter:
        f = cls()
        f.id = cls.name
        f.setup(p, make_context(geometry, truth, out_dir, seed))
        return f

    given = _input_series(cls, packets)
    before = _snapshot(packets)
    f = fresh()
    reference = flatten(run_filter(f, packets))
    if bad := _mutated(before, packets):
        raise ContractError(f"{cls.name}: mutated its input ({bad})")
    _check_added_series(cls, p, given, reference)
    f.reset()
    replay = flatten(run_filter(f, packets))
    f.close()
    if bad := _same_arrays(reference, replay):
        raise ContractError(f"{cls.name}: reset() then replay changed the output in {bad}")
    for label, cut in standard_cuts(packets).items():
        g = fresh()
        try:
            got = flatten(run_filter(g, cut))
        finally:
            g.close()
        if bad := _same_arrays(reference, got):
            raise ContractError(f"{cls.name}: cutting the stream ({label}, {len(cut)} packets) "
                                f"changed the output in {bad}")
    return reference


def _input_series(cls: type[Filter], packets: list[Packet]) -> dict[str, np.dtype]:
    """The series of the input stream by name; it must carry those ``cls`` needs, with the
    dtypes it reads."""
    given = {name: entries.dtype for p in packets for name, entries in p.series.items()}
    for want in (*cls.needs_series, *cls.optional_series):
        if want.name in given and given[want.name] != want.dtype:
            raise ValueError(f"check_filter: the input's series {want.name!r} has fields "
                             f"({', '.join(given[want.name].names)}); {cls.name} reads "
                             f"({want.fields()})")
    missing = [s.name for s in cls.needs_series if s.name not in given]
    if missing:
        raise ValueError(f"check_filter: {cls.name} needs the series {missing} on its input "
                         "packets (its needs_series)")
    return given


def _check_added_series(cls: type[Filter], params, given: dict[str, np.dtype],
                        output: dict[str, np.ndarray]) -> None:
    declared = {s.name: s for s in cls.series_added(params)}
    for key, entries in output.items():
        if not key.startswith("series:"):
            continue
        name = key.removeprefix("series:")
        want = declared[name].dtype if name in declared else given.get(name)
        if want is None:
            raise ContractError(f"{cls.name}: its output carries the series {name!r}, which it "
                                "does not declare in adds_series")
        if entries.dtype != want:
            raise ContractError(f"{cls.name}: series {name!r} has fields "
                                f"({', '.join(entries.dtype.names)}) of dtype {entries.dtype}, "
                                f"expected {want}")
    if all(s.name in given for s in cls.optional_series):
        missing = [name for name in declared if f"series:{name}" not in output]
        if missing:
            raise ContractError(f"{cls.name}: declares it adds the series {missing}, but its "
                                "output carries none")


class UnreadableTruth:
    """Stands in for the ground truth of a stage that declares none: any read is a
    ContractError (algorithm filters never read the truth; scorers declare what they read)."""

    def __init__(self, stage: str):
        object.__setattr__(self, "_stage", stage)

    def __getattribute__(self, name: str):
        if name.startswith("__"):
            return object.__getattribute__(self, name)
        stage = object.__getattribute__(self, "_stage")
        raise ContractError(f"{stage}: reads context.truth.{name} but declares neither "
                            "needs_truth nor uses_truth (algorithm filters never read the "
                            "ground truth)")


def check_truth_provided(cls: type[Filter], context: Context) -> None:
    """The source ``cls`` set ``context.truth`` implementing exactly its ``provides_truth``."""
    has = [p for p in PROTOCOLS if context.truth is not None and isinstance(context.truth, p)]
    declared = [p for p in PROTOCOLS if p in cls.provides_truth]
    if has != declared:
        raise ContractError(f"{cls.name}: provides_truth declares "
                            f"[{describe(declared)}] but its context.truth "
                            f"({type(context.truth).__name__}) implements [{describe(has)}]")


def _mutated(before: list[dict[str, np.ndarray]], packets: list[Packet]) -> list[str]:
    bad = []
    for i, (snap, now) in enumerate(zip(before, _snapshot(packets), strict=True)):
        bad += [f"packet {i} {k}" for k in _same_arrays(snap, now)]
    return bad


def check_source(cls: type[Filter], params: dict[str, Any], out_dir: Path | None = None,
                 seed: int = 0, max_packets: int = 50) -> list[Packet]:
    """A source yields valid packets with consecutive slices, and the same after reset().

    Files go to ``out_dir``, else to a temporary directory removed afterwards.
    """
    if out_dir is None:
        with tempfile.TemporaryDirectory(prefix="evchain-contract-") as tmp:
            return check_source(cls, params, Path(tmp), seed, max_packets)
    context = Context(seed=seed, out_dir=Path(out_dir), debug=True)
    f = cls()
    f.id = cls.name
    f.setup(cls.Params(**params), context)
    check_truth_provided(cls, context)

    def take() -> list[Packet]:
        got = []
        for i, packet in enumerate(f.packets()):
            packet.validate(f"{cls.name} packet {i}")
            if got and packet.t_start != got[-1].t_end:
                raise ContractError(f"{cls.name}: packet {i} starts at {packet.t_start} us, the "
                                    f"previous ended at {got[-1].t_end} us")
            got.append(packet)
            if len(got) >= max_packets:
                break
        return got

    try:
        first = take()
        if context.geometry is None:
            raise ContractError(f"{cls.name}: a source must set context.geometry in setup()")
        f.reset()
        second = take()
    finally:
        f.close()
    if not first:
        raise ContractError(f"{cls.name}: produced no packets")
    if bad := _same_arrays(flatten(first), flatten(second)):
        raise ContractError(f"{cls.name}: reset() then replay changed the output in {bad}")
    return first
