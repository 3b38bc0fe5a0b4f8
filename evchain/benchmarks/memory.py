"""Peak memory of a run against the length of its recording: rows ``memory-flow-chain``.

The flow chain of ``pipelines/reference-lk.yaml`` after its emulator (``lk_flow`` -> ``foe_map``
-> ``foe_fit`` -> ``ttc``, with that file's parameters; no scorers, which need ground truth)
runs through :func:`evchain.core.chain.run_pipeline` on an AEDAT file holding a synthetic
stream (:func:`evchain.benchmarks.plane_flow.expanding_scene_events`, 240x180, 2 s; 0.5 s with
``--quick``) repeated 1, 4 and 8 times end to end. Each run is a fresh Python process; its peak
resident memory (``resource.getrusage`` ``ru_maxrss``, Linux: KiB) is the row's
``peak_rss_mib``, beside the memory after the imports and a warm-up (``start_rss_mib``). A
runner whose memory is flat in the recording's length gives about the same peak for 1x and
8x. ``throughput`` is input events per wall second of the run (series written included).

Run it alone: ``evchain bench --exact memory-flow-chain`` (or ``python -m
evchain.benchmarks.memory [--quick] [--events FILE.aedat]``, which prints the table; with
``--events`` a recording is repeated instead, e.g. a rendered stretch of the reference drive).
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from pathlib import Path

from evchain.bench import BenchRow

ROOT = Path(__file__).resolve().parents[2]
PIPELINE = ROOT / "pipelines" / "reference-lk.yaml"
FLOW_CHAIN = ("lk_flow", "foe_map", "foe_fit", "ttc")
REPEATS = (1, 4, 8)


def stream_seconds(quick: bool) -> float:
    return 0.5 if quick else 2.0


def write_repeated(path: Path, seconds: float, repeats: int, source: Path | None = None) -> int:
    """The synthetic stream (or the events of the AEDAT file ``source``) written ``repeats``
    times end to end; returns the event count."""
    from evchain.benchmarks.plane_flow import expanding_scene_events
    from evchain.io.aedat2 import Writer, chip_for, read_aedat2
    from evchain.io.atomic import AtomicFile

    if source is None:
        ev, _ = expanding_scene_events(seconds=seconds)
        span = int(seconds * 1e6)
    else:
        ev = read_aedat2(source)
        span = ev.t_end - ev.t_start
    with AtomicFile(path) as out:
        writer = Writer(out, chip_for(ev.geometry, None))
        for k in range(repeats):
            writer.write(ev.x, ev.y, ev.t + k * span, ev.p)
    return len(ev) * repeats


def chain_text(events: Path) -> str:
    """The pipeline: the file as the source, then the flow chain of :data:`PIPELINE`."""
    import yaml

    from evchain.core.config import load_pipeline
    from evchain.core.registry import make_registry

    spec = load_pipeline(PIPELINE, make_registry())
    chain = [{"use": "aedat", "path": str(events)}]
    chain += [{"use": s.use, **s.params.model_dump(mode="json")} for s in spec.stages
              if s.use in FLOW_CHAIN]
    return yaml.safe_dump({"name": "memory-flow-chain", "chain": chain}, sort_keys=False)


def measure(events: Path, out: Path) -> dict:
    """Run the chain on ``events`` into ``out`` in this process; its peak memory."""
    import resource
    import time

    from evchain.core.chain import run_pipeline
    from evchain.core.config import pipeline_from_text
    from evchain.core.registry import make_registry

    registry = make_registry()
    spec = pipeline_from_text(chain_text(events), "memory-flow-chain", registry)
    start = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    report = run_pipeline(spec, registry, out, progress=False).report
    wall = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return {"events": report["filters"][0]["events_out"], "wall_s": wall,
            "start_rss_mib": start / 1024, "peak_rss_mib": peak / 1024,
            "series_entries": sum(report["series"].values())}


def _child(events: Path, out: Path) -> dict:
    code = ("import json, sys; from pathlib import Path; "
            "from evchain.benchmarks.memory import measure; "
            "print(json.dumps(measure(Path(sys.argv[1]), Path(sys.argv[2]))))")
    done = subprocess.run([sys.executable, "-c", code, str(events), str(out)],
                          capture_output=True, text=True, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def memory_rows(quick: bool, source: Path | None = None) -> list[BenchRow]:
    """The rows; ``source``: an AEDAT file to repeat instead of the synthetic stream."""
    seconds = stream_seconds(quick)
    what = (f"synthetic expanding scene 240x180, {seconds:g} s" if source is None
            else f"{source}")
    rows = []
    with tempfile.TemporaryDirectory(prefix="evchain-memory-") as tmp:
        tmp = Path(tmp)
        warm = tmp / "warm.aedat"
        write_repeated(warm, seconds, 1, source)
        _child(warm, tmp / "warm")  # compiles the kernels (numba's cache) outside the rows
        for k in REPEATS:
            events = tmp / f"x{k}.aedat"
            n = write_repeated(events, seconds, k, source)
            got = _child(events, tmp / f"run-x{k}")
            assert got["events"] == n
            rows.append(BenchRow(
                workload="memory-flow-chain", stage="run_pipeline",
                throughput=got["events"] / got["wall_s"], unit="ev/s",
                extra={"repeats": k, "events": n,
                       "peak_rss_mib": round(got["peak_rss_mib"], 1),
                       "start_rss_mib": round(got["start_rss_mib"], 1),
                       "series_entries": got["series_entries"]},
                data=f"{what} repeated {k}x; aedat -> {' -> '.join(FLOW_CHAIN)}",
                params_from="pipelines/reference-lk.yaml"))
    return rows


WORKLOADS = {"memory-flow-chain": memory_rows}


def main(argv: list[str] | None = None) -> None:
    import argparse

    p = argparse.ArgumentParser(prog="python -m evchain.benchmarks.memory",
                                description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="0.5 s of the synthetic stream")
    p.add_argument("--events", type=Path, help="an AEDAT 2.0 file to repeat instead")
    args = p.parse_args(argv)
    print("| repeats | events | series entries | start RSS MiB | peak RSS MiB |")
    print("|---|---|---|---|---|")
    for row in memory_rows(args.quick, args.events):
        e = row.extra
        print(f"| {e['repeats']} | {e['events']} | {e['series_entries']} | "
              f"{e['start_rss_mib']:.1f} | {e['peak_rss_mib']:.1f} |")


if __name__ == "__main__":
    main()
