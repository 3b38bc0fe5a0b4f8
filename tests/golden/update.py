"""Change the golden tests' expected values: ``python -m tests.golden.update --reason TEXT``.

Renders the golden stretches (tests/golden/stretch.py, each from three nearby starts), runs
both chains, prints every median that changed (old -> new) and writes
tests/golden/expected.json with the reason. Tolerances stay as they are unless ``--spread``
sets them from the run-to-run noise: twice the range of the three runs (at least the floor in
``FLOOR``; the median of three moves less than a single run), so that a change of machine or a
harmless change of rounding passes and a real change of the results does not. Commit the file
with the change that moved the values.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

from evchain.io.atomic import atomic_write_text
from tests.golden import stretch

#: the smallest tolerances (absolute, in the metric's unit)
FLOOR = {"foe.dx_mean_px": 0.25, "foe.dy_mean_px": 0.15, "flow.invalid_rate": 0.005,
         "flow.density": 0.01, "ttc.share_on_obstacle_within_20pct": 0.05,
         "ttc.coverage_on_obstacle": 0.05, "ttc.median_rel_error_on_obstacle": 0.02,
         "ttc.median_rel_error_last3s": 0.02}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reason", required=True, help="why the expected values change")
    ap.add_argument("--spread", action="store_true",
                    help="set the tolerances from the range of the three runs")
    args = ap.parse_args(argv)
    old = json.loads(stretch.EXPECTED.read_text()) if stretch.EXPECTED.is_file() else {}
    values, tolerance = {}, {}
    with tempfile.TemporaryDirectory() as tmp:
        events = stretch.record_all(Path(tmp))
        for name, (_, keys) in stretch.STRETCHES.items():
            values[name], tolerance[name] = {}, {}
            for flow in stretch.FLOWS:
                med, runs = stretch.medians(name, flow, events, Path(tmp))
                values[name][flow], tol = med, {}
                for key in keys:
                    got = runs[key]
                    kept = old.get("tolerance", {}).get(name, {}).get(flow, {}).get(key)
                    if args.spread or kept is None:
                        spread = max(got) - min(got) if None not in got else 0.0
                        tol[key] = max(FLOOR[key], 2 * spread)
                    else:
                        tol[key] = kept
                    was = old.get("values", {}).get(name, {}).get(flow, {}).get(key)
                    print(f"{name:9s} {flow:6s} {key:36s} {_fmt(was):>8s} "
                          f"{'  ' if was == med[key] else '->'} {_fmt(med[key]):>8s}  "
                          f"+- {tol[key]:.3g}   (runs: {', '.join(_fmt(v) for v in got)})")
                tolerance[name][flow] = tol
    atomic_write_text(stretch.EXPECTED, json.dumps(
        {"reason": args.reason, "values": values, "tolerance": tolerance}, indent=2) + "\n")
    print(f"wrote {stretch.EXPECTED}")
    return 0


def _fmt(v) -> str:
    return "-" if v is None else f"{v:.4g}"


if __name__ == "__main__":
    raise SystemExit(main())
