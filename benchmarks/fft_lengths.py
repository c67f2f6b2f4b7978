"""FFT lengths of the padded frame and the field grid: pwf-dask's rule against scipy's.

A frame is padded (17 px a side for the demo's optics) and rounded up to a fast FFT length
(:func:`pwf_dask.pwf.model.fast_len`), and the field grid is 1.5x that, rounded again. Until
session 52 the rounding was scipy's ``next_fast_len``, which admits the factor 11 and odd
lengths (a 512^2 frame's grid 550^2 = (2 x 5^2 x 11)^2, its field grid 825^2, the camera's
2160 x 2560 frame 2200 x 2625); the rule now is no prime factor above 7 and divisible by 4
(560^2, 840^2, 2240 x 2688). Each row times one PWF iteration (the solver's own loop, as
``pwf-dask bench iteration`` times it: the difference of a short and a long run) of the paper's
optics on both grids of one frame, interleaved in one run, on one thread of each CPU FFT
library (the library in use, and scipy's pocketfft beside it where they differ).

``--part sizes`` times the 2-D transforms themselves (complex and real, one thread, each
library) at every side from 200 to 4100 px whose prime factors are at most 11, and weighs them
as an iteration does (8 complex and 9 real transforms and the element-wise passes) for every
side n from 256 to 3700: the cost of ``fast_len(n)`` over that of scipy's choice.

    python -m benchmarks.fft_lengths [--out benchmarks/results] [--part iterations|sizes|all] [--quick]

Writes ``fft_lengths.md`` and ``.csv`` (iterations: about 12 min on 2 cores, the camera frame's
field grid most of it; ``--quick``: the three square frames only) and ``fft_lengths_sizes.md``
and ``.csv`` (sizes: about 6 min).
"""

from __future__ import annotations

import argparse
import contextlib
import math

import numpy as np
import scipy.fft

from benchmarks.reporting import device_name, interleaved_min, write_rows_csv
from pwf_dask.backend import FFT
from pwf_dask.pipeline import estimate
from pwf_dask.pwf import model as pwf_model
from pwf_dask.pwf import solver

FRAMES = [(256, 256), (512, 512), (1024, 1024), (2160, 2560)]
FIELD_UPSAMPLES = (1.0, 1.5)
PAD = 17
#: sides whose transforms ``--part sizes`` times, and the sides n whose rounding it weighs
SIZE_RANGE = (200, 4100)
WEIGHED_SIDES = (256, 3700)
#: an iteration's transforms (L1 > 0) and its element-wise seconds per grid point (27 ms at
#: 1024^2 on one thread of the AMD EPYC, session 52: an iteration less its timed transforms)
COMPLEX_FFTS, REAL_FFTS, ELEMENTWISE_S_PER_POINT = 8, 9, 2.6e-8


def scipy_len(n: int) -> int:
    """The rule before session 52: scipy's next fast length of pocketfft (factors up to 11)."""
    return int(scipy.fft.next_fast_len(int(n), real=False))


@contextlib.contextmanager
def length_rule(rule):
    """Grids built inside round their sides by ``rule`` (the model looks ``fast_len`` up when
    it builds the field grid)."""
    saved = pwf_model.fast_len
    pwf_model.fast_len = rule
    try:
        yield
    finally:
        pwf_model.fast_len = saved


def row(frame, field_upsample: float, fft: FFT) -> dict:
    """One frame at one field grid: the iteration on both rules' grids, timed side by side."""
    grids, runs = {}, []
    big = frame[0] * frame[1] * field_upsample**2 > 2e6
    short, long = (1, 3) if big else (2, 6)
    for name, rule in (("scipy", scipy_len), ("pwf-dask", pwf_model.fast_len)):
        with length_rule(rule):
            grid = tuple(rule(n + 2 * PAD) for n in frame)
            model, y = estimate.timing_problem(grid, fft, field_upsample=field_upsample)
        grids[name] = (grid, model.field_shape)
        for n in (short, long):
            runs.append(
                lambda n=n, model=model, y=y: solver.pwf(y, model, max_iter=n, tol=0, step=1e-3, step_search=False)
            )
    t = interleaved_min(runs, lambda: None, rounds=2 if big else 3, min_time=0.1)
    old, new = (t[1] - t[0]) / (long - short), (t[3] - t[2]) / (long - short)

    def shape(s):
        return "x".join(map(str, s))

    return {
        "frame": shape(frame),
        "field_upsample": field_upsample,
        "fft_library": fft.library,
        "scipy_grid": shape(grids["scipy"][0]),
        "scipy_field_grid": shape(grids["scipy"][1]),
        "scipy_iteration_ms": old * 1e3,
        "grid": shape(grids["pwf-dask"][0]),
        "field_grid": shape(grids["pwf-dask"][1]),
        "iteration_ms": new * 1e3,
        "time_ratio": new / old,
        "pixel_ratio": math.prod(grids["pwf-dask"][1]) / math.prod(grids["scipy"][1]),
    }


def write_report(out_dir, rows: list[dict]) -> None:
    lines = [
        f"# FFT lengths: pwf-dask's rule against scipy's next_fast_len ({device_name(np)})",
        "",
        "`python -m benchmarks.fft_lengths`: one PWF iteration (the paper's optics, L1 > 0, single precision,",
        f"one FFT thread) on the grid of a frame padded by {PAD} px a side, rounded up by scipy's `next_fast_len`",
        "(factors up to 11, odd lengths; the rule until session 52) and by `pwf_dask.pwf.model.fast_len`",
        "(factors up to 7, divisible by 4), the field grid 1.5x that where it is used. Timed interleaved in one",
        "run; *time* is pwf-dask's rule over scipy's, *pixels* the same for the field grid's size.",
        "",
        "| frame | field grid | FFTs | scipy's grid | field grid | iteration (ms) "
        "| pwf-dask's grid | field grid | iteration (ms) | time | pixels |",
        "|---|---:|---|---|---|---:|---|---|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['frame']} | {r['field_upsample']:g}x | {r['fft_library']} "
            f"| {r['scipy_grid']} | {r['scipy_field_grid']} "
            f"| {r['scipy_iteration_ms']:.1f} | {r['grid']} | {r['field_grid']} | {r['iteration_ms']:.1f} "
            f"| {r['time_ratio']:.2f} | {r['pixel_ratio']:.3f} |"
        )
    write_rows_csv(out_dir, "fft_lengths.csv", rows)
    with open(f"{out_dir}/fft_lengths.md", "w") as fh:
        fh.write("\n".join(lines) + "\n")


def size_rows(libraries) -> list[dict]:
    """The fastest of a few 2-D complex and real transforms of each side's square, per library."""
    rng = np.random.default_rng(0)
    rows = []
    for n in (n for n in range(*SIZE_RANGE) if pwf_model._smooth(n, (2, 3, 5, 7, 11))):
        a = (rng.standard_normal((n, n)) + 1j * rng.standard_normal((n, n))).astype(np.complex64)
        r = np.ascontiguousarray(a.real)
        row = {"side": n}
        for fft in libraries:
            runs = [lambda fft=fft, a=a: fft.fft2(a), lambda fft=fft, r=r: fft.rfft2(r)]
            c2c, r2c = interleaved_min(runs, lambda: None, rounds=3, min_time=0)
            row[f"{fft.library}_c2c_ms"], row[f"{fft.library}_r2c_ms"] = c2c * 1e3, r2c * 1e3
        rows.append(row)
        print(n, {k: round(v, 3) for k, v in row.items() if k != "side"}, flush=True)
    return rows


def weighed_rounding(rows: list[dict], library: str, lo: int, hi: int) -> dict:
    """An iteration's cost on ``fast_len(n)`` over that on scipy's choice, for n in [lo, hi)."""
    by_side = {r["side"]: r for r in rows}

    def cost(m):
        r = by_side[m]
        return (
            COMPLEX_FFTS * r[f"{library}_c2c_ms"] / 1e3
            + REAL_FFTS * r[f"{library}_r2c_ms"] / 1e3
            + ELEMENTWISE_S_PER_POINT * m * m
        )

    ratio = np.array([cost(pwf_model.fast_len(n)) / cost(scipy_len(n)) for n in range(lo, hi)])
    return {
        "library": library,
        "sides": f"{lo}-{hi - 1}",
        "mean": float(ratio.mean()),
        "p10": float(np.quantile(ratio, 0.1)),
        "p90": float(np.quantile(ratio, 0.9)),
        "max": float(ratio.max()),
    }


def write_sizes_report(out_dir, rows: list[dict], libraries: list[str]) -> None:
    lo, hi = WEIGHED_SIDES
    summary = [weighed_rounding(rows, lib, a, b) for lib in libraries for a, b in ((lo, 1200), (1200, hi + 1))]
    lines = [
        f"# FFT lengths: 2-D transforms by side, and the rounding rules weighed ({device_name(np)})",
        "",
        "`python -m benchmarks.fft_lengths --part sizes`: the fastest of three 2-D complex64 FFTs and float32",
        f"real FFTs of an n x n square, one thread, for every n in [{SIZE_RANGE[0]}, {SIZE_RANGE[1]}) with no",
        f"prime factor above 11 (`fft_lengths_sizes.csv`). Each side n from {lo} to {hi} is then rounded by",
        "`pwf_dask.pwf.model.fast_len` (factors up to 7, divisible by 4) and by scipy's `next_fast_len`, and the",
        f"two weighed as an iteration: {COMPLEX_FFTS} complex and {REAL_FFTS} real transforms plus",
        f"{ELEMENTWISE_S_PER_POINT:g} s of element-wise work a grid point. Below: fast_len's cost over scipy's.",
        "",
        "| FFTs | sides n | mean | 10th percentile | 90th percentile | max |",
        "|---|---|---:|---:|---:|---:|",
    ]
    lines += [
        f"| {s['library']} | {s['sides']} | {s['mean']:.3f} | {s['p10']:.3f} | {s['p90']:.3f} | {s['max']:.3f} |"
        for s in summary
    ]
    write_rows_csv(out_dir, "fft_lengths_sizes.csv", rows)
    with open(f"{out_dir}/fft_lengths_sizes.md", "w") as fh:
        fh.write("\n".join(lines) + "\n")


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="benchmarks/results")
    ap.add_argument("--part", choices=("iterations", "sizes", "all"), default="iterations")
    ap.add_argument("--quick", action="store_true", help="the square frames only")
    args = ap.parse_args(argv)
    libraries = [FFT.for_module(np, 1)]
    if libraries[0].library != "scipy":
        libraries.append(FFT.for_module(np, 1, "scipy"))
    if args.part in ("sizes", "all"):
        write_sizes_report(args.out, size_rows(libraries), [fft.library for fft in libraries])
        if args.part == "sizes":
            return []
    rows = []
    for frame in FRAMES[:3] if args.quick else FRAMES:
        for field_upsample in FIELD_UPSAMPLES:
            for fft in libraries:
                rows.append(row(frame, field_upsample, fft))
                r = rows[-1]
                print(
                    f"{r['frame']} {field_upsample:g}x {fft.library}: "
                    f"{r['scipy_field_grid']} {r['scipy_iteration_ms']:.1f} ms, "
                    f"{r['field_grid']} {r['iteration_ms']:.1f} ms ({r['time_ratio']:.2f})",
                    flush=True,
                )
    write_report(args.out, rows)
    return rows


if __name__ == "__main__":
    main()
