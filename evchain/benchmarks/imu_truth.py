"""Benchmarks of gyro ground truth and of reading IMU samples.

* ``imu-truth``: ``imu_truth`` and ``flow_scorer`` around ``lk_flow``, all with the parameters
  of pipelines/dvsflow16-imu-lk.yaml, on the DVSFLOW16 recording IMU_rotDisk
  (``../shared/data/dvsflow16``); without it, on a synthetic rolling camera
  (:class:`~evchain.testing.synthetic.RollingCamera` on a 240x180 sensor, 3.2 s, gyro at 1 kHz
  with a bias of (1, -0.5, 0.3) deg/s, given to ``imu_truth``, and 0.1 deg/s of noise; the
  calibration then takes the first second). Throughput = input events per CPU second of this
  thread spent in ``imu_truth`` (calibration, validity, truth) and in ``flow_scorer`` (the
  truth at every flow event, the scores) together; ``lk_flow`` between them is not counted
  (``extra``: each stage alone). Error = AEE (px/s) of the LK flow against the gyro's flow
  (``flow_scorer``'s ``aee_pxs``); normal AEE, AAE, the scored flow events and the share of
  events with truth in ``extra``.
* ``plot-imu-rate``: ``imu_rate_plot`` on the ``imu_rate`` series that ``imu_truth`` (run once,
  not timed) makes from the same input as ``imu-truth``: every packet, then the PNG written at
  the end; throughput = plots per second (wall), the series' bins per second in ``extra``. No
  error: the stage draws the series as it is given and estimates nothing (the PNG's size in
  ``extra`` shows that it was drawn).
* ``imu-read-aedat``: the ``aedat`` source on an AEDAT 2.0 file of IMU samples at 1 kHz (7
  records each, jAER's layout) with a DVS event per sample between them; throughput = IMU
  samples per CPU second of reading the whole file. The plugins add the same rows for AEDAT
  4.0 (``imu-read-aedat4``) and ROS bags (``imu-read-rosbag-ros1``) from
  :func:`imu_packets`.
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

import numpy as np

from evchain.bench import BenchRow, best_cpu_time, best_time, cut_every, imu_source_row
from evchain.benchmarks.drive_inputs import relative
from evchain.core.filter import Context
from evchain.core.packets import EventPacket, Geometry
from evchain.core.series import IMU

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / ".." / "shared" / "data" / "dvsflow16"
PIPELINE = ROOT / "pipelines" / "dvsflow16-imu-lk.yaml"
SIM_BIAS = (1.0, -0.5, 0.3)


def _stages():
    """The pipeline's ``imu_truth``, ``lk_flow`` and ``flow_scorer`` stages. Without the
    recording on disk (the rows then run on the rolling camera) its source reads ``/dev/null``
    instead, so that the pipeline loads; the source stage is not used."""
    from evchain.core.config import load_pipeline
    from evchain.core.registry import make_registry

    have = (DATA / "IMU_rotDisk.aedat").is_file()
    spec = load_pipeline(PIPELINE, make_registry(), [] if have else [f"aedat.path={os.devnull}"])
    return {use: spec.stage(use) for use in ("imu_truth", "lk_flow", "flow_scorer")}


def _input(quick: bool):
    """``(packets, imu_truth params override, data)``: IMU_rotDisk, or the rolling camera."""
    path = DATA / "IMU_rotDisk.aedat"
    if path.is_file():
        from evchain.io.aedat2 import read_aedat2, read_imu

        ev = read_aedat2(path)
        imu = read_imu(path)
        imu = imu[(imu["t"] >= ev.t_start) & (imu["t"] < ev.t_end)]
        return (cut_every(ev.with_series(IMU.name, imu)), {},
                "DVSFLOW16 IMU_rotDisk (real DAVIS240C, rolling camera, 3.2 s)")
    from evchain.testing.synthetic import RollingCamera

    cam = RollingCamera(Geometry(240, 180), centre=(131.0, 98.0), w0=0.5, amp=0.15,
                        period_s=1.0, duration_us=3_200_000)
    ev = cam.events().with_series(IMU.name, cam.imu(bias_dps=SIM_BIAS, noise_dps=0.1))
    return (cut_every(ev), {"gyro_bias_dps": SIM_BIAS, "calibration_us": 1_000_000},
            "synthetic rolling camera 240x180, 3.2 s, 29 deg/s mean roll, gyro 1 kHz "
            "(IMU_rotDisk not present)")


def _chain(stages, override: dict, geometry: Geometry):
    ctx = Context(geometry=geometry)
    made = []
    for use, st in stages.items():
        f = st.cls()
        f.id = st.id or use
        params = st.params.model_copy(update=override) if use == "imu_truth" else st.params
        f.setup(params, ctx)
        made.append(f)
    return made, ctx


def _run(stages, override, packets) -> tuple[dict, float, float, float]:
    """One pass; returns the metrics and the CPU seconds (this thread) of imu_truth,
    lk_flow and flow_scorer."""
    (truth, lk, scorer), ctx = _chain(stages, override, packets[0].geometry)
    cpu = [0.0, 0.0, 0.0]

    def step(i, f, p, final=False):
        c0 = time.thread_time()
        out = f.flush() if final else f.process(p)
        cpu[i] += time.thread_time() - c0
        return out

    for p in [*packets, None]:
        out = step(0, truth, p, final=p is None)
        flows = [] if out is None else [step(1, lk, out)]
        if p is None:
            last = step(1, lk, None, final=True)
            flows += [last] if last is not None else []
        for fl in flows:
            step(2, scorer, fl)
    step(2, scorer, None, final=True)
    for f in (truth, lk, scorer):
        f.close()
    return ctx.metrics, *cpu


def imu_truth_rows(quick: bool) -> list[BenchRow]:
    stages = _stages()
    packets, override, data = _input(quick)
    n = sum(len(p) for p in packets)
    runs = [_run(stages, override, packets) for _ in range(1 if quick else 3)]
    metrics = runs[0][0]
    best = min(runs, key=lambda r: r[1] + r[3])
    flow, truth = metrics["flow"], metrics["imu_truth"]
    return [BenchRow(
        "imu-truth", "imu_truth", n / (best[1] + best[3]), "ev/s (CPU)", flow["aee_pxs"],
        "aee_pxs", None,
        {"events": n, "imu_truth_eps": n / best[1], "flow_scorer_s": best[3],
         "lk_flow_s": best[2], "aee_normal_pxs": flow["aee_normal_pxs"],
         "aae_deg": flow["aae_deg"], "n_scored": flow["n_scored"],
         "share_with_truth": truth["events"]["share_with_truth"],
         "principal_point_px": truth["camera"]["principal_point_px"],
         "imu_truth_params": override or "the pipeline's"},
        data=data, params_from="pipelines/dvsflow16-imu-lk.yaml")]


def plot_imu_rate_rows(quick: bool) -> list[BenchRow]:
    return plot_rows(*_input(quick), repeat=1 if quick else 3)


def plot_rows(packets, override: dict, data: str, repeat: int = 3) -> list[BenchRow]:
    """``imu_rate_plot`` on the ``imu_rate`` series of ``imu_truth`` (the pipeline's, with
    ``override``) on ``packets`` (events with the series ``imu``)."""
    from evchain.filters.imu_rate_plot import ImuRatePlot
    from evchain.testing.contract import make_context

    stages = _stages()
    (truth,), _ = _chain({"imu_truth": stages["imu_truth"]}, override, packets[0].geometry)
    rated = [truth.process(p) for p in packets]
    last = truth.flush()
    rated += [last] if last is not None else []
    bins = sum(len(p.series.get("imu_rate", ())) for p in rated)
    with tempfile.TemporaryDirectory() as tmp:
        ctx = make_context(packets[0].geometry, out_dir=Path(tmp))

        def stage():
            f = ImuRatePlot()
            f.id = "imu_rate_plot"
            f.setup(ImuRatePlot.Params(), ctx)
            for p in rated:
                f.process(p)
            f.flush()

        wall = best_time(stage, repeat=repeat)
        cpu = best_cpu_time(stage, repeat=1)
        png = Path(ctx.metrics["imu_rate_plot"]["path"])
        size = png.stat().st_size
    return [BenchRow(
        "plot-imu-rate", "imu_rate_plot", 1 / wall, "plots/s", None,
        "none (draws the series as given)", None,
        {"bins": bins, "bins_per_s": bins / wall, "cpu_plots_per_s": 1 / cpu,
         "png_bytes": size, "notes": "no error: the plot estimates nothing"},
        data=f"{data}; imu_rate of imu_truth, {bins} bins", params_from=relative(PIPELINE))]


def imu_packets(samples: int, geometry: Geometry, t0: int = 0, seed: int = 0
                ) -> list[EventPacket]:
    """10 ms packets of ``samples`` IMU samples at 1 kHz from ``t0`` (random readings within
    a DAVIS IMU's ranges, exact in float32 and as 16-bit readings at 8 g and 1000 deg/s) with
    one random DVS event at the time of each."""
    from evchain.io.davis_imu import ACCEL_LSB_PER_G, GYRO_LSB_PER_DPS

    rng = np.random.default_rng(seed)
    t = t0 + 1000 * np.arange(samples, dtype=np.int64)
    a = rng.integers(-30000, 30000, (samples, 3)) / ACCEL_LSB_PER_G[8]
    g = rng.integers(-30000, 30000, (samples, 3)) / GYRO_LSB_PER_DPS[1000]
    imu = IMU.array(t=t, ax=a[:, 0], ay=a[:, 1], az=a[:, 2], gx=g[:, 0], gy=g[:, 1],
                    gz=g[:, 2], temperature_c=30.0)
    ev = EventPacket(geometry=geometry, t_start=int(t[0]), t_end=int(t[-1]) + 1000,
                     x=rng.integers(0, geometry.width, samples).astype(np.uint16),
                     y=rng.integers(0, geometry.height, samples).astype(np.uint16),
                     t=t.copy(), p=rng.choice(np.array([-1, 1], np.int8), samples))
    return cut_every(ev.with_series(IMU.name, imu))


def imu_data(samples: int) -> str:
    return (f"{samples / 1000:g} k IMU samples at 1 kHz with one DVS event each "
            "(the whole file is read)")


def imu_read_aedat(quick: bool) -> list[BenchRow]:
    from evchain.io.aedat2 import CHIPS, AedatSource, header_bytes, read_header, write_aedat2
    from evchain.io.atomic import AtomicFile
    from evchain.io.davis_imu import ACCEL_LSB_PER_G, CAMERA_SIGNS, GYRO_LSB_PER_DPS, encode_samples

    n = 50_000 if quick else 200_000
    ev = EventPacket.concat(imu_packets(n, Geometry(240, 180)))
    imu = ev.series[IMU.name]
    cols = ("ax", "ay", "az", "temperature_c", "gx", "gy", "gz")
    lsb = [ACCEL_LSB_PER_G[8]] * 3 + [1.0] + [GYRO_LSB_PER_DPS[1000]] * 3
    raw = np.stack([np.rint(imu[c] * CAMERA_SIGNS[i] * lsb[i]) if c != "temperature_c"
                    else np.zeros(n) for i, c in enumerate(cols)], 1).astype(np.int64)
    with tempfile.TemporaryDirectory() as tmp:
        dvs = write_aedat2(Path(tmp) / "dvs.aedat", ev, chip="davis240")
        rec_dvs = np.fromfile(dvs, ">u4", offset=read_header(dvs).data_offset).reshape(-1, 2)
        rec_imu = encode_samples(imu["t"], raw).astype(">u4")
        rec = np.concatenate([rec_imu.reshape(n, 7, 2), rec_dvs.reshape(n, 1, 2)], 1)
        path = Path(tmp) / "imu.aedat"
        prefs = ['<entry key="ImuGyroScale" value="GyroFullScaleDegPerSec1000"/>',
                 '<entry key="ImuAccelScale" value="ImuAccelScaleG8"/>']
        with AtomicFile(path) as out:
            out.write(header_bytes(CHIPS["davis240"], prefs) + rec.astype(">u4").tobytes())
        return [imu_source_row("imu-read-aedat", AedatSource, {"path": str(path)}, path, n,
                               n, imu_data(n))]


WORKLOADS = {"imu-truth": imu_truth_rows, "imu-read-aedat": imu_read_aedat,
             "plot-imu-rate": plot_imu_rate_rows}
