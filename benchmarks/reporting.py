"""What every benchmark and study shares: timing ratios within one run, the device's name, rows to CSV."""

from __future__ import annotations

import csv
import platform
import shlex
import sys
import time
from pathlib import Path

import numpy as np

from pwf_dask.backend import default_fft_workers


def interleaved_min(fns, sync, rounds: int, min_time: float = 0.15) -> list[float]:
    """Seconds per call of each function, the minimum over ``rounds`` rounds that alternate
    the functions, so that a noisy neighbour slows both sides of a ratio alike."""
    for fn in fns:
        fn()
    sync()
    best = [float("inf")] * len(fns)
    for _ in range(rounds):
        for i, fn in enumerate(fns):
            n = 0
            t0 = time.perf_counter()
            while True:
                fn()
                n += 1
                sync()
                el = time.perf_counter() - t0
                if el > min_time:
                    break
            best[i] = min(best[i], el / n)
    return best


def command_line(module: str, argv=None) -> str:
    """How a benchmark's files were made, for their header: ``python -m module`` and its
    arguments (``argv``, else the process's), quoted for a shell, ``--out DIR`` and
    ``--report-only`` left out: where the files went, or that the report was written again from
    the CSV, is not how they were made."""
    given = [a for a in (sys.argv[1:] if argv is None else argv) if a != "--report-only"]
    if "--out" in given:
        del given[given.index("--out") : given.index("--out") + 2]
    return shlex.join(["python", "-m", module, *given])


def device_name(xp) -> str:
    if xp is np:
        return f"CPU {platform.processor() or platform.machine()} ({default_fft_workers()} FFT threads)"
    props = xp.cuda.runtime.getDeviceProperties(xp.cuda.Device().id)
    name = props["name"]
    return name.decode() if isinstance(name, bytes) else str(name)


def timed_with(module, name: str, value, call, *args, **kwargs):
    """(``call(*args, **kwargs)``, seconds) with ``module.name`` set to ``value`` for the call
    (a module constant a study varies, such as the diffuser probe's length), restored after."""
    kept = getattr(module, name)
    setattr(module, name, value)
    try:
        t0 = time.perf_counter()
        return call(*args, **kwargs), time.perf_counter() - t0
    finally:
        setattr(module, name, kept)


def _parse_cell(text: str):
    if text in ("True", "False"):
        return text == "True"
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def read_rows_csv(out_dir: str | Path, name: str) -> list[dict]:
    """The rows :func:`write_rows_csv` wrote, with numbers and booleans parsed back."""
    with open(Path(out_dir) / name, newline="") as fh:
        return [{k: _parse_cell(v) for k, v in row.items()} for row in csv.DictReader(fh)]


def rows_of(out_dir: str | Path, name: str, report_only: bool, compute) -> list[dict]:
    """A benchmark's rows: ``compute()`` written to ``out_dir/name``, or with ``report_only``
    the rows that file holds (its report written again without re-running)."""
    if report_only:
        return read_rows_csv(out_dir, name)
    rows = compute()
    write_rows_csv(out_dir, name, rows)
    return rows


def write_rows_csv(out_dir: str | Path, name: str, rows: list[dict]) -> Path:
    """Rows as ``out_dir/name``, creating the folder: one column per key of any row, in the
    order first met; a row without a key (a refused scene) leaves its cell empty."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    with open(out / name, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(dict.fromkeys(k for r in rows for k in r)), restval="")
        w.writeheader()
        w.writerows(rows)
    return out
