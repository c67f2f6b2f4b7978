"""A coarse-to-fine start, issue #27's first route to wide-frame convergence (docs/methods.md,
"Wide frames and low frequencies").

Each scene (the paper's geometry and P3000 diffuser, calibrated coherence, one seed) is
retrieved four ways with every other default:

1. from zero (the default);
2. coarse to fine: sample and reference binned 2 x 2 and retrieved at twice the pixel size
   (calibrated there), the phase and attenuation interpolated back to the detector grid
   (bilinear) and used as psi_0 on the full frame;
3. the same start low-passed (Gaussian, sigma 4 px): only its wide structure, since the
   inverse-Laplacian preconditioner leaves high-frequency errors slow;
4. from the true psi: what any start could buy at most.

For each: the iterations (coarse + fine), the seconds, the relative phase error (rms of
recovered - true over the sample, true phase < -0.5 rad, over the true phase's rms there) and
the phase gain. ``--curve`` adds the error after fixed iteration counts (``tol=0``) from zero,
from the coarse start and from the truth on the 512^2 L1 = 0 scene.

    python -m benchmarks.coarse_start [--scenes s256,s512,l0,s1024,camera] [--curve] [--out benchmarks/results]

Writes ``coarse_start.md`` and ``.csv`` (about 25 minutes on 2 cores).
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np
from scipy import ndimage

from benchmarks.edge_step import CAMERA_SHAPE
from benchmarks.frame_size import fitted_phase_gain
from benchmarks.reporting import device_name, write_rows_csv
from pwf_dask.retrieval import retrieve_projection
from pwf_dask.simulation import SpeckleSetup, SpeckleSimulator, simulate_projection
from pwf_dask.simulation.phantoms import PAPER_BEAD_RADIUS_M, scan_phantom

#: binning of the coarse solve, and the low pass of run 3 (detector pixels)
BIN = 2
BLUR_PX = 4.0
CURVE_CAPS = (25, 50, 100, 150, 200, 280)
SCENES = {
    "s256": "256^2 beads",
    "s512": "512^2 beads",
    "l0": "512^2 beads, L1 = 0",
    "s1024": "1024^2 beads",
    "camera": "270 x 2560 rows of the camera frame (paper preset)",
}


def scene(name: str, seed: int = 1):
    """(setup, sample, reference, true phase, true attenuation) of a named scene."""
    if name == "camera":
        setup = replace(SpeckleSetup(), shape=(270, CAMERA_SHAPE[1]))
        phantom = scan_phantom(CAMERA_SHAPE, setup.pixel_size_m, 0, bead_radius_range_m=PAPER_BEAD_RADIUS_M)
        sim = SpeckleSimulator(setup, seed=0)
        sample, phase, attenuation = sim.project(phantom)
        return setup, sample, sim.reference(), phase, attenuation
    n = {"s256": 256, "s512": 512, "l0": 512, "s1024": 1024}[name]
    setup = SpeckleSetup(shape=(n, n))
    if name == "l0":
        setup = replace(setup, sample_diffuser_distance_m=0.0)
    p = simulate_projection(setup, seed=seed)
    return setup, p.sample, p.reference, p.phase, p.attenuation


def binned(a: np.ndarray, b: int = BIN) -> np.ndarray:
    """Mean over b x b pixel blocks (flat-corrected images: the mean is the binned image)."""
    ny, nx = (a.shape[0] // b) * b, (a.shape[1] // b) * b
    return a[:ny, :nx].reshape(ny // b, b, nx // b, b).mean(axis=(1, 3))


def upsampled(a: np.ndarray, b: int, shape: tuple[int, int]) -> np.ndarray:
    """Bilinear back to the detector grid (pixel centres aligned), edge values to ``shape``."""
    z = ndimage.zoom(a, b, order=1, grid_mode=True, mode="nearest")
    return np.pad(z, [(0, shape[0] - z.shape[0]), (0, shape[1] - z.shape[1])], mode="edge")


def coarse_start(sample, reference, geometry: dict) -> tuple[np.ndarray, int, float]:
    """psi_0 from the binned pair: (psi_0, the coarse run's iterations, its seconds)."""
    t0 = time.perf_counter()
    coarse = dict(geometry, pixel_size_m=geometry["pixel_size_m"] * BIN)
    r = retrieve_projection(binned(sample), binned(reference), **coarse)
    shape = sample.shape
    psi = -upsampled(np.asarray(r.attenuation), BIN, shape) + 1j * upsampled(np.asarray(r.phase), BIN, shape)
    return psi, r.iterations, time.perf_counter() - t0


def low_passed(psi: np.ndarray) -> np.ndarray:
    return ndimage.gaussian_filter(psi.real, BLUR_PX, mode="nearest") + 1j * ndimage.gaussian_filter(
        psi.imag, BLUR_PX, mode="nearest"
    )


def phase_error(phase: np.ndarray, true_phase: np.ndarray) -> tuple[float, float]:
    """(relative rms error, gain) over the sample (true phase < -0.5 rad)."""
    inside = true_phase < -0.5
    err = np.sqrt(np.mean((phase - true_phase)[inside] ** 2) / np.mean(true_phase[inside] ** 2))
    return float(err), fitted_phase_gain(phase, true_phase)


def scene_rows(name: str) -> list[dict]:
    setup, sample, reference, phase, attenuation = scene(name)
    geometry = setup.geometry()
    start, coarse_it, coarse_s = coarse_start(sample, reference, geometry)
    starts = {
        "from zero": ("zero", 0, 0.0),
        "coarse to fine": (start, coarse_it, coarse_s),
        "coarse to fine, low-passed": (low_passed(start), coarse_it, coarse_s),
        "from the true psi": (-attenuation + 1j * phase, 0, 0.0),
    }
    rows = []
    for label, (psi0, it0, s0) in starts.items():
        t0 = time.perf_counter()
        r = retrieve_projection(sample, reference, **geometry, initial=psi0)
        err, g = phase_error(np.asarray(r.phase), phase)
        rows.append(
            {
                "scene": SCENES[name],
                "start": label,
                "coarse_iterations": it0,
                "iterations": r.iterations,
                "converged": r.converged,
                "coarse_s": s0,
                "fine_s": time.perf_counter() - t0,
                "phase_error": err,
                "phase_gain": g,
            }
        )
        print(rows[-1], flush=True)
    return rows


def curve_rows() -> list[dict]:
    """The relative phase error after fixed iteration counts (``tol=0``) on the L1 = 0 scene."""
    setup, sample, reference, phase, attenuation = scene("l0")
    geometry = setup.geometry()
    start, _, _ = coarse_start(sample, reference, geometry)
    starts = {"from zero": "zero", "coarse to fine": start, "from the true psi": -attenuation + 1j * phase}
    rows = []
    for cap in CURVE_CAPS:
        row: dict = {"iterations": cap}
        for label, psi0 in starts.items():
            r = retrieve_projection(sample, reference, **geometry, initial=psi0, tol=0.0, max_iter=cap)
            row[label] = phase_error(np.asarray(r.phase), phase)[0]
        rows.append(row)
        print(row, flush=True)
    return rows


def write_markdown(rows: list[dict], curve: list[dict], path: str) -> None:
    lines = [
        "# A coarse-to-fine start against a start from zero",
        "",
        f"`python -m benchmarks.coarse_start` on {device_name(np)}: the paper's geometry and P3000 diffuser,",
        "calibrated coherence, seed 1 (the camera rows: the `paper` preset's phantom, seed 0). Coarse:",
        f"the pair binned {BIN} x {BIN} and retrieved with every default, its psi interpolated back (bilinear);",
        f"low-passed: that start blurred by a Gaussian of sigma {BLUR_PX:g} px. Phase error: rms of recovered -",
        "true over the sample, relative to the true phase's rms there.",
        "",
        "| scene | start | coarse iterations | iterations | converged | coarse s | full-frame s "
        "| phase error | phase gain |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['scene']} | {r['start']} | {r['coarse_iterations']} | {r['iterations']} | {r['converged']} "
            f"| {r['coarse_s']:.1f} | {r['fine_s']:.1f} | {r['phase_error']:.4f} | {r['phase_gain']:.3f} |"
        )
    if curve:
        labels = [k for k in curve[0] if k != "iterations"]
        lines += [
            "",
            f"## Phase error after a fixed number of iterations ({SCENES['l0']}, `tol=0`)",
            "",
            "| iterations | " + " | ".join(labels) + " |",
            "|---" * (len(labels) + 1) + "|",
        ]
        for c in curve:
            lines.append(f"| {c['iterations']} | " + " | ".join(f"{c[k]:.4f}" for k in labels) + " |")
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default=",".join(SCENES), help=f"comma-separated, of {', '.join(SCENES)}")
    ap.add_argument("--curve", action="store_true", help="add the error after fixed iteration counts")
    ap.add_argument("--out", default="benchmarks/results", help="folder for coarse_start.md and .csv")
    a = ap.parse_args()
    names = a.scenes.split(",")
    unknown = [n for n in names if n not in SCENES]
    if unknown:
        ap.error(f"unknown scene {unknown[0]!r}: choose from {', '.join(SCENES)}")
    rows = [row for name in names for row in scene_rows(name)]
    curve = curve_rows() if a.curve else []
    write_rows_csv(a.out, "coarse_start.csv", rows)
    write_markdown(rows, curve, f"{a.out}/coarse_start.md")


if __name__ == "__main__":
    main()
