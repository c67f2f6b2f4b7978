"""Device checks beside ``pwf-dask bench iteration --device gpu`` (run where a CUDA GPU is):

- ``memory``: a retrieval's device memory (CuPy's pool after one ``retrieve_projection``,
  defaults, 20 iterations) at 256^2 to 2160 x 2560 on the detector and the 1.5x field grid,
  against the host model (``pwf_dask.pipeline.estimate``);
- ``threads``: full-frame projections retrieved one after another against as many threads
  sharing the GPU, each on its own stream (``backend.task_stream``) and all on the null stream;
- ``strip ANGLES``: a 32 x 2560 paper-optics scan of ANGLES angles through ``retrieve_scan``
  on the GPU, with and without the task streams: iterations per projection and wall time;
- ``camera [ROWS COLUMNS]``: the paper preset's projection on the whole 2160 x 2560 camera frame
  (``frame_size_camera.md``'s last row) retrieved on the device, calibrated and with the lengths
  given, the CUDA kernels off and on: gain, error, iterations and seconds; then 2-4 of it at
  once on their own streams (:func:`concurrent_rows`: a scan's throughput per GPU);
- ``tomo``: a 801-angle x 8-row x 2560-px block of exact disc sinograms through the device's
  FBPs (the CuPy backprojector, the CUDA backprojection kernel, gridrec by the package's own
  NUFFT) and the host's gridrec
  (:func:`tomo_rows`): seconds a slice, errors, agreement;
- ``warm``: one step of a warm-start chain on the camera frame (:func:`warm_rows`), under
  either stop rule: iterations and seconds from zero and from the frame before.

``python -m benchmarks.gpu_checks OUT_DIR memory|threads|strip [ANGLES]|camera|tomo|warm``: one JSON line per row
on stdout, and ``OUT_DIR/<part>.json``. Session 42's rows: ``benchmarks/results/memory_model_gpu.md``
and docs/benchmarks.md ("On a GPU").
"""

from __future__ import annotations

import json
import shutil
import sys
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from scipy import ndimage

from pwf_dask import backend, retrieve_projection
from pwf_dask.pipeline import estimate

GEOMETRY = dict(
    energy_eV=10_000,
    pixel_size_m=0.65e-6,
    sample_diffuser_distance_m=3e-3,
    diffuser_detector_distance_m=0.02,
    coherence_length_x_m=3.47e-6,
    coherence_length_y_m=4.31e-6,
)


def frames(shape, rng):
    """A speckle-like reference (smoothed noise, positive) and the sample: it shifted by a
    fraction of a pixel under an absorbing disc."""
    ref = ndimage.gaussian_filter(rng.random(shape), 1.5)
    ref = np.clip(1.0 + 0.3 * (ref - ref.mean()) / ref.std(), 0.05, None)
    yy, xx = np.mgrid[: shape[0], : shape[1]]
    disc = np.clip(1 - ((yy - shape[0] / 2) ** 2 + (xx - shape[1] / 2) ** 2) / (0.3 * min(shape)) ** 2, 0, None)
    sample = ndimage.shift(ref, (0.5, 0.4), order=1, mode="nearest") * np.exp(-0.2 * np.sqrt(disc))
    return sample.astype(np.float32), ref.astype(np.float32)


def memory_rows(cp, rng) -> list[dict]:
    pool, rows = cp.get_default_memory_pool(), []
    for shape in [(256, 256), (1024, 1024), (2160, 2560)]:
        sample, ref = frames(shape, rng)
        for field in (1, 1.5):
            pool.free_all_blocks()
            base = pool.total_bytes()
            t0 = time.perf_counter()
            res = retrieve_projection(
                cp.asarray(sample), cp.asarray(ref), max_iter=20, tol=0, field_upsample=field, **GEOMETRY
            )
            phase = res.phase.get()
            rows.append(
                dict(
                    shape=f"{shape[0]}x{shape[1]}",
                    field_upsample=field,
                    device_mb=(pool.total_bytes() - base) / 1e6,
                    cpu_model_mb=estimate.retrieval_peak_mb(shape, field) - estimate.RETRIEVAL_BASE_MB,
                    seconds=time.perf_counter() - t0,
                    finite=bool(np.isfinite(phase).all()),
                    diffuser_model=res.parameters.get("diffuser_model"),
                )
            )
            print(json.dumps(rows[-1]), flush=True)
    return rows


def _at_once(fn, n: int) -> tuple[list, float]:
    """fn(0) .. fn(n - 1) on ``n`` threads at once: their results and the wall seconds."""
    t0 = time.perf_counter()
    with ThreadPoolExecutor(n) as pool:
        results = list(pool.map(fn, range(n)))
    return results, time.perf_counter() - t0


def thread_rows(cp, rng, n: int = 3, iterations: int = 60) -> list[dict]:
    sample, ref = frames((2160, 2560), rng)

    def one(_):
        with backend.task_stream(cp):
            res = retrieve_projection(
                cp.asarray(sample),
                cp.asarray(ref),
                max_iter=iterations,
                tol=0,
                diffuser_model="zero-phase",
                **GEOMETRY,
            )
            return res.phase.get()

    one(0)  # kernels compiled, FFT plans made
    rows = []
    for streams in (True, False):
        backend.task_streams = streams
        t0 = time.perf_counter()
        alone = [one(k) for k in range(n)]
        t_alone = time.perf_counter() - t0
        shared, t_shared = _at_once(one, n)
        rows.append(
            dict(
                shape="2160x2560",
                projections=n,
                iterations=iterations,
                streams=streams,
                sequential_s=t_alone,
                threads_s=t_shared,
                gain=t_alone / t_shared,
                max_phase_difference=max(float(np.abs(a - b).max()) for a, b in zip(alone, shared)),
            )
        )
        print(json.dumps(rows[-1]), flush=True)
    backend.task_streams = True
    return rows


def strip_rows(angles: int) -> list[dict]:
    import zarr

    from pwf_dask.pipeline.workflow import retrieve_scan
    from pwf_dask.simulation import simulate_scan

    scan = "/tmp/pwf_gpu_strip.zarr"
    for path in (scan, *(f"/tmp/pwf_gpu_strip_{streams}.zarr" for streams in (True, False))):
        shutil.rmtree(path, ignore_errors=True)  # the last run's: stores are never written over
    simulate_scan(scan, preset="paper", shape=(32, 2560), angles=angles, positions=1, seed=0, progress=False)
    rows = []
    for streams in (True, False):
        backend.task_streams = streams
        recon = f"/tmp/pwf_gpu_strip_{streams}.zarr"
        t0 = time.perf_counter()
        retrieve_scan(scan, recon, device="gpu")
        g = zarr.open_group(recon, mode="r", use_consolidated=False)
        its = g["iterations"][...].ravel()
        rows.append(
            dict(
                angles=angles,
                streams=streams,
                wall_s=time.perf_counter() - t0,
                retrieval_wall_s=g.attrs.get("retrieval_wall_s"),
                iterations_median=float(np.median(its)),
                iterations_mean=float(its.mean()),
                iterations_max=int(its.max()),
                converged=float(np.mean(g["converged"][...])),
                iterations=its.tolist(),
            )
        )
        print(json.dumps({k: v for k, v in rows[-1].items() if k != "iterations"}), flush=True)
    backend.task_streams = True
    return rows


def camera_rows(cp, shape=(2160, 2560), seed: int = 0) -> list[dict]:
    """The ``paper`` preset's first projection on the whole camera frame (``frame_size_camera.md``'s
    last row, simulated on the host), retrieved on the device: with PWF's defaults (coherence
    calibrated, as that row), then with those lengths given (the solve alone, as a scan's task
    runs once the scan is calibrated), with the CUDA kernels off and on. A 256^2 crop is
    retrieved first so that compiling kernels and making FFT plans is not timed."""
    from dataclasses import replace

    from benchmarks.frame_size import phase_gain, phase_rms_error
    from pwf_dask.simulation import GEOMETRY_KEYS, SpeckleSetup, SpeckleSimulator
    from pwf_dask.simulation.phantoms import PAPER_BEAD_RADIUS_M, scan_phantom

    t0 = time.perf_counter()
    setup = replace(SpeckleSetup(), shape=tuple(shape))
    phantom = scan_phantom(setup.shape, setup.pixel_size_m, seed, bead_radius_range_m=PAPER_BEAD_RADIUS_M)
    sim = SpeckleSimulator(setup, seed=seed)
    sample, phase, _ = sim.project(phantom)
    reference = sim.reference()
    del sim
    print(json.dumps({"simulated_s": time.perf_counter() - t0}), flush=True)
    geometry = {name: getattr(setup, name) for name in GEOMETRY_KEYS if not name.startswith("coherence")}

    def retrieve(sample, reference, fused: bool, **options):
        saved, backend.cuda_kernels = backend.cuda_kernels, fused
        try:
            cp.cuda.Stream.null.synchronize()
            t0 = time.perf_counter()
            r = retrieve_projection(cp.asarray(sample), cp.asarray(reference), **geometry, **options)
            recovered = cp.asnumpy(r.phase)
            return r, recovered, time.perf_counter() - t0
        finally:
            backend.cuda_kernels = saved

    retrieve(sample[:256, :256], reference[:256, :256], False, max_iter=20)
    retrieve(sample[:256, :256], reference[:256, :256], True, max_iter=20)
    rows, lengths = [], {}
    for coherence, fused in (("calibrated", False), ("given", False), ("given", True)):
        r, recovered, seconds = retrieve(sample, reference, fused, **lengths)
        lengths = {
            "coherence_length_x_m": r.coherence_length_x_m,
            "coherence_length_y_m": r.coherence_length_y_m,
        }
        rows.append(
            dict(
                frame=f"{shape[0]}x{shape[1]}",
                coherence=coherence,
                cuda_kernels=fused,
                phase_gain=phase_gain(recovered, phase),
                phase_rms_error_rad=phase_rms_error(recovered, phase),
                iterations=r.iterations,
                stop=r.parameters.get("stop_reason"),
                field_upsample=r.parameters.get("field_upsample"),
                coherence_x_um=1e6 * r.coherence_length_x_m,
                seconds=seconds,
            )
        )
        print(json.dumps(rows[-1]), flush=True)
    rows += concurrent_rows(cp, lambda: retrieve(sample, reference, False, **lengths), rows[1]["seconds"])
    return rows


#: two of the paper's 801 angles over 180 degrees: the step between a chain's projections
CHAIN_STEP_DEG = 0.45


def warm_rows(cp, shape=(2160, 2560), seed: int = 0, step_deg: float = CHAIN_STEP_DEG) -> list[dict]:
    """One step of a warm-start chain on the camera frame, on the device: the ``paper``
    preset's frame at 0 and ``step_deg`` (simulated on the host), frame 0 from zero under
    ``stationary_terms="j-or-data"`` (its coherence calibrated, then given), frame 1 from frame
    0's psi under either stop rule, and frame 1 from zero under each. On this machine's CPU
    (session 62) they took 300, 160, 160, 300 and 587 iterations; the scan's model (docs/gpu.md)
    takes these counts at the device's iteration time: this measures both."""
    from dataclasses import replace

    from benchmarks.frame_size import phase_gain, phase_rms_error
    from pwf_dask.simulation import GEOMETRY_KEYS, SpeckleSetup, SpeckleSimulator
    from pwf_dask.simulation.phantoms import PAPER_BEAD_RADIUS_M, scan_phantom

    t0 = time.perf_counter()
    setup = replace(SpeckleSetup(), shape=tuple(shape))
    phantom = scan_phantom(setup.shape, setup.pixel_size_m, seed, bead_radius_range_m=PAPER_BEAD_RADIUS_M)
    sim = SpeckleSimulator(setup, seed=seed)
    frames = [sim.project(phantom)[:2]]
    reference = cp.asarray(sim.reference())
    frames.append(sim.project(phantom, step_deg)[:2])
    del sim
    print(json.dumps({"simulated_s": time.perf_counter() - t0}), flush=True)
    geometry = {name: getattr(setup, name) for name in GEOMETRY_KEYS if not name.startswith("coherence")}
    crop = (slice(0, 256), slice(0, 256))
    retrieve_projection(cp.asarray(frames[0][0][crop]), reference[crop], **geometry, max_iter=20)  # plans
    rows, given = [], {}

    def run(name: str, index: int, terms: str, start=None):
        sample, phase = frames[index]
        cp.cuda.Stream.null.synchronize()
        t1 = time.perf_counter()
        r = retrieve_projection(
            cp.asarray(sample),
            reference,
            **geometry,
            **given,
            stationary_terms=terms,
            initial="zero" if start is None else start,
            zero_background=index == 1,  # frame 0 keeps the solver's psi: the next one's start
        )
        recovered = cp.asnumpy(r.phase)
        seconds = time.perf_counter() - t1
        rows.append(
            dict(
                run=name,
                frame=f"{shape[0]}x{shape[1]}",
                stationary_terms=terms,
                iterations=r.iterations,
                converged=bool(r.converged),
                seconds=seconds,
                phase_gain=phase_gain(recovered, phase) if index == 1 else None,
                phase_rms_error_rad=phase_rms_error(recovered, phase) if index == 1 else None,
            )
        )
        print(json.dumps(rows[-1]), flush=True)
        return r

    first = run("frame 0 from zero, calibrating", 0, "j-or-data")
    given.update(coherence_length_x_m=first.coherence_length_x_m, coherence_length_y_m=first.coherence_length_y_m)
    first = run("frame 0 from zero", 0, "j-or-data")
    start = -first.attenuation + 1j * first.phase  # the unzeroed psi, as a chain starts from
    for terms in ("j-or-data", "j"):
        run(f"frame 1 from frame 0 ({step_deg} deg)", 1, terms, start)
    for terms in ("j-or-data", "j"):
        run("frame 1 from zero", 1, terms)
    return rows


def concurrent_rows(cp, retrieve_one, alone_s: float, counts=(2, 3, 4)) -> list[dict]:
    """Throughput of one GPU on whole camera frames: ``n`` retrievals at once on ``n``
    threads, each on its own stream (``backend.task_stream``, as ``pwf-dask run --device
    gpu`` runs its tasks), against ``alone_s``, one retrieval alone. A scan's throughput is
    the seconds per projection at the count that fits the GPU's memory."""

    def one(_):
        with backend.task_stream(cp):
            return retrieve_one()

    rows = []
    for n in counts:
        results, wall = _at_once(one, n)
        rows.append(
            dict(
                concurrent=n,
                wall_s=wall,
                seconds_per_projection=wall / n,
                gain=alone_s * n / wall,
                iterations=[r[0].iterations for r in results],
                max_phase_difference=max(float(np.abs(r[1] - results[0][1]).max()) for r in results),
            )
        )
        print(json.dumps(rows[-1]), flush=True)
    return rows


def _disc_sinogram(angles_deg, rows: int, width: int, rng):
    """The exact parallel-beam sinogram (angle, row, x) of a few discs of random radius,
    centre and value per row (chords 2 sqrt(r^2 - (s - s0)^2)), and the slices (row, v, u)."""
    s = np.arange(width) - (width - 1) / 2
    theta = np.deg2rad(np.asarray(angles_deg))[:, None]
    sino = np.zeros((len(angles_deg), rows, width), np.float32)
    truth = np.zeros((rows, width, width), np.float32)
    vv, uu = np.meshgrid(s, s, indexing="ij")
    for r in range(rows):
        for _ in range(6):
            radius = rng.uniform(0.03, 0.2) * width
            cu, cv = rng.uniform(-0.25, 0.25, 2) * width
            value = rng.uniform(0.5, 2.0)
            s0 = cu * np.cos(theta) + cv * np.sin(theta)
            sino[:, r] += value * 2 * np.sqrt(np.clip(radius**2 - (s[None] - s0) ** 2, 0, None))
            truth[r] += value * ((uu - cu) ** 2 + (vv - cv) ** 2 <= radius**2)
    return sino, truth


def tomo_rows(cp, rows: int = 8, angles: int = 801, width: int = 2560) -> list[dict]:
    """One tomography block on the device (the backprojector, its CUDA kernel, and gridrec by
    the package's own NUFFT, :mod:`pwf_dask.tomo.nufft`) against gridrec on the host's cores
    (finufft): seconds per slice at the camera's width and the paper's angles, and how far they
    agree inside the field of view."""
    from pwf_dask.backend import FFT, default_fft_workers
    from pwf_dask.tomo import tomography

    theta = np.linspace(0.0, 180.0, angles, endpoint=False)
    sino, truth = _disc_sinogram(theta, rows, width, np.random.default_rng(0))
    yy, xx = np.mgrid[:width, :width] - (width - 1) / 2
    inside = xx**2 + yy**2 < (0.45 * width) ** 2
    host_fft = FFT.for_module(np, default_fft_workers())
    device_fft = FFT.for_module(cp)
    out, results = [], {}
    plans = [
        ("host", "gridrec", np, host_fft, False),
        ("device", "backproject", cp, device_fft, False),
        ("device", "backproject", cp, device_fft, True),  # the CUDA backprojection kernel
        ("device", "gridrec", cp, device_fft, False),
    ]
    for where, method, xp, fft, kernel in plans:
        saved, backend.cuda_kernels = backend.cuda_kernels, kernel
        try:
            tomography.back_projection(xp.asarray(sino[:8, :1, :256]), theta[:8], 1.0, fft=fft, method=method)
            cp.cuda.Stream.null.synchronize()
            t0 = time.perf_counter()
            slices = tomography.back_projection(xp.asarray(sino), theta, 1.0, fft=fft, method=method)
            slices = cp.asnumpy(slices) if xp is cp else slices
            seconds = time.perf_counter() - t0
        finally:
            backend.cuda_kernels = saved
        results[(where, method + ("-kernel" if kernel else ""))] = slices
        error = np.sqrt(np.mean((slices[:, inside] - truth[:, inside]) ** 2) / np.mean(truth[:, inside] ** 2))
        out.append(
            dict(
                where=where,
                fbp=method,
                cuda_kernel=kernel,
                threads=fft.workers if xp is np else None,
                angles=angles,
                rows=rows,
                width_px=width,
                seconds=seconds,
                seconds_per_slice=seconds / rows,
                position_s=seconds / rows * 2160 * 2,  # phase and attenuation, 2160 rows
                relative_rms_error_to_truth=float(error),
            )
        )
        print(json.dumps(out[-1]), flush=True)
    out += background_rows(cp, results[("host", "gridrec")])
    host, device = results[("host", "gridrec")], results[("device", "backproject")]
    agreement = np.sqrt(np.mean((device[:, inside] - host[:, inside]) ** 2) / np.mean(host[:, inside] ** 2))
    kernel = results[("device", "backproject-kernel")]
    kernel_gap = np.abs(kernel - device).max() / np.abs(device).max()
    gridded = results[("device", "gridrec")]
    out.append(
        dict(
            device_backproject_vs_host_gridrec_relative_rms=float(agreement),
            cuda_kernel_vs_backproject_max_relative=float(kernel_gap),
            device_gridrec_vs_host_gridrec_max_relative=float(np.abs(gridded - host).max() / np.abs(host).max()),
        )
    )
    print(json.dumps(out[-1]), flush=True)
    return out


def background_rows(cp, slices) -> list[dict]:
    """Each tomogram slice's quadratic background fit (``tomography.remove_background``, part of
    every tomo task) on the device and on the host: seconds a slice, a position's worth."""
    from pwf_dask.tomo import tomography

    rows = []
    for where, xp in (("device", cp), ("host", np)):
        block = xp.asarray(slices)
        tomography.remove_background(block[:1])  # compiled, planned
        cp.cuda.Stream.null.synchronize()
        t0 = time.perf_counter()
        tomography.remove_background(block)
        cp.cuda.Stream.null.synchronize()
        seconds = time.perf_counter() - t0
        n = slices.shape[0]
        per_slice = seconds / n
        rows.append(
            dict(where=where, stage="background", rows=n, width_px=slices.shape[-1], seconds_per_slice=per_slice)
        )
        rows[-1]["position_s"] = per_slice * 2160 * 2  # phase and attenuation, 2160 rows
        print(json.dumps(rows[-1]), flush=True)
    return rows


def main(argv=None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    out, part = argv[0], argv[1]
    cp = backend.resolve_device("gpu")
    rng = np.random.default_rng(0)
    if part == "memory":
        rows = memory_rows(cp, rng)
    elif part == "threads":
        rows = thread_rows(cp, rng)
    elif part == "camera":
        rows = camera_rows(cp, tuple(int(n) for n in argv[2:4]) if len(argv) > 3 else (2160, 2560))
    elif part == "strip":
        rows = strip_rows(int(argv[2]) if len(argv) > 2 else 101)
    elif part == "tomo":
        rows = tomo_rows(cp)
    elif part == "warm":
        rows = warm_rows(cp)
    else:
        raise SystemExit(f"unknown part {part!r}: memory, threads, strip, camera, tomo or warm")
    with open(f"{out}/{part}.json", "w") as f:
        json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
