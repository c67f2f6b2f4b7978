"""Phase gain against frame size, and the wide-strip regime of issue #27 (docs/methods.md, Wide frames).

The scenes, PWF with its defaults (calibrated coherence, automatic field grid and alpha):

1. ``beads``: the paper's geometry and diffuser (10 keV, 0.65 um, L1 = 3 mm, L2 = 20 mm, four
   layers of P3000, 1e4 ph/px); one cellulose rod with glass beads, sized for a 256 px field of
   view, in the middle of 256^2, 512^2 and 1024^2 frames: the same sample, more frame around it;
   the smallest also with the single-material prior told "cellulose", where it is wrong (the
   beads are glass).
2. ``strip``: the real scan's regime: 25 keV, 6.5 um pixels, the diffuser 50 mm upstream of the
   sample (L1 = 0), L2 = 0.7 m, coherence 25 / 20 um (6.7 % speckle visibility), four PMMA rods
   of 1.5-3.3 mm across a 2220 px strip, the last cut by the frame's edge; crops of 160 and 430
   rows by 700 and 2220 columns, each retrieved as it is and with the single-material prior
   (``single_material=True``, PMMA: the phase's low frequencies from the attenuation).
   ``--truth-start`` adds a run started from the true psi. ``--scenes grits`` retrieves the
   160 x 2220 crop on P1200 and P2000 sandpaper instead (``frame_size_grits.md``). These runs
   name the single-material diffuser fit; ``--scenes defaults`` retrieves the four crops with
   every default, the upstream distance not given as in the issue's real-data call and then
   given (``"auto"`` takes zero phase at 25 keV), and the whole frame of a second draw
   (``frame_size_defaults.md``, about 11 minutes).
3. ``camera`` (``frame_size_camera.md``): the ``paper`` preset's first projection on the whole
   2160 x 2560 camera frame (the paper's geometry and diffuser, its cellulose rod 0.96 mm
   across with glass beads 50-106 um across), retrieved whole and as centred crops of 540 and
   1080 rows: the same sample, more of its length in the frame, its full width in every crop.
4. ``bead-grains`` (``frame_size_bead_grains.md``, about 20 minutes): the bead scene's frame
   sizes on two more draws of P3000 (seeds 2, 3) and on sandpaper of 1.2 um (seed 1) and 4.5 um
   (seeds 1-3) median grain radius.

    python -m benchmarks.frame_size [--scenes beads strip] [--sizes 256 512 1024] [--out benchmarks/results]

Writes ``frame_size.md`` and ``.csv`` (about 15 minutes on 2 cores).
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np

from benchmarks.reporting import device_name, write_rows_csv
from pwf_dask.retrieval import retrieve_projection
from pwf_dask.simulation import GEOMETRY_KEYS, Rods, SpeckleSetup, SpeckleSimulator, default_phantom
from pwf_dask.simulation.phantoms import PAPER_BEAD_RADIUS_M, scan_phantom

STRIP_SETUP = SpeckleSetup(
    shape=(430, 2220),
    energy_eV=25000.0,
    pixel_size_m=6.5e-6,
    sample_diffuser_distance_m=0.0,
    diffuser_detector_distance_m=0.7,
    diffuser_upstream_m=0.05,
    coherence_length_x_m=25e-6,
    coherence_length_y_m=20e-6,
    photons=1e4,
)
STRIP_CROPS = [(160, 700), (430, 700), (160, 2220), (430, 2220)]
#: coarser and finer sandpaper than the default P3000 for the strip (``--scenes grits``)
GRITS = ("P1200", "P2000")
#: (median grain radius, seed) of the bead scene on finer and coarser sandpaper than P3000
#: (None: P3000, two more draws than ``beads``'s) for ``--scenes bead-grains``
BEAD_GRAIN_RUNS = ((None, 2), (None, 3), (1.2e-6, 1), (4.5e-6, 1), (4.5e-6, 2), (4.5e-6, 3))


def phase_gain(recovered: np.ndarray, true: np.ndarray) -> float:
    """Slope of recovered on true phase where the sample is (> 2 % of its deepest phase),
    after removing the recovered background's mean (true phase 0 there)."""
    inside = np.abs(true) > 0.02 * np.abs(true).max()
    background = np.abs(true) < 1e-6
    r = recovered - (recovered[background].mean() if background.any() else 0.0)
    return float(np.dot(r[inside], true[inside]) / np.dot(true[inside], true[inside]))


def fitted_phase_gain(recovered: np.ndarray, true: np.ndarray) -> float:
    """The accuracy tests' gain: the slope of a line (with offset) fitted to recovered against
    true phase where the true phase is below -0.5 rad; blind to a constant offset of the
    sample's phase, which :func:`phase_gain` counts through the background's level."""
    inside = true < -0.5
    return float(np.polyfit(true[inside], np.asarray(recovered)[inside], 1)[0])


def phase_rms_error(recovered: np.ndarray, true: np.ndarray) -> float:
    """rms of recovered - true phase over the frame (rad), the recovered background's mean removed."""
    background = np.abs(true) < 1e-6
    r = recovered - (recovered[background].mean() if background.any() else 0.0)
    return float(np.sqrt(np.mean((r - true) ** 2)))


def strip_rods(width_px: int, pixel_size_m: float) -> Rods:
    w = width_px * pixel_size_m
    return Rods(u_m=(-0.36 * w, -0.08 * w, 0.17 * w, 0.5 * w - 0.4e-3), radii_m=(1.65e-3, 1.0e-3, 0.75e-3, 1.65e-3))


def _retrieve(sample, reference, setup: SpeckleSetup, initial="zero", **options):
    t0 = time.perf_counter()
    r = retrieve_projection(
        sample,
        reference,
        **{name: getattr(setup, name) for name in GEOMETRY_KEYS},
        diffuser_upstream_m=setup.diffuser_upstream_m,
        initial=initial,
        **options,
    )
    return r, time.perf_counter() - t0


def _row(scene, frame, r, seconds, true_phase, start="zero") -> dict:
    p = r.parameters
    recovered = np.asarray(r.phase)
    return {
        "scene": scene,
        "frame": frame,
        "start": start,
        "prior": "single-material" if p.get("single_material") else "none",
        "phase_gain": phase_gain(recovered, true_phase),
        "phase_rms_error_rad": phase_rms_error(recovered, true_phase),
        "iterations": r.iterations,
        "stop": p["stop_reason"],
        "residual_pct": r.residual_rmse,
        "field_upsample": p["field_upsample"],
        "coherence_x_um": 1e6 * r.coherence_length_x_m,
        "seconds": seconds,
    }


def beads(sizes: list[int], seed: int = 1, wrong_prior: bool = True, grain_radius_m: float | None = None) -> list[dict]:
    """The bead scene in each frame size; ``grain_radius_m``: the sandpaper's median grain
    radius instead of P3000's (the scene is then named by it)."""
    rows = []
    base = SpeckleSetup()
    scene = "beads"
    if grain_radius_m is not None:
        base = replace(base, diffuser_radius_median_m=grain_radius_m)
        scene = f"beads, {1e6 * grain_radius_m:g} µm grains"
    fov = 256 * base.pixel_size_m
    phantom = default_phantom(fov, np.random.default_rng(seed + 1), height_m=fov)
    for n in sizes:
        setup = replace(base, shape=(n, n))
        sim = SpeckleSimulator(setup, seed=seed)
        sample, phase, _ = sim.project(phantom)
        # the prior where it is wrong: glass beads in a cellulose rod, told "cellulose"
        wrong = wrong_prior and n == sizes[0]
        runs = [{}] + ([{"single_material": True, "sample_material": "cellulose"}] if wrong else [])
        for options in runs:
            r, s = _retrieve(sample, sim.reference(), setup, **options)
            row = _row(scene, f"{n} x {n}", r, s, phase)
            rows.append({**row, "phase_gain_fitted": fitted_phase_gain(np.asarray(r.phase), phase)})
            print(rows[-1], flush=True)
    return rows


def strip_projection(setup: SpeckleSetup = STRIP_SETUP, seed: int = 1):
    """(sample, reference, true phase, true attenuation) of the strip regime's rods."""
    sim = SpeckleSimulator(setup, seed=seed)
    sample, phase, attenuation = sim.project(strip_rods(setup.shape[1], setup.pixel_size_m))
    return sample, sim.reference(), phase, attenuation


def strip_crop(setup: SpeckleSetup, rows: int, columns: int):
    """The strip's crop of ``rows`` centred rows and its first ``columns`` columns."""
    y0 = (setup.shape[0] - rows) // 2
    return np.s_[y0 : y0 + rows, :columns]


def strip_setup(grit: str | None = None) -> SpeckleSetup:
    """The strip regime with the diffuser of sandpaper ``grit`` instead of P3000 (None)."""
    return STRIP_SETUP if grit is None else replace(STRIP_SETUP, diffuser_grit=grit, diffuser_radius_median_m=None)


def strip(truth_start: bool, seed: int = 1, grit: str | None = None, crops=STRIP_CROPS) -> list[dict]:
    """The strip regime's crops, each without and with the single-material prior; ``grit``
    replaces the default P3000 diffuser (the scene is then named by it)."""
    setup = strip_setup(grit)
    scene = "strip" if grit is None else f"strip, {grit}"
    sample, reference, phase, attenuation = strip_projection(setup, seed)
    rows = []
    for ny, nx in crops:
        crop = strip_crop(setup, ny, nx)
        # measured with the single-material diffuser fit, which "auto" leaves at 25 keV
        fit = {"diffuser_model": "single-material"}
        runs = [("zero", fit), ("zero", {**fit, "single_material": True, "sample_material": "PMMA"})]
        if truth_start and (ny, nx) == (160, 2220):
            runs.append(("truth", fit))
        for start, options in runs:
            initial = "zero" if start == "zero" else -attenuation[crop] + 1j * phase[crop]
            r, s = _retrieve(sample[crop], reference[crop], setup, initial, **options)
            rows.append(_row(scene, f"{ny} x {nx}", r, s, phase[crop], start))
            print(rows[-1], flush=True)
    return rows


def strip_defaults(seeds: tuple[int, ...] = (1, 2), crops=STRIP_CROPS) -> list[dict]:
    """The strip's crops (``seeds[0]``) and its whole frame (the other seeds) retrieved with
    every default: L1 = 0, L2 = 0.7 m and nothing else (the issue's real-data call), then with
    the diffuser's upstream distance given."""
    rows = []
    for i, seed in enumerate(seeds):
        sample, reference, phase, _ = strip_projection(STRIP_SETUP, seed)
        for ny, nx in crops if i == 0 else crops[-1:]:
            crop = strip_crop(STRIP_SETUP, ny, nx)
            for upstream_m in (0.0, STRIP_SETUP.diffuser_upstream_m):
                r, s = _retrieve(sample[crop], reference[crop], replace(STRIP_SETUP, diffuser_upstream_m=upstream_m))
                given = f"{upstream_m * 1e3:g} mm upstream given" if upstream_m else "distance not given"
                scene = f"strip, seed {seed}, every default ({r.parameters['diffuser_model']}), {given}"
                rows.append(_row(scene, f"{ny} x {nx}", r, s, phase[crop]))
                print(rows[-1], flush=True)
    return rows


#: ``camera``: centred row crops of the 2160 x 2560 frame, each holding the rod's full width and background
CAMERA_CROPS = [(540, 2560), (1080, 2560), (2160, 2560)]


def camera(seed: int = 0, crops=CAMERA_CROPS) -> list[dict]:
    """The ``paper`` preset's projection at 0 degrees on the whole camera frame and its crops."""
    setup = replace(SpeckleSetup(), shape=CAMERA_CROPS[-1])
    phantom = scan_phantom(setup.shape, setup.pixel_size_m, seed, bead_radius_range_m=PAPER_BEAD_RADIUS_M)
    sim = SpeckleSimulator(setup, seed=seed)
    sample, phase, _ = sim.project(phantom)
    reference = sim.reference()
    del sim
    rows = []
    for ny, nx in crops:
        y0, x0 = (setup.shape[0] - ny) // 2, (setup.shape[1] - nx) // 2
        crop = np.s_[y0 : y0 + ny, x0 : x0 + nx]
        r, s = _retrieve(sample[crop], reference[crop], setup)
        rows.append(_row("paper preset", f"{ny} x {nx}", r, s, phase[crop]))
        print(rows[-1], flush=True)
    return rows


def _spread(rows: list[dict], key: str) -> str:
    values = [r[key] for r in rows]
    return f"{100 * (max(values) - min(values)) / np.mean(values):.1f} %"


def write_markdown(rows: list[dict], path: str, command: str = "python -m benchmarks.frame_size") -> None:
    fitted = all("phase_gain_fitted" in r for r in rows)
    head = (
        "| scene | frame | start | prior | phase gain | "
        + ("gain, line fitted | " if fitted else "")
        + "phase rms error (rad) | iterations | stop | residual % | field grid | coherence x (µm) | s |"
    )
    title = {
        "grits": " and diffuser grit",
        "camera": " up to the camera's 2160 x 2560",
        "defaults": ": the strip with every default",
        "bead-grains": ": the bead scene on finer and coarser grains",
    }
    lines = [
        "# Phase gain against frame size" + next((t for k, t in title.items() if k in command), ""),
        "",
        f"`{command}` on {device_name(np)}. PWF defaults (calibrated coherence);",
        "gain = slope of recovered on true phase inside the sample; rms error over the frame, the",
        "recovered background's mean removed."
        + (
            " Gain, line fitted: the accuracy tests' measure (a line with offset where the true"
            " phase is below -0.5 rad), blind to the sample's phase offset."
            if fitted
            else ""
        )
        + (
            " Prior: `single_material=True` with the rods' PMMA (the phase's low frequencies from"
            " the attenuation through Paganin's filter)."
            if any(r["prior"] != "none" for r in rows)
            else ""
        ),
        "",
        head,
        "|" + "---|" * (13 if fitted else 12),
    ]
    for r in rows:
        lines.append(
            f"| {r['scene']} | {r['frame']} | {r['start']} | {r['prior']} | {r['phase_gain']:.3f} "
            + (f"| {r['phase_gain_fitted']:.3f} " if fitted else "")
            + f"| {r['phase_rms_error_rad']:.2f} | {r['iterations']} | {r['stop']} "
            f"| {r['residual_pct']:.2f} | {r['field_upsample']}x | {r['coherence_x_um']:.2f} | {r['seconds']:.0f} |"
        )
    for scene in dict.fromkeys(r["scene"] for r in rows if r["scene"].startswith("beads")):
        own = [r for r in rows if r["scene"] == scene and r["prior"] == "none"]
        if len(own) > 1:
            lines += ["", f"{scene}: gains spread {_spread(own, 'phase_gain')} across frame sizes (target: within 3 %)"]
            lines[-1] += f", the fitted line's {_spread(own, 'phase_gain_fitted')}." if fitted else "."
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--scenes",
        nargs="+",
        default=["beads", "strip"],
        choices=["beads", "strip", "grits", "camera", "defaults", "bead-grains"],
        help="grits: the 160 x 2220 strip on P1200 and P2000 sandpaper, to frame_size_grits.md; "
        "defaults: the strip's crops with every default, the upstream distance not given and given, to "
        "frame_size_defaults.md; "
        "camera: the paper preset on the whole 2160 x 2560 frame and two row crops, to frame_size_camera.md; "
        "bead-grains: the bead scene's frame sizes on more draws of P3000, 1.2 um and 4.5 um grains, "
        "to frame_size_bead_grains.md",
    )
    ap.add_argument("--sizes", nargs="+", type=int, default=[256, 512, 1024], help="bead scene frame sizes (px)")
    ap.add_argument("--truth-start", action="store_true", help="also start the 160 x 2220 strip from the truth")
    ap.add_argument("--out", default="benchmarks/results", help="folder for frame_size.md and .csv")
    a = ap.parse_args()
    rows: list[dict] = []
    if "beads" in a.scenes:
        rows += beads(a.sizes)
    if "strip" in a.scenes:
        rows += strip(a.truth_start)
    if rows:
        write_rows_csv(a.out, "frame_size.csv", rows)
        write_markdown(rows, f"{a.out}/frame_size.md")
    if "grits" in a.scenes:
        grit_rows = [row for grit in GRITS for row in strip(False, grit=grit, crops=[(160, 2220)])]
        write_rows_csv(a.out, "frame_size_grits.csv", grit_rows)
        write_markdown(grit_rows, f"{a.out}/frame_size_grits.md", "python -m benchmarks.frame_size --scenes grits")
    if "defaults" in a.scenes:
        default_rows = strip_defaults()
        write_rows_csv(a.out, "frame_size_defaults.csv", default_rows)
        write_markdown(
            default_rows, f"{a.out}/frame_size_defaults.md", "python -m benchmarks.frame_size --scenes defaults"
        )
    if "bead-grains" in a.scenes:
        grain_rows = [
            {**row, "scene": f"{row['scene']}, seed {seed}"}
            for radius, seed in BEAD_GRAIN_RUNS
            for row in beads(a.sizes, seed=seed, wrong_prior=False, grain_radius_m=radius)
        ]
        write_rows_csv(a.out, "frame_size_bead_grains.csv", grain_rows)
        write_markdown(
            grain_rows, f"{a.out}/frame_size_bead_grains.md", "python -m benchmarks.frame_size --scenes bead-grains"
        )
    if "camera" in a.scenes:
        camera_rows = camera()
        write_rows_csv(a.out, "frame_size_camera.csv", camera_rows)
        write_markdown(camera_rows, f"{a.out}/frame_size_camera.md", "python -m benchmarks.frame_size --scenes camera")


if __name__ == "__main__":
    main()
