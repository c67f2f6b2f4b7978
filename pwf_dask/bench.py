"""Benchmarks: speed measured as ratios within one run (machines here are shared and noisy).

``pwf-dask bench iteration``: the time of one PWF iteration (Algorithm S1: model, Wirtinger
derivative, preconditioner, regularizer, Nesterov update) and of one complex64 FFT of the same
size, measured in the same run, and their ratio.
"""

from __future__ import annotations

import csv
import platform
import time
from pathlib import Path

import numpy as np

from . import optics, solver
from .backend import FFT, default_fft_workers, resolve_device


def _interleaved_min(fns, sync, rounds: int, min_time: float = 0.15) -> list[float]:
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


def iteration_benchmark(
    shape, *, device: str = "cpu", l1_m: float = 3e-3, upsample: int = 1, precision: str = "single", repeat: int = 3
) -> dict:
    """One row: seconds per iteration, per FFT, and the ratio, for one grid shape."""
    xp = resolve_device(device)
    fft = FFT.for_module(xp)
    rng = np.random.default_rng(0)
    wl = optics.wavelength_m(10_000)
    p = 0.65e-6
    t = xp.asarray(np.exp(1j * rng.normal(size=shape)).astype(np.complex64))
    model = solver.build_model(
        t,
        frame_shape=shape,
        pixel_size_m=p,
        wavelength=wl,
        sample_diffuser_distance_m=l1_m,
        diffuser_detector_distance_m=0.02,
        coherence_length_x_m=3.47e-6,
        coherence_length_y_m=4.31e-6,
        upsample=upsample,
        precision=precision,
        fft=fft,
    )
    y = xp.asarray(rng.random(shape).astype(np.float32) + 0.5)
    state = {"psi": xp.zeros(shape, model.cdtype), "phi_prev": xp.zeros(shape, model.cdtype)}

    def iteration():
        _, d, _ = solver.objective_and_direction(state["psi"], y, model)
        phi = state["psi"] - 1e-3 * d
        state["psi"] = phi + 0.5 * (phi - state["phi_prev"])
        state["phi_prev"] = phi

    a = xp.asarray((rng.normal(size=shape) + 1j * rng.normal(size=shape)).astype(model.cdtype))

    def sync():
        if xp is not np:
            xp.cuda.Stream.null.synchronize()

    t_fft, t_it = _interleaved_min([lambda: fft.fft2(a), iteration], sync, rounds=repeat)
    return {
        "device": device_name(xp),
        "variant": f"L1{'>0' if l1_m else '=0'}, upsample {upsample}, {precision}",
        "shape": f"{shape[0]}x{shape[1]}",
        "pixels": shape[0] * shape[1],
        "iteration_ms": t_it * 1e3,
        "fft_ms": t_fft * 1e3,
        "ratio": t_it / t_fft,
        "fft_workers": fft.workers,
    }


def device_name(xp) -> str:
    if xp is np:
        return f"CPU {platform.processor() or platform.machine()} ({default_fft_workers()} FFT threads)"
    props = xp.cuda.runtime.getDeviceProperties(xp.cuda.Device().id)
    name = props["name"]
    return name.decode() if isinstance(name, bytes) else str(name)


def run_iteration_benchmark(out_dir: str | Path, device: str = "cpu", sizes=None, quick: bool = False) -> list[dict]:
    """All rows for ``pwf-dask bench iteration``; writes ``bench_iteration_<dev>.csv|md|png``."""
    xp = resolve_device(device)
    if sizes is None:
        sizes = [(256, 256)] if quick else [(512, 512), (1024, 1024), (2048, 2048)]
        if xp is not np and not quick:
            sizes.append((2160, 2560))
    variants = [dict(l1_m=3e-3, upsample=1), dict(l1_m=0.0, upsample=1)]
    if not quick:
        variants.append(dict(l1_m=3e-3, upsample=2))
    rows = []
    for shape in sizes:
        for v in variants:
            row = iteration_benchmark(shape, device=device, repeat=2 if quick else 5, **v)
            rows.append(row)
            print(
                f"{row['shape']:>10}  {row['variant']:<28} iteration {row['iteration_ms']:9.2f} ms   "
                f"FFT {row['fft_ms']:8.3f} ms   ratio {row['ratio']:6.1f}",
                flush=True,
            )
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    tag = "gpu" if xp is not np else "cpu"
    with open(out / f"bench_iteration_{tag}.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    lines = [
        f"# PWF iteration time / complex64 FFT time ({rows[0]['device']})",
        "",
        "Measured in one run by `pwf-dask bench iteration`; an iteration is Algorithm S1 with",
        "Algorithm S2's model, Wirtinger derivative, preconditioner and regularizer.",
        "",
        "| shape | variant | iteration (ms) | FFT (ms) | ratio |",
        "|---|---|---:|---:|---:|",
    ]
    lines += [
        f"| {r['shape']} | {r['variant']} | {r['iteration_ms']:.2f} | {r['fft_ms']:.3f} | {r['ratio']:.1f} |"
        for r in rows
    ]
    (out / f"bench_iteration_{tag}.md").write_text("\n".join(lines) + "\n")
    from .plots import bench_ratio_plot

    bench_ratio_plot(out / f"bench_iteration_{tag}.png", rows)
    return rows
