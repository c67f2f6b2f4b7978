"""Peak memory per worker of each stage, measured against :mod:`pwf_dask.pipeline.estimate` (issue #29).

Every measurement runs in a fresh process and reads its peak resident memory
(``ru_maxrss``) after one task of the stage, on inputs loaded from disk (so that making
them does not count): one PWF retrieval (paper geometry, 10 iterations, field_upsample 1 and
2) at several frame sizes, one tomography task (``workflow._tomo_task`` on a row block), and
one FSC of two tomograms. A retrieval's process first runs a 48 x 64 retrieval, as a worker has
run its first task: what that loads once (numba's compiled kernels, MKL, scipy's optimizers:
~190 MB, session 52) is the worker's baseline, not the task's. The prediction is
:mod:`pwf_dask.pipeline.estimate`'s; the worker's baseline (``estimate.WORKER_BASE_MB``) is measured
beside it: a process with pwf-dask, zarr and distributed imported, after that small retrieval.

    python -m benchmarks.memory_model [--out benchmarks/results]

Writes ``memory_model.md`` and ``.csv`` (about 3 minutes on 2 cores).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.reporting import device_name, write_rows_csv

#: the retrieval options of every child (the paper's optics, the lengths given, one FFT thread as
#: a scan task), and the small retrieval a worker has run as its first task
_OPTIONS = r"""
kw = dict(energy_eV=1e4, pixel_size_m=0.65e-6, sample_diffuser_distance_m=3e-3, diffuser_detector_distance_m=20e-3,
    coherence_length_x_m=3.47e-6, coherence_length_y_m=4.31e-6, tol=0.0, fft_workers=1)
def first_task(s, r, **options):
    retrieve_projection(s[:48, :64], r[:48, :64], max_iter=3, **kw, **options)
"""

RETRIEVAL = (
    r"""
import json, os, resource, sys
import numpy as np
from pwf_dask.retrieval import retrieve_projection
"""
    + _OPTIONS
    + r"""
ny, nx, up, cache = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
f = f"{cache}/sim_{ny}x{nx}.npz"
if not os.path.exists(f):
    from pwf_dask.simulation import SpeckleSetup, simulate_projection
    sim = simulate_projection(SpeckleSetup(shape=(ny, nx)), seed=1)
    np.savez(f, s=sim.sample, r=sim.reference)
    sys.exit(3)
d = np.load(f)
s, r = d["s"].astype(np.float32), d["r"].astype(np.float32)
first_task(s, r, field_upsample=up)
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
retrieve_projection(s, r, max_iter=10, field_upsample=up, **kw)
print(json.dumps({"base_mb": base, "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""
)

BASELINE = (
    r"""
import json, resource, sys
import numpy as np, zarr, distributed
from pwf_dask.pipeline import workflow
from pwf_dask.retrieval import retrieve_projection
"""
    + _OPTIONS
    + r"""
imported = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
d = np.load(sys.argv[1])
first_task(d["s"].astype(np.float32), d["r"].astype(np.float32))
print(json.dumps({"imported_mb": imported, "base_mb": 0.0,
    "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""
)

TOMO = r"""
import json, resource, sys
import numpy as np, zarr
from pwf_dask.pipeline import workflow
from pwf_dask.stores import scan_io
from pwf_dask.stores.scan_io import ScanInfo
nang, ny, nx, path, fbp = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), sys.argv[4], sys.argv[5]
info = ScanInfo(path="none", n_positions=1, angles_deg=np.linspace(0, 180, nang, endpoint=False), shape=(ny, nx),
    x_m=np.zeros(nx), y_m=np.zeros(ny), energy_eV=1e4, pixel_size_m=1e-6, sample_diffuser_distance_m=0.003,
    diffuser_detector_distance_m=0.02, coherence_length_x_m=None, coherence_length_y_m=None,
    flat_dark_corrected=True, has_flat=False, has_dark=False, attrs={"energy_eV": 1e4, "pixel_size_m": 1e-6})
g = scan_io.create_reconstruction(path, info, {"method": "pwf"})
rng = np.random.default_rng(0)
for a in range(nang):
    g["phase"][0, a] = rng.normal(size=(ny, nx)).astype(np.float32)
    g["attenuation"][0, a] = rng.normal(size=(ny, nx)).astype(np.float32)
g["iterations"][...] = 1
g.attrs["rotation_center_m"] = 0.0
workflow._create_tomograms(g, 0.0, False, fbp)
rb = g["delta"].chunks[1]
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
workflow._tomo_task((0, 0), recon_path=path, center_m=0.0, device="cpu", fft_workers=1, fbp=fbp)
print(json.dumps({"base_mb": base, "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, "rows": rb}))
"""

FSC = r"""
import json, resource, sys
import numpy as np
from pwf_dask.tomo import fsc
ny, nx = int(sys.argv[1]), int(sys.argv[2])
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
rng = np.random.default_rng(0)
a = rng.normal(size=(ny, nx, nx)).astype(np.float32)
b = rng.normal(size=(ny, nx, nx)).astype(np.float32)
fsc.fourier_shell_correlation(a, b, 1e-6)
print(json.dumps({"base_mb": base, "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""


def _child(code: str, *args) -> dict | None:
    out = subprocess.run([sys.executable, "-c", code, *map(str, args)], capture_output=True, text=True)
    lines = [x for x in out.stdout.splitlines() if x.startswith("{")]
    if out.returncode == 3:  # the inputs were made; measure in a fresh process
        return _child(code, *args)
    if not lines:
        raise RuntimeError(out.stderr[-2000:])
    return json.loads(lines[-1])


def main(argv=None) -> None:
    from pwf_dask.pipeline import estimate

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="benchmarks/results")
    args = p.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for ny, nx in ((256, 256), (512, 512), (768, 1024), (1024, 1024)):
            for up in (1, 2):
                m = _child(RETRIEVAL, ny, nx, up, tmp)
                predicted = estimate.retrieval_peak_mb((ny, nx), up, positions=0)
                rows.append(_row(f"retrieve, field_upsample {up}", f"{ny}x{nx}", m, predicted))
        for fbp in ("backproject", "gridrec"):
            for nang, ny, nx in ((181, 64, 256), (361, 32, 512), (361, 25, 1024)):
                m = _child(TOMO, nang, ny, nx, f"{tmp}/t{nang}_{nx}_{fbp}.zarr", fbp)
                predicted = estimate.tomo_peak_mb(nang, m["rows"], nx, fbp)
                rows.append(_row(f"tomo task, {fbp}", f"{nang} angles x {m['rows']} rows x {nx}", m, predicted))
        for ny, nx in ((32, 256), (64, 512), (16, 1024)):
            m = _child(FSC, ny, nx)
            rows.append(_row("fsc", f"{ny} x {nx} x {nx}", m, estimate.fsc_peak_mb(ny, nx)))
        baseline = _child(BASELINE, f"{tmp}/sim_256x256.npz")
        rows.append(_row("worker baseline (imports, a first task)", "48x64", baseline, estimate.WORKER_BASE_MB))
    out = Path(args.out)
    write_rows_csv(out, "memory_model.csv", rows)
    lines = [
        f"# Peak memory per task: measured against the model ({device_name(np)})",
        "",
        "`python -m benchmarks.memory_model`: each task in a fresh process, its peak resident memory",
        "(`ru_maxrss`) above the process's baseline before the task (imports, inputs and, for a retrieval,",
        "a 48 x 64 retrieval run first, as a worker's first task), against `pwf_dask.pipeline.estimate`'s",
        "prediction of the task's own arrays. `pwf-dask estimate SCAN` adds a worker's baseline",
        f"({estimate.WORKER_BASE_MB:.0f} MB: the last row, a process with pwf-dask, zarr and distributed",
        f"imported, {baseline['imported_mb']:.0f} MB, after a 48 x 64 retrieval) to each.",
        "",
        "| stage | size | measured (MB) | predicted (MB) | predicted / measured |",
        "|---|---|---:|---:|---:|",
    ]
    lines += [
        f"| {r['stage']} | {r['size']} | {r['measured_mb']:.0f} | {r['predicted_mb']:.0f} | {r['ratio']:.2f} |"
        for r in rows
    ]
    (out / "memory_model.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def _row(stage: str, size: str, measured: dict, predicted_mb: float) -> dict:
    used = measured["peak_mb"] - measured["base_mb"]
    return {
        "stage": stage,
        "size": size,
        "measured_mb": used,
        "predicted_mb": predicted_mb,
        "ratio": predicted_mb / used if used > 0 else float("nan"),
    }


if __name__ == "__main__":
    main()
