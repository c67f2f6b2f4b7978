"""Memory and time of a scan's stages, predicted before it runs (``pwf-dask estimate SCAN``).

Memory per worker is a linear model in the arrays a task holds, with coefficients measured on
this project's code (issue #29; ``benchmarks/results/memory_model.md``, the commands there):

* retrieval: ``RETRIEVAL_BASE_MB`` + bytes per pixel of the padded detector grid, more when
  the sample field goes on a finer grid (``field_upsample`` u: u^2 - 1 extra fine pixels per
  detector pixel), plus the diffuser estimates a worker keeps (one per position, 8 at most);
* tomography: one row block's two sinograms (float32) and the FBP's working set per
  sinogram element, plus the volume-sized arrays per output voxel;
* FSC: two float32 tomograms and the single-precision FSC (16 bytes per voxel of spectra).

Time: one PWF iteration of the scan's padded grid, on its field grid and with its L1, timed
here by the solver's own loop on one thread (as a scan task runs; the FFT library this
machine uses); the FBP of a slice costs a fixed part plus one per angle, timed here at the
scan's width. Both are measured by :func:`measure_speeds` on the machine that runs the
estimate. (Until session 43 the iteration was one FFT times a ratio from the 2-thread
pocketfft table, 16 FFT-times; on the full-width bench of the paper's optics that predicted
25 min where the run took 55: MKL's ratio is another, and P3000 takes the 1.5x field grid.)
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

#: a worker process with pwf-dask, zarr and distributed imported (88 MB) and what its first
#: retrieval loads once and keeps: numba's compiled kernels, MKL, scipy's optimizers (MB;
#: 258-285 measured after a 48 x 64 retrieval, 278 on one FFT thread with MKL, session 52:
#: ``benchmarks/results/memory_model.md``; until then 85, the imports alone, which left a
#: worker ~190 MB above its estimate)
WORKER_BASE_MB = 280.0
#: retrieval: fixed part and bytes per padded detector-grid pixel (field_upsample 1), and per
#: extra field-grid pixel when field_upsample > 1 (fit of peak RSS at 256^2-1024^2, 10 iterations,
#: after a first small retrieval). No fixed part is left once the worker's runtime is loaded
#: (measured less the per-pixel terms: -8 to +8 MB at field_upsample 1, session 52); the 59 MB
#: fitted before held part of that runtime
RETRIEVAL_BASE_MB = 0.0
RETRIEVAL_BYTES_PER_PIXEL = 337.0
RETRIEVAL_BYTES_PER_FIELD_PIXEL = 79.0
#: tomography task (fit of peak RSS of ``workflow._tomo_task``, 256-1024 px): per sinogram
#: element, both float32 sinograms as read (zarr's decode buffers beside them) and one FBP's
#: filtered copy and slopes; per output voxel, the FBP's slice, its scaled copy and the
#: background fit's float32 output
TOMO_BASE_MB = 0.0
TOMO_BYTES = {"backproject": (19.6, 18.6), "gridrec": (25.9, 18.8)}
#: FSC: two float32 volumes, then the transform of each (complex64 half spectra) and slabs
FSC_BYTES_PER_VOXEL = 8.0 + 16.0
#: iterations per projection assumed when none is given: the mean of the full-width scan of the
#: paper's optics (``bench fullwidth``, chains of 8: 252 in session 69 under the default stop, J's
#: test on J or its data term, whose warm starts stop at 222 for J alone's 233; 261 in session 48
#: under J alone, 254 in session 46 over one window, 356 in session 45 at jtol 1e-5)
DEFAULT_ITERATIONS = 252
#: the sample field's grid assumed when none is given: the 1.5x grid that coarse diffusers such
#: as the paper's P3000 take (``field_upsample="auto"``); fine grains stay on the detector grid (1)
DEFAULT_FIELD_UPSAMPLE = 1.5


@dataclass
class StageEstimate:
    """One stage: its tasks, the peak memory of one worker, and the time on ``workers``."""

    stage: str
    tasks: int
    peak_mb_per_worker: float
    seconds: float
    note: str = ""


@dataclass
class Speeds:
    """What :func:`measure_speeds` timed on this machine."""

    iteration_s: float  # one PWF iteration of the padded grid, one thread
    fft_s: float  # one complex64 FFT of the padded grid (the FSC's transforms scale from it)
    fbp_row_s: float  # FBP and background of one row (slice) of the scan's width: fixed part ...
    fbp_row_s_per_angle: float  # ... and per angle
    fbp: str = "backproject"  # the method timed

    def slice_s(self, n_angles: int) -> float:
        """One slice's FBP from ``n_angles`` projections."""
        return self.fbp_row_s + self.fbp_row_s_per_angle * n_angles


def padded_grid(shape: tuple[int, int], pad: int = 17) -> tuple[int, int]:
    from pwf_dask.retrieval import computational_shape

    return computational_shape(shape, pad)


#: the paper's optics for timing an iteration: pixel, coherence lengths (x, y), L1, L2, energy
TIMING_PIXEL_M = 0.65e-6
TIMING_COHERENCE_M = (3.47e-6, 4.31e-6)
TIMING_L1_M, TIMING_L2_M, TIMING_ENERGY_EV = 3e-3, 0.02, 10_000.0


def timing_problem(grid: tuple[int, int], fft, *, l1_m: float = TIMING_L1_M, **model_options):
    """(model, y): a PWF model of the paper's optics on ``grid`` with a random diffuser, and a
    random image, on ``fft``'s array module; what an iteration is timed on (here and by
    ``bench iteration``). ``model_options`` go to :func:`pwf_dask.pwf.solver.build_model`."""
    from pwf_dask.physics import optics
    from pwf_dask.pwf import solver

    xp = fft.xp
    rng = np.random.default_rng(0)
    model = solver.build_model(
        xp.asarray(np.exp(1j * rng.normal(size=grid)).astype(np.complex64)),
        frame_shape=grid,
        pixel_size_m=TIMING_PIXEL_M,
        wavelength=optics.wavelength_m(TIMING_ENERGY_EV),
        sample_diffuser_distance_m=l1_m,
        diffuser_detector_distance_m=TIMING_L2_M,
        coherence_length_x_m=TIMING_COHERENCE_M[0],
        coherence_length_y_m=TIMING_COHERENCE_M[1],
        fft=fft,
        **model_options,
    )
    return model, xp.asarray(rng.random(grid).astype(np.float32) + 0.5)


def iteration_seconds(
    shape: tuple[int, int], field_upsample: float = 1, l1_zero: bool = False, fft_workers: int = 1, pad: int = 17
) -> float:
    """One PWF iteration of ``shape``'s padded grid: the solver's own loop (stop statistics,
    restarts and Nesterov included) on a random diffuser: a (1 + n)-iteration run less a
    1-iteration run (each pays the same set-up), over n, the fastest of two rounds, as
    ``bench iteration`` times it. n starts at 2 and grows 4x (to 128) while the n iterations
    are under a quarter of the short run: on a small grid two iterations sit inside the run's
    own timing noise (112^2 under a test suite's load read 0 s)."""
    from pwf_dask.backend import FFT
    from pwf_dask.pwf import solver

    fft = FFT.for_module(np, fft_workers)
    l1_m = 0.0 if l1_zero else TIMING_L1_M
    model, y = timing_problem(padded_grid(shape, pad), fft, l1_m=l1_m, field_upsample=field_upsample)

    def run(n: int) -> float:
        t = time.perf_counter()
        solver.pwf(y, model, max_iter=n, tol=0, step=1e-3, step_search=False)
        return time.perf_counter() - t

    run(1)  # compiles the fused passes and checks the FFT layouts once, as a task's first iteration does
    extra = 2
    while True:
        # the fastest of two interleaved rounds of each (a shared machine's noise only adds)
        ones, longer = zip(*[(run(1), run(1 + extra)) for _ in range(2)])
        spent = min(longer) - min(ones)
        if spent > 0.25 * min(ones) or extra >= 128:
            return max(spent / extra, 0.0)
        extra *= 4


def measure_speeds(
    shape: tuple[int, int],
    fft_workers: int = 1,
    pad: int = 17,
    fbp: str = "auto",
    field_upsample: float = DEFAULT_FIELD_UPSAMPLE,
    l1_zero: bool = False,
) -> Speeds:
    """Time one PWF iteration of ``shape``'s padded grid (:func:`iteration_seconds`), one FFT of
    it, and the FBP ``fbp`` of two rows of a rod's sinogram at the scan's width from 16 and from
    48 angles, with each slice's background fit (its cost per slice: a fixed part plus one per
    angle)."""
    import scipy.fft

    from pwf_dask.backend import FFT
    from pwf_dask.tomo import tomography

    iteration_s = iteration_seconds(shape, field_upsample, l1_zero, fft_workers, pad)
    x = (np.random.default_rng(0).normal(size=padded_grid(shape, pad)) + 0j).astype(np.complex64)
    scipy.fft.fft2(x, workers=fft_workers)
    t = time.perf_counter()
    for _ in range(3):
        scipy.fft.fft2(x, workers=fft_workers)
    fft_s = (time.perf_counter() - t) / 3
    method = tomography.resolve_fbp(fbp)
    # a rod's sinogram (a slice with sample and background, as the background search meets it)
    u = np.arange(shape[1]) - shape[1] / 2
    chord = 2 * np.sqrt(np.clip((0.3 * shape[1]) ** 2 - u**2, 0, None)) / shape[1]
    seconds = []
    for na in (16, 48):
        sino = chord + 0.01 * np.random.default_rng(1).normal(size=(na, 2, shape[1]))
        theta = np.linspace(0, 180, na, endpoint=False)
        t = time.perf_counter()
        slices = tomography.back_projection(
            sino.astype(np.float32), theta, 1e-6, fft=FFT.for_module(np, fft_workers), method=method
        )
        seconds.append((time.perf_counter() - t) / 2)
    t = time.perf_counter()
    tomography.remove_background(slices)  # each slice's quadratic background, part of a tomo task
    background_s = (time.perf_counter() - t) / 2
    per_angle = max(0.0, (seconds[1] - seconds[0]) / 32)
    return Speeds(iteration_s, fft_s, max(0.0, seconds[0] - 16 * per_angle) + background_s, per_angle, method)


def retrieval_peak_mb(shape: tuple[int, int], field_upsample: float = 1, positions: int = 1, pad: int = 17) -> float:
    ny, nx = padded_grid(shape, pad)
    pixels = ny * nx
    diffusers = min(8, positions) * pixels * field_upsample**2 * 8  # complex64 transmission each
    extra = RETRIEVAL_BYTES_PER_FIELD_PIXEL * (field_upsample**2 - 1) * pixels
    return RETRIEVAL_BASE_MB + (RETRIEVAL_BYTES_PER_PIXEL * pixels + extra + diffusers) / 1e6


#: a retrieval's device memory over the host model's arrays (:func:`retrieval_peak_mb` less
#: :data:`RETRIEVAL_BASE_MB`), measured as CuPy's pool after one ``retrieve_projection`` (diffuser
#: fit included) on an H100 in session 42: 1.24 at 256^2, 1.27 at 1024^2, 1.72 at 2160 x 2560
#: (1.31-1.62 on the 1.5x field grid), cuFFT's plans and the pool's rounding beside the arrays;
#: the largest, rounded up (``benchmarks/results/memory_model_gpu.md``)
GPU_RETRIEVAL_MEMORY_FACTOR = 1.75

#: of a GPU's free memory, the share that concurrent retrieval tasks are planned to fill
GPU_MEMORY_SHARE = 0.8


def retrieval_device_mb(shape: tuple[int, int], field_upsample: float = 1, positions: int = 1, pad: int = 17) -> float:
    """Device memory of one retrieval task on a GPU (MB), from the host model."""
    host = retrieval_peak_mb(shape, field_upsample, positions, pad) - RETRIEVAL_BASE_MB
    return GPU_RETRIEVAL_MEMORY_FACTOR * host


def gpu_tasks_that_fit(task_mb: float, free_bytes: float) -> int:
    """How many retrieval tasks of ``task_mb`` share a GPU with ``free_bytes`` free (at least one)."""
    return max(1, int(GPU_MEMORY_SHARE * free_bytes / (task_mb * 1e6)))


def tomo_peak_mb(n_angles: int, rows: int, nx: int, fbp: str = "backproject") -> float:
    sinogram = n_angles * rows * nx
    per_element, per_voxel = TOMO_BYTES[fbp]
    return TOMO_BASE_MB + (per_element * sinogram + per_voxel * rows * nx * nx) / 1e6


def fsc_peak_mb(ny: int, nx: int) -> float:
    return FSC_BYTES_PER_VOXEL * ny * nx * nx / 1e6


def estimate_scan(
    shape: tuple[int, int],
    n_angles: int,
    n_positions: int,
    *,
    workers: int = 1,
    iterations: int = DEFAULT_ITERATIONS,
    field_upsample: float = DEFAULT_FIELD_UPSAMPLE,
    upstream_or_l1_zero: bool = False,
    speeds: Speeds,
) -> list[StageEstimate]:
    """Peak memory per worker and wall time of retrieval, tomography and FSC on ``workers``
    single-threaded workers (time divided evenly: the tasks outnumber the workers); the
    iteration's time in ``speeds`` is that of ``field_upsample`` and the L1 given."""
    from pwf_dask.stores.scan_io import row_block

    ny, nx = shape
    variant = "L1 = 0" if upstream_or_l1_zero else "L1 > 0"
    if field_upsample > 1:
        variant += f", field on {field_upsample:g}x grid"
    per_projection = iterations * speeds.iteration_s
    projections = n_angles * n_positions
    rb = row_block(ny, nx)
    blocks = n_positions * -(-ny // rb)
    fbp = 2 * speeds.slice_s(n_angles) * ny * n_positions  # phase and attenuation
    base = WORKER_BASE_MB
    return [
        StageEstimate(
            "retrieve",
            projections,
            base + retrieval_peak_mb(shape, field_upsample, n_positions),
            projections * per_projection / workers,
            f"{iterations} iterations x {speeds.iteration_s * 1e3:.1f} ms per iteration ({variant}, timed here)",
        ),
        StageEstimate(
            "tomo",
            blocks,
            base + tomo_peak_mb(n_angles, rb, nx, speeds.fbp),
            # a worker's largest row block at least: there may be fewer blocks than workers
            max(fbp / workers, 2 * speeds.slice_s(n_angles) * min(rb, ny)),
            f"{blocks} row blocks of {rb} rows; {speeds.fbp} FBP {speeds.slice_s(n_angles):.2f} s per slice",
        ),
        _fsc_stage(ny, nx, n_angles, n_positions, speeds),
    ]


def _fsc_stage(ny: int, nx: int, n_angles: int, n_positions: int, speeds: Speeds) -> StageEstimate:
    """K >= 2: two stored tomograms at a time; K = 1: the even and odd half-scans are
    reconstructed in the driver before their FSC. Either on at most the central
    :data:`pwf_dask.pipeline.workflow.FSC_MAX_ROWS` rows."""
    from pwf_dask.pipeline.workflow import FSC_MAX_ROWS

    ny = min(ny, FSC_MAX_ROWS)
    voxels = ny * nx * nx
    ffts = 2 * speeds.fft_s * voxels * np.log2(voxels) / (nx * nx * np.log2(nx * nx)) / 2  # two real 3-D FFTs
    if n_positions >= 2:
        pairs = min(5, n_positions * (n_positions - 1) // 2)
        return StageEstimate(
            "fsc", pairs, WORKER_BASE_MB + fsc_peak_mb(ny, nx), pairs * ffts, "in the driver: two tomograms at a time"
        )
    fbp = 2 * 2 * speeds.slice_s(n_angles // 2) * ny  # both halves, phase and attenuation
    peak = tomo_peak_mb(n_angles // 2, ny, nx, speeds.fbp) + fsc_peak_mb(ny, nx)
    return StageEstimate(
        "fsc", 1, WORKER_BASE_MB + peak, fbp + ffts, f"in the driver: even/odd half-scans, central {ny} rows"
    )


def format_estimate(
    stages: list[StageEstimate], workers: int, memory_mb: float | None = None, gpu_task_mb: float | None = None
) -> list[str]:
    """The lines ``pwf-dask estimate`` prints: a table, a warning for a stage that cannot fit,
    and (``gpu_task_mb``) a retrieval task's device memory on a GPU."""
    from pwf_dask.progress import format_seconds

    lines = [f"{'stage':<10}{'tasks':>8}{'peak memory per worker':>26}{f'time on {workers} worker(s)':>24}"]
    for s in stages:
        lines.append(f"{s.stage:<10}{s.tasks:>8}{s.peak_mb_per_worker / 1e3:>23.2f} GB{format_seconds(s.seconds):>24}")
    lines += [f"  {s.stage}: {s.note}" for s in stages if s.note]
    if gpu_task_mb:
        cards = ", ".join(f"{gpu_tasks_that_fit(gpu_task_mb, gb * 1e9)} on {gb} GB" for gb in (24, 80))
        lines.append(
            f"  retrieve on a GPU (--device gpu): {gpu_task_mb / 1e3:.1f} GB of device memory per task; "
            f"tasks at a time: {cards}"
        )
    if memory_mb:
        for s in stages:
            if s.peak_mb_per_worker > memory_mb:
                lines.append(
                    f"  warning: {s.stage} needs {s.peak_mb_per_worker / 1e3:.1f} GB per worker; "
                    f"this machine has {memory_mb / 1e3:.1f} GB"
                )
    return lines


def machine_memory_mb() -> float | None:
    try:
        return os_memory_bytes() / 1e6
    except (OSError, ValueError, AttributeError):
        return None


def os_memory_bytes() -> int:
    import os

    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def estimate_for_scan(
    scan_path,
    *,
    workers: int = 1,
    iterations: int = DEFAULT_ITERATIONS,
    field_upsample: float = DEFAULT_FIELD_UPSAMPLE,
    fbp: str = "auto",
) -> tuple[list[StageEstimate], dict]:
    """:func:`estimate_scan` for a scan store (its metadata only; nothing is read but the
    coordinates), with the speeds measured here. Returns the stages and the scan's sizes."""
    from pwf_dask.stores.scan_io import open_scan

    if field_upsample == "auto":  # decided from the diffuser at run time: plan for the coarse case
        field_upsample = DEFAULT_FIELD_UPSAMPLE
    _, info = open_scan(scan_path, check_values=False)
    l1_zero = info.sample_diffuser_distance_m == 0
    speeds = measure_speeds(info.shape, fbp=fbp, field_upsample=field_upsample, l1_zero=l1_zero)
    stages = estimate_scan(
        info.shape,
        info.angles_deg.size,
        info.n_positions,
        workers=workers,
        iterations=iterations,
        field_upsample=field_upsample,
        upstream_or_l1_zero=l1_zero,
        speeds=speeds,
    )
    sizes = {"positions": info.n_positions, "angles": int(info.angles_deg.size), "shape": info.shape}
    sizes["gpu_task_mb"] = retrieval_device_mb(info.shape, field_upsample, info.n_positions)
    return stages, sizes
