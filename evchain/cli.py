"""The ``evchain`` command: run, validate, filters, plugins, sweep, bench, results, docs.

User mistakes (an :class:`EvchainError`) print one line and exit with code 2; ``--debug`` (before
or after the subcommand) shows the traceback. Unexpected errors are bugs: they exit with code 1.
Notices that are not the result (kernels compiling, runs taken from a sweep's cache) go to the
``evchain`` logger, shown on stderr. Ctrl-C during ``run`` stops the stream, writes complete
outputs and exits with code 130 (a second Ctrl-C aborts at once).
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import traceback
from pathlib import Path

from evchain.errors import EvchainError, FilterError, RunInterrupted


def _registry():
    from evchain.core.registry import make_registry

    return make_registry()


def cmd_run(args) -> int:
    from evchain.core.chain import run_pipeline
    from evchain.core.config import load_pipeline

    registry = _registry()
    spec = load_pipeline(args.pipeline, registry, args.set)
    if args.replay:
        from evchain.filters.scene_events import replay_spec

        spec = replay_spec(spec, args.replay)
    out = Path(args.out) if args.out else Path("out") / spec.name
    interrupted = None
    try:
        result = run_pipeline(spec, registry, out, progress=not args.no_progress,
                              debug=args.debug, threads=not args.serial)
    except RunInterrupted as exc:  # finished cleanly after Ctrl-C: say what was written
        result, interrupted = exc.result, exc
    rep = result.report
    done = "stopped after" if interrupted else "done in"
    print(f"{spec.name}: {done} {rep['wall_s']:.2f} s, results in {out}/")
    for f in rep["filters"]:
        eps = f["throughput_eps"]
        if not eps:
            rate = "-"
        elif f.get("unit_in") == "frames":
            rate = f"{eps:9.0f} frames/s"
        else:
            rate = f"{eps / 1e6:9.2f} M events/s"
        print(f"  {f['id']:18s} in {f['events_in']:>11,d}  out {f['events_out']:>11,d}  "
              f"{f['wall_s']:8.3f} s {rate}")
    for group, values in rep["metrics"].items():
        if isinstance(values, dict):
            shown = ", ".join(f"{k}={_fmt(v)}" for k, v in values.items()
                              if not isinstance(v, dict | list))
            print(f"  metrics.{group}: {shown}")
    if interrupted is not None:
        print(f"evchain: {interrupted}", file=sys.stderr)
        return 130  # 128 + SIGINT, as for a process stopped by Ctrl-C
    return 0


def _fmt(v) -> str:
    return f"{v:.4g}" if isinstance(v, float) else str(v)


def cmd_validate(args) -> int:
    from evchain.core.config import load_pipeline
    from evchain.sweep import load_sweep, looks_like_sweep, validate_sweep

    for path in args.pipeline:
        if looks_like_sweep(path):
            n = validate_sweep(load_sweep(path), _registry())
            print(f"{path}: ok (sweep: {n} runs validated)")
            continue
        spec = load_pipeline(path, _registry(), args.set)
        print(f"{path}: ok ({len(spec.stages)} stages: "
              f"{' -> '.join(s.id for s in spec.stages)})")
    return 0


def cmd_filters(args) -> int:
    from evchain.core.registry import unknown_filter_message
    from evchain.core.schema import describe_filter

    registry = _registry()
    if args.name:
        if args.name not in registry.filters:
            raise EvchainError(unknown_filter_message(args.name, registry.filters))
        info = registry.filters[args.name]
        print(describe_filter(info.cls, info.distribution))
        return 0
    for name in sorted(registry.filters):
        info = registry.filters[name]
        cls = info.cls
        wiring = (f"{cls.consumes.__name__ if cls.consumes else 'source'} -> "
                  f"{cls.produces.__name__ if cls.produces else 'same'}")
        print(f"{name:18s} {info.distribution:18s} {wiring:28s} {cls.summary()}")
    return 0


def cmd_plugins(args) -> int:
    registry = _registry()
    for dist, version in sorted(registry.distributions.items()):
        names = sorted(n for n, i in registry.filters.items() if i.distribution == dist)
        print(f"{dist:24s} {version:10s} {', '.join(names)}")
    return 0


def cmd_bench(args) -> int:
    from evchain import bench

    known = _registry().workloads
    workloads = bench.select(known, args.prefix, exact=args.exact)
    unknown = sorted(set(args.prefix) - set(known)) if args.exact else []
    if not workloads or unknown:
        raise EvchainError(f"no benchmark workload {'is' if args.exact else 'matches'} "
                           f"{unknown or args.prefix}; known: {', '.join(sorted(known))}")
    if args.repeat < 1:
        raise EvchainError(f"--repeat {args.repeat}: expected a count of at least 1")
    if args.prepare:
        if args.json:
            raise EvchainError("--prepare makes inputs and runs no rows: nothing to write to "
                               f"{args.json} (run again without --prepare)")
        made = bench.prepare(workloads, quick=args.quick)
        print(f"prepared {len(made)} input(s); run the rows with: "
              + " ".join(["evchain bench", *(["--exact"] if args.exact else []), *args.prefix]
                         + (["--quick"] if args.quick else [])))
        return 0
    bench.check_inputs(workloads, quick=args.quick,
                       selection=(["--exact"] if args.exact else []) + args.prefix)
    print(bench.HEADER)
    rows = bench.run(workloads, quick=args.quick, repeat=args.repeat)
    if args.json:
        bench.write_json(rows, args.json)
        print(f"wrote {len(rows)} rows to {args.json}")
    return 0


def cmd_sweep(args) -> int:
    from evchain.sweep import load_sweep, run_sweep

    sweep = load_sweep(args.sweep, args.set)
    if args.replay:
        sweep.replay, sweep.record = Path(args.replay), None
    out = Path(args.out) if args.out else Path("out") / "sweeps" / sweep.name
    print(f"sweep {sweep.name}: {len(sweep.runs())} runs of "
          f"{', '.join(str(b) for b in sweep.bases.values())}"
          + (f" with {' '.join(sweep.extra_set)}" if sweep.extra_set else "") + f" -> {out}/")
    run_sweep(sweep, out, workers=args.workers, scheduler=args.scheduler)
    print(f"table: {out}/sweep.md")
    return 0


def cmd_results(args) -> int:
    from evchain import results

    manifest = results.load_manifest(Path(args.root))
    if args.run is not None:
        saved = results.run_and_save(manifest, args.run, workers=args.workers)
        print(f"saved {len(saved)} results: " + ", ".join(str(p) for p in saved))
    if args.check:
        ok, message = results.check(manifest)
        print(message, file=sys.stdout if ok else sys.stderr)
        return 0 if ok else 1
    print(f"wrote {results.write(manifest)}")
    return 0


def cmd_docs(args) -> int:
    from evchain.core.schema import filters_markdown, hooks_markdown
    from evchain.io.atomic import atomic_write_text

    out = Path(args.out)
    atomic_write_text(out / "filters.md", filters_markdown(_registry()))
    atomic_write_text(out / "hooks.md", hooks_markdown())
    print(f"wrote {out}/filters.md and {out}/hooks.md")
    return 0


DEBUG_HELP = "show tracebacks and debug messages; check every packet"


def build_parser() -> argparse.ArgumentParser:
    from evchain import __version__

    p = argparse.ArgumentParser(prog="evchain", description=__doc__.splitlines()[0])
    p.add_argument("--debug", action="store_true", help=DEBUG_HELP)
    p.add_argument("--version", action="version", version=f"evchain {__version__}")
    # --debug after the subcommand too; SUPPRESS keeps a --debug given before it
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                        help=DEBUG_HELP)
    sub = p.add_subparsers(dest="command", required=True)

    def add(name: str, **kw) -> argparse.ArgumentParser:
        return sub.add_parser(name, parents=[common], **kw)

    r = add("run", help="run a pipeline")
    r.add_argument("pipeline")
    r.add_argument("--set", action="append", default=[], metavar="STAGE.PARAM=VALUE",
                   help="override a parameter (stage by 'use' name or 'id'; PARAM+=NUMBER "
                        "adds to its value); repeatable")
    r.add_argument("--out", help="output folder (default out/NAME)")
    r.add_argument("--replay", metavar="EVENTS.aedat",
                   help="instead of scene -> emulator, read their events from an earlier run "
                        "of the same pipeline start (its folder's events.aedat), with the "
                        "scene's exact ground truth")
    r.add_argument("--no-progress", action="store_true", help="no progress bar")
    r.add_argument("--serial", action="store_true",
                   help="every stage on one thread (for debuggers and profilers; the same "
                        "results); by default each stage runs on a thread of its own")
    r.set_defaults(fn=cmd_run)

    v = add("validate", help="check pipelines (or sweeps: every run) without "
                       "running them")
    v.add_argument("pipeline", nargs="+")
    v.add_argument("--set", action="append", default=[], metavar="STAGE.PARAM=VALUE")
    v.set_defaults(fn=cmd_validate)

    f = add("filters", help="list filters, or show one filter's parameters")
    f.add_argument("name", nargs="?")
    f.set_defaults(fn=cmd_filters)

    pl = add("plugins", help="list plugin distributions and versions")
    pl.set_defaults(fn=cmd_plugins)

    sw = add("sweep", help="run variations of a pipeline, cached, as one table")
    sw.add_argument("sweep")
    sw.add_argument("--set", action="append", default=[], metavar="STAGE.PARAM=VALUE",
                    help="append to the sweep's 'set' (every run, before each variation's "
                         "own overrides); repeatable")
    sw.add_argument("--out", help="output folder (default out/sweeps/NAME)")
    sw.add_argument("--workers", type=int, default=2, help="local processes (1: in-process)")
    sw.add_argument("--replay", metavar="EVENTS.aedat",
                    help="every run reads these recorded events instead of scene -> emulator "
                         "(instead of the sweep's 'replay' or 'record')")
    sw.add_argument("--scheduler", help="Dask scheduler address (needs evchain[dask])")
    sw.set_defaults(fn=cmd_sweep)

    d = add("docs", help="generate the reference docs (filters, hooks)")
    d.add_argument("--out", default="docs/reference")
    d.set_defaults(fn=cmd_docs)

    rs = add("results", help="docs/results.md from the saved results (--run: "
                        "measure them first)")
    rs.add_argument("--run", nargs="*", metavar="NAME",
                    help="run the manifest's sweeps and benchmarks (all, or those named) and "
                         "save them under results/ before writing")
    rs.add_argument("--check", action="store_true",
                    help="exit 1 if docs/results.md is not what the saved results give")
    rs.add_argument("--workers", type=int, default=2, help="local processes for sweeps")
    rs.add_argument("--root", default=".", help="repository folder (default: here)")
    rs.set_defaults(fn=cmd_results)

    b = add(
        "bench", help="benchmarks: throughput next to error",
        description="Run benchmark workloads; each row is a throughput next to the error it "
                    "reached and says what it ran on. Rows on the simulated reference drive "
                    "read inputs (rendered events, flow) from the cache folder ($EVCHAIN_CACHE, "
                    "default the user cache folder); when one is missing nothing runs and the "
                    "error names the --prepare command that makes it.")
    b.add_argument("prefix", nargs="*", help="workload name prefixes (default: all)")
    b.add_argument("--quick", action="store_true", help="smaller workloads")
    b.add_argument("--exact", action="store_true",
                   help="the names are whole workload names, not prefixes (each row's "
                        "'command' uses this)")
    b.add_argument("--json", help="write the rows to this JSON file (a list of row objects)")
    b.add_argument("--prepare", action="store_true",
                   help="only make the missing cached inputs of the selected workloads (with "
                        "--quick: of their quick rows) and run no rows; rows without inputs "
                        "need none. Rendering takes minutes for the full-size inputs")
    b.add_argument("--repeat", type=int, default=1, metavar="N",
                   help="run every selected workload N times (round-robin); each row records "
                        "its repeat (0-based)")
    b.set_defaults(fn=cmd_bench)
    return p


def _setup_logging(debug: bool) -> None:
    """The ``evchain`` logger on stderr: notices at INFO, everything with ``--debug``."""
    logger = logging.getLogger("evchain")
    if not any(getattr(h, "_evchain_cli", False) for h in logger.handlers):
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter("evchain: %(message)s"))
        handler._evchain_cli = True
        logger.addHandler(handler)
    logger.setLevel(logging.DEBUG if debug else logging.INFO)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    _setup_logging(args.debug)
    try:
        rc = args.fn(args)
        sys.stdout.flush()  # a closed pipe shows here, not at exit
        return rc
    except BrokenPipeError:  # e.g. `evchain filters | head`: the reader has all it wants
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())  # nothing more to write at exit
        return 141  # 128 + SIGPIPE, as a process killed by the signal
    except EvchainError as exc:
        if args.debug:
            traceback.print_exc()
        print(f"evchain: error: {exc}", file=sys.stderr)
        if isinstance(exc, FilterError) and exc.internal:
            if not args.debug:
                print("evchain: this looks like a bug; rerun with --debug for the traceback",
                      file=sys.stderr)
            return 1
        return 2
    except KeyboardInterrupt:
        print("evchain: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
