"""Series streamed to CSV: the same text as writing the whole series at once, row by row."""

import numpy as np

from evchain.io.series_csv import SeriesCsvWriter, csv_rows

DTYPE = [("t", "i8"), ("x", "f4"), ("y", "f8"), ("n", "i4"), ("ok", "?")]


def naive_csv(entries: np.ndarray) -> str:
    """One row at a time, each value converted on its own (the obvious way)."""
    lines = [",".join(entries.dtype.names)]
    for row in entries:
        lines.append(",".join(repr(float(v)) if isinstance(v, np.floating) else str(v)
                              for v in row))
    return "\n".join(lines) + "\n"


def entries(n, seed):
    rng = np.random.default_rng(seed)
    a = np.zeros(n, DTYPE)
    a["t"] = np.sort(rng.integers(0, 10**9, n))
    a["x"] = rng.normal(size=n).astype(np.float32) * 1e3
    a["y"] = rng.normal(size=n) * 10.0 ** rng.integers(-30, 30, n)
    a["n"] = rng.integers(-5, 5, n)
    a["ok"] = rng.random(n) > 0.5
    if n > 3:
        a["y"][:3] = [np.nan, np.inf, -0.0]
        a["x"][1] = np.nan
    return a


def test_rows_match_the_naive_text():
    a = entries(500, 1)
    assert a.dtype.names[0] + "," in naive_csv(a)
    assert naive_csv(a) == ",".join(a.dtype.names) + "\n" + csv_rows(a)
    assert csv_rows(a[:0]) == ""


def test_streamed_file_equals_the_whole_series_written_at_once(tmp_path):
    parts = [entries(n, seed) for seed, n in enumerate([7, 0, 120, 1, 33])]
    w = SeriesCsvWriter(tmp_path / "series")
    for part in parts:
        w.append({"s": part, "empty": part[:0]})
    assert not (tmp_path / "series" / "s.csv").exists()           # not complete yet
    assert (tmp_path / "series" / "s.csv.partial").exists()
    w.commit()
    whole = np.concatenate(parts)
    assert (tmp_path / "series" / "s.csv").read_text() == naive_csv(whole)
    assert (tmp_path / "series" / "empty.csv").read_text() == "t,x,y,n,ok\n"
    assert w.counts == {"s": len(whole), "empty": 0}


def test_abort_leaves_only_the_partial_file(tmp_path):
    w = SeriesCsvWriter(tmp_path)
    w.append({"s": entries(5, 2)})
    w.abort()
    assert not (tmp_path / "s.csv").exists() and (tmp_path / "s.csv.partial").exists()
