"""Benchmarks: speed measured as ratios within one run (machines here are shared and noisy).

``pwf-dask bench iteration``: the time of one PWF iteration (Algorithm S1: model, Wirtinger
derivative, preconditioner, regularizer, Nesterov update, timed inside the solver's own loop
with its stop-rule statistics) and of one complex64 FFT of the same size, measured in the same
run, and their ratio.
"""

from __future__ import annotations

import json
import math
import shutil
import time
from pathlib import Path

import numpy as np

from benchmarks.reporting import device_name, interleaved_min, write_rows_csv
from pwf_dask import backend
from pwf_dask.backend import FFT, default_fft_workers, resolve_device
from pwf_dask.physics import optics
from pwf_dask.pipeline import estimate
from pwf_dask.pwf import solver
from pwf_dask.stores import scan_io
from pwf_dask.tomo import tomography
from tests.algorithm_s1 import algorithm_s1_inputs, algorithm_s1_step


def iteration_benchmark(
    shape,
    *,
    device: str = "cpu",
    l1_m: float = 3e-3,
    upsample: int = 1,
    field_upsample: float = 1,
    precision: str = "single",
    repeat: int = 3,
    fft_workers: int | None = None,
    sample_field_grid: str = "field",
) -> dict:
    """One row: seconds per iteration, per FFT, and the ratio, for one grid shape.

    ``fft_workers`` is the CPU thread budget of the FFTs and of the threaded element-wise pass
    (default: all cores); 1 is how a scan task runs when the cores are shared among tasks.
    """
    xp = resolve_device(device)
    fft = FFT.for_module(xp, fft_workers)
    rng = np.random.default_rng(1)
    p, (cx, cy) = estimate.TIMING_PIXEL_M, estimate.TIMING_COHERENCE_M
    model, y = estimate.timing_problem(
        shape,
        fft,
        l1_m=l1_m,
        upsample=upsample,
        field_upsample=field_upsample,
        precision=precision,
        sample_field_grid=sample_field_grid,
    )
    # the solver's own loop (stop-rule statistics, restarts and Nesterov included), a fixed
    # number of iterations from a fixed start, so every call does the same work; a call also
    # pays for its set-up (the low-band filter, the first evaluation), which a projection's
    # hundreds of iterations do not see: the iteration is the difference of two call lengths
    # (on the GPU the set-up is 45 ms at 2160 x 2560, eight iterations' worth)
    short, long = 2, 8

    def iteration(n):
        return lambda: solver.pwf(y, model, max_iter=n, tol=0, step=1e-3, step_search=False)

    a = xp.asarray((rng.normal(size=shape) + 1j * rng.normal(size=shape)).astype(model.cdtype))

    def sync():
        if xp is not np:
            xp.cuda.Stream.null.synchronize()

    fns = [lambda: fft.fft2(a), iteration(short), iteration(long)]
    if xp is not np:
        # the CUDA kernels of pwf.kernels beside the default (PWF_DASK_CUDA_KERNELS), the same run
        def with_kernels(n):
            def run():
                saved, backend.cuda_kernels = backend.cuda_kernels, True
                try:
                    solver.pwf(y, model, max_iter=n, tol=0, step=1e-3, step_search=False)
                finally:
                    backend.cuda_kernels = saved

            return run

        fns += [with_kernels(short), with_kernels(long)]
    # scipy's pocketfft beside the library in use: the second yardstick
    pocketfft = FFT.for_module(np, fft.workers, "scipy") if xp is np else None
    if pocketfft is not None and fft.library != "scipy":
        fns.append(lambda: pocketfft.fft2(a))
    literal = upsample == 1 and field_upsample == 1
    if literal:
        inputs = algorithm_s1_inputs(model, p, cx, cy)
        zero = xp.zeros(shape, dtype=model.cdtype)

        def literal_iterations():
            state = (zero, zero, 1.0)
            for _ in range(long - short):
                state = algorithm_s1_step(*state, 1e-3, y, **inputs)

        fns.append(literal_iterations)
    times = interleaved_min(fns, sync, rounds=repeat)
    t_fft, t_it = times[0], (times[2] - times[1]) / (long - short)
    t_lit = times[-1] / (long - short) if literal else math.nan
    gpu = xp is not np
    t_scipy = times[3] if not gpu and len(fns) > 3 + literal else (t_fft if fft.library == "scipy" else math.nan)
    t_kernels = (times[4] - times[3]) / (long - short) if gpu else math.nan
    return {
        "device": device_name(xp),
        "variant": f"L1{'>0' if l1_m else '=0'}, "
        + (f"field on {field_upsample:g}x grid" if field_upsample > 1 else f"upsample {upsample}")
        + (", exp(psi) on the detector grid" if model.sample_field_grid == "detector" else "")
        + f", {precision}",
        "shape": f"{shape[0]}x{shape[1]}",
        "pixels": shape[0] * shape[1],
        "iteration_ms": t_it * 1e3,
        "fft_library": fft.library,
        "fft_ms": t_fft * 1e3,
        "ratio": t_it / t_fft,
        "scipy_fft_ms": t_scipy * 1e3,
        "scipy_ratio": t_it / t_scipy,
        "cuda_kernels_ms": t_kernels * 1e3,
        "literal_ms": t_lit * 1e3,
        "literal_ratio": t_lit / t_fft,
        "fft_workers": fft.workers,
    }


def run_iteration_benchmark(out_dir: str | Path, device: str = "cpu", sizes=None, quick: bool = False) -> list[dict]:
    """All rows for ``pwf-dask bench iteration``; writes ``bench_iteration_<dev>.csv|md|png``."""
    xp = resolve_device(device)
    if sizes is None:
        sizes = [(256, 256)] if quick else [(512, 512), (1024, 1024), (2048, 2048)]
        if xp is not np and not quick:
            sizes.append((2160, 2560))
    variants = [dict(l1_m=3e-3, upsample=1), dict(l1_m=0.0, upsample=1)]
    if xp is np and default_fft_workers() > 1:
        # a scan shares the cores among tasks (one FFT thread each on 2 cores): the ratio there
        variants += [dict(l1_m=3e-3, upsample=1, fft_workers=1), dict(l1_m=0.0, upsample=1, fft_workers=1)]
    if not quick:
        variants += [dict(l1_m=3e-3, upsample=2)] + [dict(l1_m=3e-3, field_upsample=s) for s in (1.5, 2)]
        # the 1.5x grid with exp(psi) on the detector grid: 6 of its FFTs per iteration, not 10
        variants += [dict(l1_m=3e-3, field_upsample=1.5, sample_field_grid="detector")]
    rows = []
    for shape in sizes:
        for v in variants:
            row = iteration_benchmark(shape, device=device, repeat=2 if quick else 5, **v)
            rows.append(row)
            print(
                f"{row['shape']:>10}  {row['variant']:<28} {row['fft_workers']} thr  "
                f"iteration {row['iteration_ms']:9.2f} ms   FFT {row['fft_ms']:8.3f} ms   ratio {row['ratio']:6.1f}"
                + (
                    f"   with CUDA kernels {row['cuda_kernels_ms']:7.2f} ms"
                    if xp is not np
                    else f"   / scipy's FFT {row['scipy_ratio']:6.1f}"
                )
                + f"   as printed {row['literal_ratio']:6.1f}",
                flush=True,
            )
    tag = "gpu" if xp is not np else "cpu"
    out = write_rows_csv(out_dir, f"bench_iteration_{tag}.csv", rows)
    # the library can depend on the thread budget (resolve_fft_library): each one named
    libraries = ", ".join(sorted({f"{r['fft_library']} on {r['fft_workers']} thread(s)" for r in rows}))
    lines = [
        f"# PWF iteration time / complex64 FFT time ({rows[0]['device']}, FFTs: {libraries})",
        "",
        "Measured in one run by `pwf-dask bench iteration`; an iteration is Algorithm S1 with",
        "Algorithm S2's model, Wirtinger derivative, preconditioner and regularizer, timed as the",
        "difference of 8- and 2-iteration solver runs (a run's set-up, which hundreds of iterations",
        "share, left out). Threads: the",
        "thread budget of the FFTs (and of the threaded exp(psi)), the same for the FFT timed beside.",
        "*As printed*: Algorithms S1/S2 transcribed line by line (`tests/algorithm_s1.py`:",
        "16 complex FFTs, 14 with L1 = 0, one array pass per printed operation, as the authors'",
        "released code), timed in the same interleaved rounds; it gives the solver's direction (test).",
        "*FFT*: one complex64 FFT of the library in use (`PWF_DASK_FFT`: MKL on Intel CPUs, and on "
        "others for one thread; else scipy's pocketfft); *scipy FFT*: scipy's, timed beside it (the "
        "same column without MKL).",
        "",
        "| shape | variant | threads | iteration (ms) | FFT (ms) | ratio | scipy FFT (ms) | ratio to scipy FFT "
        "| as printed (ms) | ratio | speed-up |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]

    def printed(r):
        if not math.isfinite(r["literal_ms"]):
            return "| | | |"
        return f"| {r['literal_ms']:.2f} | {r['literal_ratio']:.1f} | {r['literal_ms'] / r['iteration_ms']:.2f} |"

    if tag == "gpu":
        # no scipy FFT on the device: its columns give the CUDA kernels' gain instead
        lines[-4:-3] = [
            "*FFT*: one complex64 FFT (cuFFT, through CuPy). *With CUDA kernels*: the same solver with",
            "the element-wise passes as the CUDA kernels of `pwf_dask.pwf.kernels` (`PWF_DASK_CUDA_KERNELS=1`;",
            "the iteration column: the default, one CuPy kernel per NumPy operation), same rounds.",
        ]
        lines[-2] = lines[-2].replace("scipy FFT (ms) | ratio to scipy FFT", "with CUDA kernels (ms) | kernels' gain")

    def second(r):
        if tag == "gpu":
            return f"{r['cuda_kernels_ms']:.2f} | {r['iteration_ms'] / r['cuda_kernels_ms']:.2f}"
        return f"{r['scipy_fft_ms']:.3f} | {r['scipy_ratio']:.1f}"

    lines += [
        f"| {r['shape']} | {r['variant']} | {r['fft_workers']} | {r['iteration_ms']:.2f} | {r['fft_ms']:.3f} "
        f"| {r['ratio']:.1f} | {second(r)} {printed(r)}"
        for r in rows
    ]
    (out / f"bench_iteration_{tag}.md").write_text("\n".join(lines) + "\n")
    from pwf_dask.plots import bench_ratio_plot

    bench_ratio_plot(out / f"bench_iteration_{tag}.png", rows)
    return rows


def run_scan_benchmark(
    out_dir: str | Path,
    *,
    workers=(1, 2),
    max_iter: int = 150,
    full_iterations: int | None = None,
    work_dir: str | Path | None = None,
) -> list[dict]:
    """``pwf-dask bench scan``: projections per second per worker, scaling, peak memory, model.

    A simulated scan (``demo`` preset, 2 positions x 61 angles of 48 x 128 pixels) is
    retrieved on a distributed LocalCluster of 1 and of 2 single-threaded workers with a fixed
    iteration count (so every run does the same work). The wall time of an 801 x 2160 x 2560
    scan on N workers is modelled as 801 x iterations x t_iter(2160 x 2560) / (N x scaling
    efficiency), with t_iter measured here on a full frame and the iterations PWF needed on the
    simulated scenes (median, or ``full_iterations``); its tomography as 87 row-block tasks
    of the time measured for one (:func:`_full_width_tomo_task_s`) over N x efficiency.
    """
    import shutil
    import tempfile

    from pwf_dask.pipeline.cluster import Runner
    from pwf_dask.pipeline.workflow import retrieve_scan
    from pwf_dask.simulation import simulate_scan

    tmp = Path(work_dir or tempfile.mkdtemp(prefix="pwf-bench-"))
    scan = tmp / "scan.zarr"
    if not scan.exists():
        simulate_scan(scan, preset="demo", seed=0, progress=False)
    rows = []
    for n in workers:
        recon = tmp / f"recon_{n}.zarr"
        shutil.rmtree(recon, ignore_errors=True)
        with Runner("local", workers=n) as runner:
            r = retrieve_scan(scan, recon, runner=runner, max_iter=max_iter, tol=0.0)
        tasks = r["tasks"]
        rows.append(
            {
                "workers": n,
                "projections": len(tasks),
                "wall_s": r["wall_s"],
                "projections_per_s_per_worker": len(tasks) / r["wall_s"] / n,
                "task_s_median": float(np.median([t[5] for t in tasks])),
                "peak_memory_mb_per_worker": float(max(t[6] for t in tasks)),
            }
        )
        print(
            f"{n} worker(s): {rows[-1]['projections_per_s_per_worker']:.2f} projections/s/worker, "
            f"peak {rows[-1]['peak_memory_mb_per_worker']:.0f} MB/worker",
            flush=True,
        )
    eff = rows[-1]["projections_per_s_per_worker"] / rows[0]["projections_per_s_per_worker"]
    # one full-size iteration, measured here (the padded grid of a 2160 x 2560 frame, the field
    # on the grid that "auto" takes for the paper's P3000 at 0.65 um pixels)
    full = iteration_benchmark(
        (solver.fast_len(2160 + 34), solver.fast_len(2560 + 34)), field_upsample=SCAN_FIELD_UPSAMPLE, repeat=1
    )
    iters = full_iterations or 300
    t_proj = full["iteration_ms"] / 1e3 * iters
    t_tomo = _full_width_tomo_task_s()
    blocks = -(-2160 // scan_io.row_block(2160, 2560))
    model = []
    for n in (1, 2, 8, 32, 128):
        e = eff if n > 1 else 1.0
        model.append(
            {
                "workers": n,
                "hours": 801 * t_proj / (n * e) / 3600,
                "tomo_hours": blocks * t_tomo / (n * e) / 3600,
            }
        )
    out = write_rows_csv(out_dir, "bench_scan_cpu.csv", rows)
    lines = [
        f"# Scan retrieval throughput ({full['device']})",
        "",
        "`pwf-dask bench scan`: the `demo` scan (2 x 61 projections of 48 x 128 px, padded to the",
        f"computational grid), {max_iter} PWF iterations per projection, distributed LocalCluster of",
        "single-threaded workers.",
        "",
        "| workers | projections | wall (s) | projections/s/worker | task median (s) | peak memory/worker (MB) |",
        "|---:|---:|---:|---:|---:|---:|",
    ]
    lines += [
        f"| {r['workers']} | {r['projections']} | {r['wall_s']:.1f} | {r['projections_per_s_per_worker']:.2f} | "
        f"{r['task_s_median']:.2f} | {r['peak_memory_mb_per_worker']:.0f} |"
        for r in rows
    ]
    lines += [
        "",
        f"Scaling efficiency 1 -> {rows[-1]['workers']} workers: {eff:.2f}.",
        "",
        f"## Modelled 801 x 2160 x 2560 scan (K = 1), {iters} iterations per projection",
        "",
        f"One iteration on the padded full frame ({full['shape']}, the field on the {SCAN_FIELD_UPSAMPLE:g}x grid "
        f"the paper's diffuser takes) measured here: {full['iteration_ms']:.0f} ms "
        f"({full['ratio']:.1f} FFT-times), so {t_proj / 60:.1f} min per projection on one worker.",
        "",
        f"Tomography: one task (FBP of one {scan_io.row_block(2160, 2560)}-row block, 2560 wide, to a 2560^2 grid, "
        f"{_tomo_timing_text()}): {t_tomo:.0f} s, {blocks} blocks per position.",
        "",
        "| workers | modelled retrieval (h) | modelled tomography (h) |",
        "|---:|---:|---:|",
    ]
    lines += [f"| {m['workers']} | {m['hours']:.2f} | {m['tomo_hours']:.2f} |" for m in model]
    (out / "bench_scan_cpu.md").write_text("\n".join(lines) + "\n")
    return rows


#: angles of the timed full-width FBP task in :func:`run_scan_benchmark`
_TOMO_BENCH_ANGLES = 41
#: the field grid ``field_upsample="auto"`` takes on the paper's scene (P3000 grains fill the
#: detector band: ``retrieval.diffuser_aliasing``), what the modelled scan's iteration is timed on
SCAN_FIELD_UPSAMPLE = 1.5


def _tomo_timing_text() -> str:
    """How :func:`_full_width_tomo_task_s` timed the task, for the report."""
    if tomography.resolve_fbp("auto") == "gridrec":
        return "phase and attenuation by gridding FBP, one thread, timed on 4 of its rows with all 801 angles"
    return f"phase and attenuation by backprojection, one thread, timed from {_TOMO_BENCH_ANGLES} angles"


def _full_width_tomo_task_s(angles: int = _TOMO_BENCH_ANGLES, scan_angles: int = 801) -> float:
    """Seconds of one tomography task of an 801 x 2160 x 2560 scan (one thread, the default
    FBP): two FBPs of a row block (phase and attenuation). The backprojector is timed with
    ``angles`` angles and scaled linearly (its cost is); gridding, whose cost is not linear in
    the angles, with all ``scan_angles`` on 4 rows and scaled to the block's rows (each row is
    its own transform)."""
    rows = scan_io.row_block(2160, 2560)
    gridding = tomography.resolve_fbp("auto") == "gridrec"
    timed_angles, timed_rows = (scan_angles, 4) if gridding else (angles, rows)
    sino = np.random.default_rng(0).random((timed_angles, timed_rows, 2560)).astype(np.float32)
    theta = np.linspace(0.0, 180.0, timed_angles, endpoint=False)
    t0 = time.perf_counter()
    tomography.back_projection(sino, theta, 0.65e-6, fft=FFT.for_module(np, 1))
    return 2 * (time.perf_counter() - t0) * (scan_angles / timed_angles) * (rows / timed_rows)


def run_fbp_benchmark(out_dir: str | Path, quick: bool = False) -> list[dict]:
    """``pwf-dask bench fbp``: gridding FBP against the direct backprojector, side by side in
    one run: 801 angles, one row block's worth of rows (4 here: both are linear in the rows),
    widths up to the camera's 2560 px. One FFT thread each, as one single-threaded worker."""
    sizes = [(181, 4, 256)] if quick else [(801, 4, 512), (801, 4, 1024), (801, 4, 2560)]
    fft = FFT.for_module(np, 1)
    rows = []
    for angles, nrow, nx in sizes:
        sino = np.random.default_rng(0).random((angles, nrow, nx)).astype(np.float32)
        theta = np.linspace(0.0, 180.0, angles, endpoint=False)
        times = {}
        for method in ("gridrec", "backproject"):
            t0 = time.perf_counter()
            tomography.back_projection(sino, theta, 0.65e-6, fft=fft, method=method)
            times[method] = time.perf_counter() - t0
        rows.append(
            {
                "angles": angles,
                "rows": nrow,
                "width_px": nx,
                "backproject_s": times["backproject"],
                "gridrec_s": times["gridrec"],
                "speedup": times["backproject"] / times["gridrec"],
                "threads": fft.workers,
            }
        )
        print(f"{angles} x {nrow} x {nx}: backproject {times['backproject']:.2f} s, gridrec {times['gridrec']:.2f} s")
    write_rows_csv(out_dir, "bench_fbp_cpu.csv", rows)
    full = rows[-1]
    per_position = full["gridrec_s"] / full["rows"] * 2160 * 2  # phase and attenuation, 2160 rows
    # one 2-core worker: the same block with finufft's threads (the task's FFT budget)
    sino = np.random.default_rng(0).random((full["angles"], full["rows"], full["width_px"])).astype(np.float32)
    theta = np.linspace(0.0, 180.0, full["angles"], endpoint=False)
    t0 = time.perf_counter()
    tomography.back_projection(sino, theta, 0.65e-6, fft=FFT.for_module(np, 2), method="gridrec")
    per_position_2 = (time.perf_counter() - t0) / full["rows"] * 2160 * 2
    lines = [
        f"# Gridding FBP against the direct backprojector ({device_name(np)})",
        "",
        "`pwf-dask bench fbp`: the same filtered sinograms (Ram-Lak, angle weights) back-projected by",
        "`tomography.filtered_back_projection` (direct, linear interpolation) and `gridrec.gridrec_back_projection`",
        "(finufft type-1 NUFFT onto the slice's spectrum), one FFT thread each, timed in one run.",
        "",
        "| angles | rows | width (px) | backproject (s) | gridrec (s) | speed-up |",
        "|---:|---:|---:|---:|---:|---:|",
    ]
    lines += [
        f"| {r['angles']} | {r['rows']} | {r['width_px']} | {r['backproject_s']:.2f} | {r['gridrec_s']:.2f} | "
        f"{r['speedup']:.1f}x |"
        for r in rows
    ]
    lines += [
        "",
        f"At {full['width_px']} px, one diffuser position of an {full['angles']}-angle scan with 2160 rows (phase and",
        f"attenuation) takes {per_position / 60:.1f} min of gridrec on one worker against "
        f"{per_position * full['speedup'] / 3600:.1f} h of backprojection; {per_position_2 / 60:.1f} min of gridrec "
        "with two threads (one 2-core worker).",
        "Agreement (tests/test_gridrec.py): 0.7 % relative RMS inside the field of view on a band-limited",
        "Shepp-Logan, against both the backprojector and scikit-image's iradon; they differ at sharp edges, where",
        "the backprojector's linear interpolation blurs and gridding's band-limited one does not.",
    ]
    (Path(out_dir) / "bench_fbp_cpu.md").write_text("\n".join(lines) + "\n")
    return rows


def _start_worker() -> None:
    """What a worker pays once per process whatever task comes first: the imports and numba's
    compiled loops (loaded from its disk cache, ~1.3 s here), done on a 64^2 frame before
    anything is timed, so that it is charged to none of the stages compared (the first one
    timed used to carry it: the 256^2 retrieval until the diffuser fit used compiled loops)."""
    from pwf_dask import calibration, retrieval, simulation

    setup = simulation.SpeckleSetup(shape=(64, 64))
    sim = simulation.simulate_projection(setup, seed=1)
    calibration.fit_coherence_lengths(
        sim.reference,
        setup.pixel_size_m,
        energy_eV=setup.energy_eV,
        diffuser_detector_distance_m=setup.diffuser_detector_distance_m,
    )
    geo = setup.geometry()
    common = dict(
        energy_eV=setup.energy_eV,
        pixel_size_m=setup.pixel_size_m,
        fft_workers=1,
        coherence_length_x_m=setup.coherence_length_x_m,
        coherence_length_y_m=setup.coherence_length_y_m,
    )
    t = retrieval.estimate_diffuser(
        sim.reference, diffuser_detector_distance_m=setup.diffuser_detector_distance_m, **common
    )
    retrieval.retrieve_projection(sim.sample, sim.reference, diffuser=t, max_iter=5, **{**geo, **common})


def run_per_scan_benchmark(out_dir: str | Path, quick: bool = False) -> list[dict]:
    """``pwf-dask bench perscan``: what a scan does once per diffuser position (the coherence
    calibration, the diffuser fit) and once per projection besides PWF's iterations (the model
    build), each against one projection's whole retrieval, timed in one run on the paper's
    geometry (simulated P3000 sandpaper, one FFT thread: one single-threaded worker)."""
    from pwf_dask import calibration, retrieval, simulation

    sizes = [(256, 256)] if quick else [(256, 256), (512, 512), (1024, 1024)]
    rows = []
    _start_worker()
    for shape in sizes:
        setup = simulation.SpeckleSetup(shape=shape)
        sim = simulation.simulate_projection(setup, seed=1)
        geo = setup.geometry()
        calibration.coherence._template_spectrum.cache_clear()  # a fresh worker's calibration
        t0 = time.perf_counter()
        fit = calibration.fit_coherence_lengths(
            sim.reference,
            setup.pixel_size_m,
            energy_eV=setup.energy_eV,
            diffuser_detector_distance_m=setup.diffuser_detector_distance_m,
        )
        t_cal = time.perf_counter() - t0
        coh = dict(coherence_length_x_m=fit.x_m, coherence_length_y_m=fit.y_m)
        common = dict(energy_eV=setup.energy_eV, pixel_size_m=setup.pixel_size_m, fft_workers=1, **coh)
        t0 = time.perf_counter()
        t = retrieval.estimate_diffuser(
            sim.reference, diffuser_detector_distance_m=setup.diffuser_detector_distance_m, **common
        )
        t_dif = time.perf_counter() - t0
        t0 = time.perf_counter()
        solver.build_model(
            t,
            frame_shape=shape,
            pixel_size_m=setup.pixel_size_m,
            wavelength=optics.wavelength_m(setup.energy_eV),
            sample_diffuser_distance_m=setup.sample_diffuser_distance_m,
            diffuser_detector_distance_m=setup.diffuser_detector_distance_m,
            pad=(t.shape[0] - shape[0]) // 2,
            fft=FFT.for_module(np, 1),
            **coh,
        )
        t_model = time.perf_counter() - t0
        t0 = time.perf_counter()
        res = retrieval.retrieve_projection(sim.sample, sim.reference, diffuser=t, **{**geo, **common})
        t_ret = time.perf_counter() - t0
        rows.append(
            {
                "shape": f"{shape[0]}x{shape[1]}",
                "calibration_s": t_cal,
                "diffuser_fit_s": t_dif,
                "model_build_s": t_model,
                "retrieval_s": t_ret,
                "iterations": res.iterations,
                "calibration_pct": 100 * t_cal / t_ret,
                "diffuser_fit_pct": 100 * t_dif / t_ret,
                "model_build_pct": 100 * t_model / t_ret,
            }
        )
        print(
            f"{shape}: calibration {t_cal:.2f} s, diffuser {t_dif:.2f} s, model {t_model:.3f} s, "
            f"retrieval {t_ret:.1f} s ({res.iterations} iterations)",
            flush=True,
        )
    write_rows_csv(out_dir, "bench_per_scan_cpu.csv", rows)
    probe = [] if quick else [per_scan_probe(430, 700), per_scan_probe(430, 2220)]
    if probe:
        write_rows_csv(out_dir, "bench_per_scan_probe_cpu.csv", probe)
    lines = [
        f"# Per-scan work against one projection's retrieval ({device_name(np)})",
        "",
        "`pwf-dask bench perscan`: the paper's geometry (10 keV, 0.65 um pixels, L1 = 3 mm, L2 = 20 mm,",
        "simulated P3000 sandpaper), one FFT thread, timed in one run. The calibration (template fit of the",
        "coherence lengths, fresh template cache; its templates simulated side by side on the driver's",
        f"{default_fft_workers()} cores, as before a scan's tasks start) and the diffuser fit run once per",
        "diffuser position in a scan (`tests/test_workflow.py` counts the fits); the model build runs once per",
        "projection. Retrieval: one projection from zero with the stored diffuser, default stop. A worker's",
        "start-up (imports, numba's cached loops) is paid first, on a 64^2 frame, and charged to none of them.",
        "",
        "| frame | calibration (s) | diffuser fit (s) | model build (s) | retrieval (s) | iterations "
        "| calibration / retrieval | diffuser / retrieval | model / retrieval |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    lines += [
        f"| {r['shape']} | {r['calibration_s']:.2f} | {r['diffuser_fit_s']:.2f} | {r['model_build_s']:.3f} | "
        f"{r['retrieval_s']:.1f} | {r['iterations']} | {r['calibration_pct']:.1f} % | {r['diffuser_fit_pct']:.1f} % | "
        f"{r['model_build_pct']:.2f} % |"
        for r in rows
    ]
    lines += [
        "",
        "The calibration's cost is its templates (simulated speckle of up to 13 grain sizes, 8 at the paper's",
        "pixel, on frames of at least 256 px), nearly independent of the frame, so its share falls with the",
        "frame: per scan it is paid once",
        "per position, against one projection's retrieval for every angle (801 in the paper's scan).",
    ]
    lines += _probe_lines(probe)
    (Path(out_dir) / "bench_per_scan_cpu.md").write_text("\n".join(lines) + "\n")
    return rows


def per_scan_probe(rows: int, columns: int) -> dict:
    """``diffuser_model="auto"``'s probe, once per diffuser position where the absorption rule
    gives zero phase: on the issue's real-data regime (25 keV, the strip of PMMA rods of
    benchmarks/frame_size.py, a crop of ``rows`` x ``columns``; the true coherence lengths, one
    FFT thread), :func:`pwf_dask.retrieval.choose_diffuser` less the whole frame's zero-phase
    estimate (the retrieval needs it whatever the model), against one projection's retrieval
    with the model chosen."""
    from benchmarks.frame_size import STRIP_SETUP, strip_crop, strip_projection
    from pwf_dask import retrieval

    sample, reference, _, _ = strip_projection(STRIP_SETUP, 1)
    crop = strip_crop(STRIP_SETUP, rows, columns)
    sample, reference = sample[crop], reference[crop]
    geo = STRIP_SETUP.geometry()
    lengths = dict(
        coherence_length_x_m=STRIP_SETUP.coherence_length_x_m, coherence_length_y_m=STRIP_SETUP.coherence_length_y_m
    )
    t0 = time.perf_counter()
    retrieval.estimate_diffuser(
        reference,
        energy_eV=geo["energy_eV"],
        pixel_size_m=geo["pixel_size_m"],
        diffuser_detector_distance_m=geo["diffuser_detector_distance_m"],
        fft_workers=1,
        **lengths,
    )
    t_zero = time.perf_counter() - t0
    t0 = time.perf_counter()
    choice = retrieval.choose_diffuser(sample, reference, **geo, **lengths, fft_workers=1)
    t_probe = time.perf_counter() - t0 - t_zero
    t0 = time.perf_counter()
    res = retrieval.retrieve_projection(
        sample, reference, **geo, **lengths, diffuser=choice.transmission, diffuser_model=choice.model, fft_workers=1
    )
    t_ret = time.perf_counter() - t0
    window = retrieval.probe_window((rows, columns))
    row = {
        "shape": f"{rows}x{columns}",
        "probed": f"{window[0].stop - window[0].start}x{window[1].stop - window[1].start}",
        "model": choice.model,
        "probe_s": t_probe,
        "retrieval_s": t_ret,
        "iterations": res.iterations,
        "probe_pct": 100 * t_probe / t_ret,
    }
    print(row, flush=True)
    return row


def _probe_lines(rows: list[dict]) -> list[str]:
    from pwf_dask.retrieval import DIFFUSER_PROBE_ITER

    if not rows:
        return []
    return [
        "",
        '## The diffuser probe (where `"auto"` runs it)',
        "",
        "Once per position where the absorption rule gives zero phase (`retrieval.choose_diffuser` on a scan's",
        "middle angle): the issue's real-data regime (25 keV, 6.5 um pixels, L1 = 0, L2 = 0.7 m, the strip of",
        "PMMA rods of `benchmarks/frame_size.py`, true coherence lengths, one FFT thread). Probe: both diffuser",
        f"estimates and {DIFFUSER_PROBE_ITER} iterations of each model on the frame's centred window of at most",
        "512^2 pixels, a frame of its own (`retrieval.probe_window`); the whole frame's zero-phase estimate,",
        "which the retrieval needs anyway, not counted. Retrieval: one projection with the model chosen,",
        "default stop.",
        "",
        "| frame | probed | model | probe (s) | retrieval (s) | iterations | probe / retrieval |",
        "|---|---|---|---:|---:|---:|---:|",
        *(
            f"| {r['shape']} | {r['probed']} | {r['model']} | {r['probe_s']:.1f} | {r['retrieval_s']:.1f} "
            f"| {r['iterations']} | {r['probe_pct']:.1f} % |"
            for r in rows
        ),
    ]


#: the full-width run's scan: the paper's frame width and angles, a slab of rows (K = 1)
FULLWIDTH_SCAN = dict(preset="paper", shape=(32, 2560), angles=801, positions=1)


def run_fullwidth_benchmark(
    out_dir: str | Path, quick: bool = False, work_dir: str | Path | None = None, device: str = "cpu"
) -> dict:
    """``pwf-dask bench fullwidth``: a simulated scan of the paper's width and angles (801 x
    32 rows x 2560 px, paper optics, K = 1) through ``pwf-dask run --scheduler processes`` on
    this machine (one single-threaded worker per core); the wall time of each stage, the peak
    memory of a retrieval worker, the iterations per projection; and from them the paper's
    801 x 2160 x 2560 scan modelled on 1-128 workers. ``device="gpu"``: ``pwf-dask run --device
    gpu`` on the threaded scheduler (one GPU), the full scan modelled from the iterations per
    projection and one full-frame iteration measured on the GPU."""
    import subprocess
    import sys
    import tempfile

    import zarr

    from pwf_dask.simulation import simulate_scan

    cfg = dict(FULLWIDTH_SCAN, shape=(32, 256), angles=41) if quick else dict(FULLWIDTH_SCAN)
    tmp = Path(work_dir or tempfile.mkdtemp(prefix="pwf-fullwidth-"))
    scan, recon = tmp / "scan.zarr", tmp / "recon.zarr"
    # a work_dir may be given again to finish an interrupted run (``pwf-dask run`` resumes):
    # the simulation goes in under another name until complete, and each invocation's time is kept
    log_path = tmp / "fullwidth_runs.json"
    log = json.loads(log_path.read_text()) if log_path.exists() else {"simulate_s": 0.0, "run_s": []}
    if not scan.exists():
        t0 = time.perf_counter()
        partial = tmp / "scan.partial.zarr"
        shutil.rmtree(partial, ignore_errors=True)
        simulate_scan(partial, seed=0, progress=False, **cfg)
        partial.rename(scan)
        log["simulate_s"] = time.perf_counter() - t0
        log_path.write_text(json.dumps(log))
    t_sim = log["simulate_s"]
    t0 = time.perf_counter()
    gpu = device == "gpu"
    cmd = [sys.executable, "-m", "pwf_dask.cli", "-q", "run", str(scan), str(recon)]
    cmd += ["--device", "gpu"] if gpu else ["--scheduler", "processes"]
    subprocess.run(cmd, check=True)
    log["run_s"].append(time.perf_counter() - t0)
    log_path.write_text(json.dumps(log))
    t_run, invocations = sum(log["run_s"]), len(log["run_s"])
    g = zarr.open_group(str(recon), mode="r", use_consolidated=False)
    a = dict(g.attrs)
    its = g["iterations"][...].ravel()
    ny, nx = cfg["shape"]
    workers = default_fft_workers()
    # the full frame's iteration against this slab's, each on its padded grid, one thread, the
    # field on the grid the paper's diffuser takes (P3000 aliases: retrieval.DIFFUSER_FIELD_UPSAMPLE)
    from pwf_dask.retrieval import DIFFUSER_FIELD_UPSAMPLE

    pad, s = 2 * 17, DIFFUSER_FIELD_UPSAMPLE
    threads = None if gpu else 1
    small = iteration_benchmark(
        (solver.fast_len(ny + pad), solver.fast_len(nx + pad)), device=device, field_upsample=s, fft_workers=threads
    )
    full = iteration_benchmark(
        (solver.fast_len(2160 + pad), solver.fast_len(2560 + pad)),
        device=device,
        field_upsample=s,
        repeat=1 if not gpu else 3,
        fft_workers=threads,
    )
    frame_ratio = full["iteration_ms"] / small["iteration_ms"]
    # one worker's time per projection, as each task recorded it (a killed and resumed run too)
    per_projection_s = float(np.nanmean(g["retrieval_seconds"][...]))
    iterating_s = float(np.mean(its)) * small["iteration_ms"] / 1e3
    if gpu:
        # tasks share the one GPU concurrently: its throughput is the stage's wall time per
        # projection; a full frame fills the GPU alone, so it is modelled as its iterations at
        # the full frame's measured iteration time plus this run's time beyond the iterations
        wall = a.get("retrieval_wall_s_total", a["retrieval_wall_s"])
        per_projection_s = float(wall) / its.size
        full_projection_s = float(np.mean(its)) * full["iteration_ms"] / 1e3 + max(0.0, per_projection_s - iterating_s)
    else:
        # a projection's time beyond its iterations (reading, drift, step search, writing) is
        # taken to grow with the frame as the iterations do: an upper bound
        full_projection_s = per_projection_s * frame_ratio
    row_ratio = 2160 / ny
    # the tomography's tasks are row blocks: its wall time is the largest block's delta and beta
    # slices on one worker (25 and 7 rows here), not the rows shared evenly by the workers
    block_rows = min(ny, scan_io.row_block(ny, nx))
    slice_s = a.get("tomo_wall_s", math.nan) / (2 * block_rows)
    result = {
        "scan": f"{cfg['angles']} x {ny} x {nx}",
        "simulate_s": t_sim,
        "run_s": t_run,
        "retrieval_s": a.get("retrieval_wall_s_total", a["retrieval_wall_s"]),
        "retrieval_runs_projection_s": per_projection_s,
        "tomo_s": a.get("tomo_wall_s", math.nan),
        "fsc_s": a.get("fsc_wall_s", math.nan),
        "workers": workers,
        "retrieval_peak_mb_per_worker": a["retrieval_peak_rss_mb"],
        "iterations_median": float(np.median(its)),
        "iterations_mean": float(np.mean(its)),
        "iterations_max": int(its.max()),
        "converged_fraction": float(np.mean(g["converged"][...])),
        "diffuser_fit_s": a.get("diffuser_fit_s", ""),
        "iteration_ms_slab": small["iteration_ms"],
        "iteration_ms_full_frame": full["iteration_ms"],
        "fbp": a.get("fbp", ""),
    }
    dev = "gpu" if gpu else "cpu"
    write_rows_csv(out_dir, f"bench_fullwidth_{dev}.csv", [result])
    tomo_peak = estimate.tomo_peak_mb(801, scan_io.row_block(2160, 2560), 2560, result["fbp"] or "gridrec")
    model = []
    for n in (1, 2, 4, 8) if gpu else (1, 8, 32, 128):
        retrieval_h = 801 * full_projection_s / n / 3600
        tomo_h = result["tomo_s"] * row_ratio / n / 3600 if gpu else 2 * 2160 * slice_s / n / 3600
        model.append((n, retrieval_h, tomo_h))
    # the FSC compares at most the central FSC_MAX_ROWS rows, whatever the scan's height
    from pwf_dask.pipeline.workflow import FSC_MAX_ROWS

    fsc_rows = min(2160, FSC_MAX_ROWS)
    fsc_h = result["fsc_s"] * fsc_rows / min(ny, FSC_MAX_ROWS) / 3600
    lines = [
        f"# A full-width scan, measured ({device_name(resolve_device(device))})",
        "",
        f"`pwf-dask bench fullwidth`: a simulated scan of {result['scan']} (angles x rows x columns; the paper's",
        "optics: 10 keV, 0.65 um pixels, L1 = 3 mm, L2 = 20 mm, P3000 sandpaper, K = 1, coherence calibrated)",
        f"run by `pwf-dask run {' '.join(cmd[cmd.index(str(recon)) + 1 :])}`"
        + (" (one GPU, the threaded scheduler)" if gpu else f" ({workers} single-threaded workers, this machine)")
        + ", defaults",
        "otherwise. Stage wall times as the store records them.",
        "",
        "| stage | wall (s) |",
        "|---|---:|",
        f"| simulate the scan (not part of a run) | {t_sim:.0f} |",
        f"| retrieval (PWF, every projection) | {result['retrieval_s']:.0f} |",
        f"| tomography ({result['fbp']}) | {result['tomo_s']:.1f} |",
        f"| FSC (even/odd halves) | {result['fsc_s']:.1f} |",
        f"| the whole `pwf-dask run` ({invocations} invocation{'s' if invocations > 1 else ''}) | {t_run:.0f} |",
        "",
        f"Iterations per projection: median {result['iterations_median']:.0f}, mean {result['iterations_mean']:.0f}, "
        f"max {result['iterations_max']}; converged {100 * result['converged_fraction']:.0f} %.",
        f"Peak memory of a retrieval worker: {result['retrieval_peak_mb_per_worker']:.0f} MB (resident, imports "
        f"included). Diffuser fit (once, s): {result['diffuser_fit_s']}.",
        "",
        "## The paper's 801 x 2160 x 2560 scan, modelled from this run",
        "",
        *(
            [
                f"- Retrieval: {per_projection_s:.2f} s per projection here (the GPU's throughput over the stage),"
                f" {iterating_s:.2f} s of iterations",
                f"  per projection at the slab's single-stream iteration ({small['iteration_ms']:.2f} ms); a full"
                " frame:"
                f" {result['iterations_mean']:.0f} iterations x {full['iteration_ms']:.1f} ms (measured now, padded",
                f"  2160 x 2560 at the {s}x field grid) plus the time beyond the iterations: {full_projection_s:.1f} s"
                " per projection,",
                "  at the same iterations per projection (full frames may need more: issue #27).",
            ]
            if gpu
            else [
                f"- Retrieval: {per_projection_s:.1f} s per projection on one worker here ({iterating_s:.1f} s of it in"
                " the",
                "  iterations alone), times the full frame's iteration over this slab's (each padded, one thread,",
                f"  measured now: {full['iteration_ms']:.0f} ms against {small['iteration_ms']:.1f} ms,"
                f" x{frame_ratio:.0f}): {full_projection_s / 60:.1f} min per projection,",
                "  at the same iterations per projection (full frames may need more: issue #27).",
            ]
        ),
        (
            f"- Tomography: this run's {result['tomo_s']:.1f} s on one GPU, linear in the rows (x{row_ratio:.1f});"
            if gpu
            else f"- Tomography: this run's {result['tomo_s']:.1f} s is one worker's {2 * block_rows} slices (its"
            f" largest row block, {block_rows} rows, delta and beta): {slice_s:.2f} s a slice, times 2 x 2160 slices;"
        )
        + f" a task's peak memory {tomo_peak:.0f} MB (`pwf_dask.pipeline.estimate`).",
        f"- FSC runs in the client, not on the workers, on the central {fsc_rows} rows"
        f" (`workflow.FSC_MAX_ROWS`): {fsc_h * 60:.1f} min, whatever the workers.",
        "- Tasks are independent: time divided by the workers (no scaling loss assumed).",
        "",
        "| GPUs | retrieval (h) | tomography (h) |"
        if gpu
        else "| CPU workers (1 thread each) | retrieval (h) | tomography (h) |",
        "|---:|---:|---:|",
    ]
    lines += [f"| {n} | {r:.2f} | {t:.3f} |" for n, r, t in model]
    (Path(out_dir) / f"bench_fullwidth_{dev}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return result
