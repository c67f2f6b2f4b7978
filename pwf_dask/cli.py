"""Command line: parses and calls; every computation lives in the library modules.

Commands of docs/scan-format.md §3: simulate, retrieve, tomo, fsc, run, demo; plus ``ingest``, ``estimate``, ``verify``,
``preview``, ``export`` and ``bench``.
"""

from __future__ import annotations

import argparse
import os
import sys
import threading
import time
import warnings
from pathlib import Path

#: ``pwf-dask demo``'s PWF iterations per projection at most: its 48 x 128 projections' measures
#: settle by 150, before the stop rule's median 340 (docs/validation.md, Scan-level findings, 10;
#: 61 angles, positions 0 / 1: cylinder delta -14.9 / -9.2 % against -16.0 / -7.8 % at 300, bead
#: delta -10.2 / -4.3 % against -10.7 / -3.6 %, FSC against the truth 4.5 px either way), in 0.65x
#: the time
DEMO_MAX_ITER = 150


def _scan_demo(args) -> int:
    from pwf_dask.pipeline.workflow import run_scan
    from pwf_dask.plots import preview
    from pwf_dask.simulation import simulate_scan
    from pwf_dask.stores import scan_io

    out = Path(args.dir)
    out.mkdir(parents=True, exist_ok=True)
    scan, recon = out / "scan.zarr", out / "recon.zarr"
    t0 = time.perf_counter()
    if not scan.exists():
        simulate_scan(scan, preset="demo", seed=args.seed, rotation_axis_offset_px=2.5)
    with _runner(args) as runner:
        summary = run_scan(
            scan,
            recon,
            scheduler=args.scheduler,
            device=args.device,
            runner=runner,
            max_iter=args.max_iter,
            phase_scale=args.phase_scale,
        )
    figs = preview(recon, out)
    sds, _ = scan_io.open_scan(scan, check_values=False)
    f = summary["fsc"]
    print(f"done in {time.perf_counter() - t0:.0f} s")
    print(
        f"FSC ({f['split']}, 1/4): delta {f['delta'] * 1e6:.2f} µm, beta {f['beta'] * 1e6:.2f} µm"
        + (f"; against the truth (1/2): delta {f['delta_truth'] * 1e6:.2f} µm" if "delta_truth" in f else "")
    )
    print(
        f"rotation centre {summary['tomo']['rotation_center_m'] * 1e6:+.2f} µm "
        f"(simulated {float(sds.attrs['simulation_rotation_axis_offset_m']) * 1e6:+.2f} µm)"
    )
    print(f"scan: {scan}\nreconstruction: {recon}\nfigures: " + ", ".join(str(p) for p in figs))
    return 0


def _simulate(args) -> int:
    from pwf_dask.simulation import simulate_scan
    from pwf_dask.simulation.scan import OPTICS_FIELDS

    shape = tuple(args.shape) if args.shape else None
    path = simulate_scan(
        args.out,
        preset=args.preset,
        shape=shape,
        angles=args.angles,
        positions=args.positions,
        photons=args.photons,
        seed=args.seed,
        raw=not args.corrected,
        rotation_axis_offset_px=args.axis_offset_px,
        diffuser_upstream_m=args.diffuser_upstream_m,
        zingers=args.zingers,
        diffuser_drift_px=tuple(args.diffuser_drift_px),
        cylinder_width_fraction=args.cylinder_width_fraction,
        dark_field_px=args.dark_field_px,
        diffuser_grit=args.grit,
        diffuser_radius_median_m=None if args.grain_radius_um is None else args.grain_radius_um * 1e-6,
        diffuser_grain_shape=args.grain_shape,
        beads=not args.no_beads,
        detector_blur_fwhm_m=args.detector_blur_um * 1e-6,
        detector_halo=(args.detector_halo[0], args.detector_halo[1] * 1e-6),
        optics={k: getattr(args, k) for k in OPTICS_FIELDS if getattr(args, k) is not None},
        coherence_model=args.coherence_model,
    )
    print(f"wrote scan {path}")
    return 0


def _ingest(args) -> int:
    from pwf_dask.stores.ingest import dxchange_specs, ingest_scan

    specs = dxchange_specs(args.dxchange) if args.dxchange else {}
    projections = args.projections or ([specs["projections"]] if "projections" in specs else None)
    reference = args.reference or ([specs["reference"]] if "reference" in specs else None)
    if not projections or not reference:
        raise ValueError("give --projections and --reference (TIFF files/globs or FILE.h5:/dataset), or --dxchange")
    angles = args.angles_from or (None if args.angles else specs.get("angles"))
    path = ingest_scan(
        args.out,
        projections=projections,
        reference=reference,
        flat=args.flat,
        dark=args.dark or specs.get("dark"),
        angles=angles,
        angles_range_deg=args.angles,
        angles_unit=args.angles_unit,
        energy_eV=args.energy_eV,
        pixel_size_m=args.pixel_size_m,
        sample_diffuser_distance_m=args.sample_diffuser_distance_m,
        diffuser_detector_distance_m=args.diffuser_detector_distance_m,
        coherence_length_x_m=args.coherence_length_x_m,
        coherence_length_y_m=args.coherence_length_y_m,
        flat_dark_corrected=args.flat_dark_corrected,
        diffuser_upstream_m=args.diffuser_upstream_m,
        full_scale_counts=args.full_scale_counts,
    )
    print(f"wrote scan {path}")
    return 0


def retrieval_kwargs(args) -> dict:
    """The retrieval options shared by ``retrieve``, ``run`` and deploy/jobqueue.py, as keyword
    arguments of :func:`pwf_dask.pipeline.workflow.run_scan`."""
    return dict(
        method=args.method,
        max_iter=args.max_iter,
        tol=args.tol,
        stationary_terms=args.stationary_terms,
        gamma=args.gamma,
        alpha=args.alpha,
        phase_scale=args.phase_scale,
        field_upsample=args.field_upsample,
        sample_field_grid=args.sample_field_grid,
        coherence_method=args.coherence_method,
        diffuser_model=args.diffuser_model,
        diffuser_material=args.diffuser_material,
        sample_material=args.sample_material,
        sample_delta_over_beta=args.sample_delta_over_beta,
        outlier_sigma=args.outlier_sigma,
        diffuser_drift=args.diffuser_drift,
        angle_chain=args.angle_chain,
        # only when asked: stores made without the option keep their recorded parameters
        **({"single_material": True} if args.single_material else {}),
        # None: the scan's recorded diffuser_upstream_m (0 when it has none)
        **({} if args.diffuser_upstream_m is None else {"diffuser_upstream_m": args.diffuser_upstream_m}),
        **({} if args.diffuser_nsr_floor is None else {"diffuser_nsr_floor": args.diffuser_nsr_floor}),
        **(
            {}
            if args.detector_halo is None
            else {
                "detector_halo_fraction": args.detector_halo[0],
                "detector_halo_radius_m": args.detector_halo[1] * 1e-6,
            }
        ),
    )


def _retrieve(args) -> int:
    from pwf_dask.pipeline.workflow import retrieve_scan

    with _runner(args) as runner:
        r = retrieve_scan(
            args.scan, args.recon, scheduler=args.scheduler, device=args.device, runner=runner, **retrieval_kwargs(args)
        )
    print(f"retrieved {r['computed']} projections in {r['wall_s']:.1f} s into {args.recon}")
    return 0


def tomo_kwargs(args, runner) -> dict:
    """``tomo`` and ``run``'s keywords for the tomography stage (add_tomo_options)."""
    return dict(
        scheduler=args.scheduler,
        device=args.device,
        center_m=None if args.center_um is None else args.center_um * 1e-6,
        runner=runner,
        fbp=args.fbp,
        slice_background=args.slice_background,
    )


def _tomo(args) -> int:
    from pwf_dask.pipeline.workflow import tomo_scan

    with _runner(args) as runner:
        r = tomo_scan(args.recon, **tomo_kwargs(args, runner))
    print(f"tomograms delta, beta written to {args.recon} (rotation centre {r['rotation_center_m'] * 1e6:+.2f} µm)")
    return 0


def _fsc(args) -> int:
    from pwf_dask.pipeline.workflow import fsc_scan

    r = fsc_scan(args.recon, split=args.split, criterion=args.criterion)
    print(f"FSC ({r['split']}, {args.criterion}): delta {r['delta'] * 1e6:.2f} µm, beta {r['beta'] * 1e6:.2f} µm")
    for k in ("delta_truth", "beta_truth"):
        if k in r:
            print(f"FSC against the simulated truth (1/2): {k.split('_')[0]} {r[k] * 1e6:.2f} µm")
    return 0


def _run(args) -> int:
    from pwf_dask.pipeline.workflow import run_scan
    from pwf_dask.plots import preview

    with _runner(args) as runner:
        r = run_scan(args.scan, args.recon, split=args.split, **tomo_kwargs(args, runner), **retrieval_kwargs(args))
    f = r["fsc"]
    figures = preview(args.recon, args.figures)
    if f is None:
        print(
            f"reconstruction {args.recon}: {r['retrieve']['computed']} projections retrieved (one angle: no tomogram)"
        )
    else:
        print(
            f"reconstruction {args.recon}: {r['retrieve']['computed']} projections retrieved; "
            f"FSC delta {f['delta'] * 1e6:.2f} µm, beta {f['beta'] * 1e6:.2f} µm ({f['split']}, 1/4)"
        )
    print("figures: " + ", ".join(str(p) for p in figures))
    return 0


def _estimate(args) -> int:
    from pwf_dask.pipeline.estimate import estimate_for_scan, format_estimate, machine_memory_mb

    if args.workers < 1 or args.iterations < 1:
        raise ValueError("--workers and --iterations are whole numbers >= 1")
    stages, sizes = estimate_for_scan(
        args.scan, workers=args.workers, iterations=args.iterations, field_upsample=args.field_upsample, fbp=args.fbp
    )
    ny, nx = sizes["shape"]
    print(f"{args.scan}: {sizes['positions']} position(s) x {sizes['angles']} angles x {ny} x {nx} px")
    print("\n".join(format_estimate(stages, args.workers, machine_memory_mb(), sizes["gpu_task_mb"])))
    return 0


def _verify(args) -> int:
    from pwf_dask.stores.integrity import verify_store

    report = verify_store(args.store, repair=args.repair)
    print("\n".join(report.lines()))
    if not report.ok and not args.repair:
        print("run 'pwf-dask verify --repair' and then the same 'pwf-dask run' to recompute what is damaged")
    return 0 if report.ok else 1


def _preview(args) -> int:
    from pwf_dask.plots import preview

    figures = preview(args.recon, args.dir)
    print("figures: " + ", ".join(str(p) for p in figures))
    return 0


def _export(args) -> int:
    from pwf_dask.stores.export import export_tiff

    files = export_tiff(args.recon, args.dir, layout=args.layout)
    print(f"wrote {len(files)} TIFF file{'s' * (len(files) != 1)} to {args.dir}")
    return 0


def _benchmarks_checkout() -> Path:
    """The repository root whose ``benchmarks/`` the bench verb runs (benchmarks are not installed)."""
    root = Path(__file__).resolve().parents[1]
    if not (root / "benchmarks" / "__init__.py").exists():
        raise ValueError("pwf-dask bench needs a source checkout: no benchmarks/ folder beside the pwf_dask package")
    if str(root) not in sys.path:
        sys.path.insert(0, str(root))
    return root


def _bench(args) -> int:
    _benchmarks_checkout()
    from benchmarks import speed as bench
    from benchmarks import speed_accuracy, stability

    runs = {
        "iteration": lambda: bench.run_iteration_benchmark(args.out, device=args.device, quick=args.quick),
        "accuracy": lambda: speed_accuracy.run_accuracy_benchmark(args.out, preset=args.preset),
        "scan": lambda: bench.run_scan_benchmark(args.out),
        "fbp": lambda: bench.run_fbp_benchmark(args.out, quick=args.quick),
        "perscan": lambda: bench.run_per_scan_benchmark(args.out, quick=args.quick),
        "fullwidth": lambda: bench.run_fullwidth_benchmark(
            args.out, quick=args.quick, work_dir=args.work_dir, device=args.device
        ),
        "stability": lambda: stability.run_stability_benchmark(args.out, quick=args.quick, axes=args.axes),
    }
    if args.what not in runs:
        raise SystemExit(f"pwf-dask bench: unknown benchmark {args.what!r}")
    runs[args.what]()
    print(f"results written to {args.out}")
    return 0


def _compute_options(p: argparse.ArgumentParser) -> None:
    from pwf_dask.pipeline.cluster import DEFAULT_DASHBOARD_ADDRESS

    p.add_argument(
        "--scheduler",
        default="threads",
        help="threads (default), processes, local, local-cuda, or tcp://HOST:PORT / tls://HOST:PORT",
    )
    p.add_argument("--device", default="cpu", choices=["cpu", "gpu", "auto"], help="NumPy or CuPy numerics")
    p.add_argument(
        "--dashboard-address",
        default=DEFAULT_DASHBOARD_ADDRESS,
        metavar="HOST:PORT",
        help="local, local-cuda: where the dashboard listens (default: this host only, any free port)",
    )
    p.add_argument(
        "--security",
        metavar="FILE.yaml",
        help="tls:// schedulers: a YAML of distributed.Security options (tls_ca_file, tls_client_cert, "
        "tls_client_key; docs/clusters.md)",
    )


def _runner(args):
    """The scheduler connection of a computing command (validated before anything is written)."""
    from pwf_dask.pipeline.cluster import Runner

    return Runner(args.scheduler, dashboard_address=args.dashboard_address, security=args.security)


def add_tomo_options(p) -> None:
    """The tomography options of ``tomo`` and ``run``."""
    p.add_argument(
        "--center-um", type=float, help="rotation axis on detector x, µm from the frame centre (default: found)"
    )
    p.add_argument(
        "--fbp",
        default="auto",
        choices=["auto", "gridrec", "backproject"],
        help="filtered back projection: gridrec (gridding with a non-uniform FFT: finufft on the CPU, the "
        "package's own on the GPU) or backproject (the direct reference); auto: gridrec where its NUFFT is there",
    )
    p.add_argument(
        "--slice-background",
        default="auto",
        choices=["auto", "quadratic", "none", "beta"],
        help="the quadratic background fit after the FBP (the paper's Methods). auto: on both tomograms, over "
        "the sample-free pixels beyond the sample's halo (one equivalent radius out), on slices where those "
        "cover a quarter of the field of view, else none; quadratic: over every sample-free pixel (the "
        "paper's; a halo then reads as curvature: the demo's cylinder delta -2.5 %% bare, -15.9 %% fitted); "
        "none; beta: on beta alone (docs/user-guide.md)",
    )


def _field_upsample(text: str):
    from pwf_dask.retrieval import check_field_upsample

    try:
        return check_field_upsample(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e).replace("field_upsample must be", "must be")) from None


def _nsr_floor(text: str) -> float | str:
    """A number, else the text ("sample"): the retrieval refuses any other in one line."""
    try:
        return float(text)
    except ValueError:
        return text


def add_retrieval_options(p: argparse.ArgumentParser) -> None:
    """Every retrieval option of ``retrieve`` and ``run`` (read back by :func:`retrieval_kwargs`)."""
    from pwf_dask.calibration.diffuser import DIFFUSER_MODEL_CHOICES
    from pwf_dask.options import DEFAULTS
    from pwf_dask.pipeline.workflow import DEFAULT_ANGLE_CHAIN
    from pwf_dask.pwf.stopping import STATIONARY_TERMS

    p.add_argument(
        "--method",
        default=DEFAULTS.method,
        choices=["pwf", "lcs", "umpa", "gf", "mist"],
        help="pwf (single shot, the paper's) or a speckle-tracking baseline (K >= 1 positions; docs/validation.md)",
    )
    p.add_argument("--max-iter", type=int, default=DEFAULTS.max_iter, help="pwf: iterations per projection at most")
    p.add_argument("--tol", type=float, default=DEFAULTS.tol, help="1 - field correlation of successive iterates")
    p.add_argument(
        "--stationary-terms",
        default=DEFAULTS.stationary_terms,
        choices=STATIONARY_TERMS,
        help="pwf: the stop's J test on J or its data term (the default: the camera's whole frame from zero "
        "300 iterations for 587), or on J alone (the rule before session 67; docs/validation.md)",
    )
    p.add_argument(
        "--gamma",
        type=float,
        default=DEFAULTS.gamma,
        help="width of the regularization window over the STF (0: no window)",
    )
    p.add_argument(
        "--alpha",
        default=str(DEFAULTS.alpha).strip("()"),
        help="regularization weights: 'sensitivity' (the default: 0.1+0.05j, docs/methods.md, with Im(alpha) "
        "lowered where the data see the phase weakly: faint speckle, high energy, and Re(alpha) where the sample "
        "absorbs strongly; once per scan), a complex number (e.g. 0.03+0.05j for small dense inclusions), "
        "'paper' (0.1+0.01j) or 'discrepancy' (Im(alpha) by the discrepancy principle, once per scan)",
    )
    p.add_argument(
        "--phase-scale",
        type=float,
        default=DEFAULTS.phase_scale,
        help="metric scale kappa of the phase block: faster phase convergence, same solution",
    )
    p.add_argument(
        "--field-upsample",
        default=DEFAULTS.field_upsample,
        type=_field_upsample,
        help="sample field and propagation on a finer grid: auto (1.5x for a diffuser whose spectrum fills the "
        "detector band, 2x more for thick samples), 1 (the paper's detector grid), or a factor such as 1.5 or 2",
    )
    p.add_argument(
        "--sample-field-grid",
        default=DEFAULTS.sample_field_grid,
        choices=["field", "detector"],
        help="pwf on a finer field grid: where exp(psi) is formed, on that grid (default) or on the detector grid "
        "(6 instead of 10 of its FFTs per iteration, 1.1-1.3x faster on the 1.5x grid; phase error 0-20 %% "
        "higher on P3000 scenes; with --field-upsample auto, coarse pixels keep it on the field grid: docs/methods.md)",
    )
    p.add_argument(
        "--coherence-method",
        default=DEFAULTS.coherence_method,
        choices=["template", "gaussian"],
        help="pwf: how the coherence lengths are calibrated from the reference when the scan does not give them: "
        "template (the IOTF fitted jointly with the sandpaper's own speckle spectrum) or gaussian (the paper's "
        "Siegert fit alone, long on grains as coarse as P3000)",
    )
    p.add_argument(
        "--diffuser-model",
        default=DEFAULTS.diffuser_model,
        choices=DIFFUSER_MODEL_CHOICES,
        help="diffuser estimate from the reference: one material fitted, the paper's zero phase, or auto "
        "(default): one material where the diffuser absorbs at least 5 /mm (silicon carbide up to ~11 keV), "
        "else zero phase unless a 20-iteration probe of both on each position's middle projection leaves "
        "the one material under half of zero phase's residual; where --alpha sensitivity lowers alpha and "
        "the one material then misfits more than zero phase, auto takes zero phase (a named one material "
        "keeps the default alpha instead)",
    )
    p.add_argument(
        "--diffuser-upstream-m",
        type=float,
        metavar="D",
        help="pwf: the diffuser sits D metres upstream of the sample (the scan has L1 = 0); its fitted field "
        "is propagated to the sample (default: the scan's diffuser_upstream_m attribute, else 0)",
    )
    p.add_argument(
        "--detector-halo",
        type=float,
        nargs=2,
        metavar=("FRACTION", "RADIUS_UM"),
        help="pwf: the detector spreads FRACTION of the light over an exponential halo of this 1/e radius in "
        "um (scattered scintillation light, from the detector's measured MTF); modelled beside the IOTF "
        "(default: none, the paper's model)",
    )
    p.add_argument(
        "--diffuser-nsr-floor",
        type=_nsr_floor,
        help="pwf: the least noise-to-signal ratio the diffuser estimate's Wiener filters take: 'sample' (the "
        "default: the sample image's photon noise over the reference's speckle, so that a reference averaged "
        "from many flats is not deconvolved past what the sample image shows), or a number (0: the reference's "
        "own ratio, as read); docs/methods.md, 'A reference too clean breaks the zero-phase estimate'",
    )
    p.add_argument(
        "--diffuser-material",
        default=DEFAULTS.diffuser_material,
        help="the diffuser's material, for its beta/delta (xraydb): silicon carbide, alumina, ...",
    )
    p.add_argument(
        "--sample-material",
        default=DEFAULTS.sample_material,
        help="mist and --single-material: the sample's one material, for its delta/beta (xraydb): cellulose, PMMA, ...",
    )
    p.add_argument(
        "--sample-delta-over-beta",
        type=float,
        help="mist and --single-material: the sample's delta/beta (overrides --sample-material)",
    )
    p.add_argument(
        "--single-material",
        action="store_true",
        help="pwf: the sample is one material (--sample-material): the phase's low frequencies follow its "
        "attenuation through Paganin's filter; for thick samples with sharp edges (mm rods at um pixels), "
        "wrong for samples of several materials",
    )
    p.add_argument(
        "--outlier-sigma",
        type=float,
        default=DEFAULTS.outlier_sigma,
        help="detector defects: single-pixel spikes and dips (zingers, hot/dead pixels) beyond this many noise "
        "sigmas of all their neighbours are left out (sample) or repaired (reference); 0 keeps every pixel",
    )
    p.add_argument(
        "--angle-chain",
        type=int,
        default=DEFAULT_ANGLE_CHAIN,
        metavar="N",
        help=f"pwf: each task retrieves N projections (every other angle), each started from the one before "
        f"(default {DEFAULT_ANGLE_CHAIN}); 1 starts every projection from zero, as the paper does",
    )
    p.add_argument(
        "--diffuser-drift",
        default=DEFAULTS.diffuser_drift,
        help="follow the speckle's drift since the reference (pwf moves its diffuser estimate, the trackers "
        "their reference frames): auto (measure it per frame, correct from 0.05 px), off, or DY,DX in pixels",
    )


def _split_option(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--split",
        default="auto",
        choices=["auto", "positions", "even-odd"],
        help="FSC halves: diffuser positions (K >= 2), even/odd angles, or auto (positions when K >= 2)",
    )


class _HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Shows each option's default, unless it has none or its help already says it."""

    def _get_help_string(self, action):
        text = action.help or ""
        if action.default in (None, False, argparse.SUPPRESS) or "default" in text:
            return text
        return super()._get_help_string(action)


def _simulate_command(command) -> None:
    from pwf_dask.physics.diffusers import DEFAULT_GRIT, FEPA_P_GRIT_DIAMETER_M, GRAIN_SHAPES
    from pwf_dask.simulation import DEFAULT_PRESET, PRESETS
    from pwf_dask.simulation.speckle import COHERENCE_MODELS

    s = command("simulate", "simulate a scan of a 3-D phantom into a Zarr store")
    s.add_argument("out", help="the new scan store (a path that does not exist yet)")
    s.add_argument(
        "--preset",
        default=DEFAULT_PRESET,
        help=f"one of {', '.join(PRESETS)}: beads (the default: paper-sized glass beads, 160 x 320 px, "
        "minutes), demo (seconds), small (the demo's phantom, 64 x 192), paper (801 x 2160 x 2560)",
    )
    s.add_argument(
        "--shape", type=int, nargs=2, metavar=("NY", "NX"), help="frame size in pixels (default: the preset's)"
    )
    s.add_argument("--angles", type=int, help="rotation angles over 180 deg (default: the preset's)")
    s.add_argument("--positions", type=int, help="diffuser positions K, one reference each (default: the preset's)")
    s.add_argument("--photons", type=float, help="photons per pixel of the open beam (default: the preset's)")
    s.add_argument("--seed", type=int, default=0, help="random seed of the diffuser and the noise")
    s.add_argument("--axis-offset-px", type=float, default=0.0, help="rotation axis offset from the frame centre")
    s.add_argument("--corrected", action="store_true", help="write flat/dark-corrected float32 instead of counts")
    s.add_argument(
        "--diffuser-upstream-m",
        type=float,
        default=0.0,
        help="put the diffuser this far upstream of the sample (the scan then has L1 = 0)",
    )
    s.add_argument(
        "--zingers",
        type=float,
        default=0.0,
        help="fraction of the pixels of every frame hit by a zinger (2-20x the open beam), e.g. 1e-4",
    )
    s.add_argument(
        "--diffuser-drift-px",
        type=float,
        nargs=2,
        default=(0.0, 0.0),
        metavar=("DY", "DX"),
        help="the diffuser drifts linearly from its reference position to (DY, DX) pixels at the last angle",
    )
    s.add_argument(
        "--cylinder-width-fraction",
        type=float,
        metavar="F",
        help="the sample cylinder's diameter over the frame width (default 0.576); above 1 the sample "
        "is wider than the field of view (an interior scan)",
    )
    s.add_argument(
        "--no-beads",
        action="store_true",
        help="leave the glass beads out: the cellulose cylinder alone, a sample of one material",
    )
    s.add_argument(
        "--dark-field-px",
        type=float,
        default=0.0,
        metavar="SIGMA",
        help="the sample scatters at small angles (pores, fibres): the speckle behind its thickest part "
        "is blurred by a Gaussian of this sigma in pixels",
    )
    s.add_argument(
        "--grit",
        default=DEFAULT_GRIT,
        choices=list(FEPA_P_GRIT_DIAMETER_M),
        help=f"the diffuser's sandpaper grade (FEPA P; default {DEFAULT_GRIT}, the paper's, 6.5 µm grains)",
    )
    s.add_argument(
        "--grain-radius-um",
        type=float,
        metavar="R",
        help="the diffuser's median grain radius in um (overrides --grit; e.g. 1.2 for sub-pixel grains)",
    )
    s.add_argument(
        "--grain-shape",
        default="spheres",
        choices=list(GRAIN_SHAPES),
        help="the diffuser's grains: spheres (default), faceted (pyramids, like crushed SiC) or mixed",
    )
    s.add_argument(
        "--detector-blur-um",
        type=float,
        default=0.0,
        metavar="FWHM",
        help="the detector's own blur (scintillator, microscope): a Gaussian of this FWHM in um on the "
        "intensity before the pixels (default 0: none)",
    )
    s.add_argument(
        "--detector-halo",
        type=float,
        nargs=2,
        default=(0.0, 0.0),
        metavar=("FRACTION", "RADIUS_UM"),
        help="a fraction of the light the detector spreads over an exponential halo of this 1/e radius in "
        "um (scattered scintillation light; default 0 0: none)",
    )
    beamline = s.add_argument_group("the beamline (default: the paper's; SI units, as `ingest` takes them)")
    for flag, dest, what in (
        ("--energy-eV", "energy_eV", "photon energy in eV (paper: 10000)"),
        ("--pixel-size-m", "pixel_size_m", "effective pixel size in m (paper: 0.65e-6); the sample scales with it"),
        (
            "--sample-diffuser-distance-m",
            "sample_diffuser_distance_m",
            "L1 in m (paper: 3e-3; 0 with an upstream diffuser)",
        ),
        ("--diffuser-detector-distance-m", "diffuser_detector_distance_m", "L2 in m (paper: 20e-3)"),
        (
            "--coherence-length-x-m",
            "coherence_length_x_m",
            "the source's coherence length in m along x (paper: 3.47e-6)",
        ),
        ("--coherence-length-y-m", "coherence_length_y_m", "along y (paper: 4.31e-6); the scan records neither"),
    ):
        beamline.add_argument(flag, dest=dest, type=float, help=what)
    beamline.add_argument(
        "--coherence-model",
        default="detector",
        choices=list(COHERENCE_MODELS),
        help="how partial coherence enters: detector (default), the paper's IPSF blur of the detector "
        "intensity, which PWF's model is; source, an extended source whose tilted waves also move the sample "
        "against the speckle (the lengths are then the reference's)",
    )
    s.set_defaults(func=_simulate)


def _ingest_command(command) -> None:
    i = command("ingest", "TIFF or HDF5 detector files into a scan store (docs/scan-format.md §1)")
    i.add_argument("out", help="the new scan store (a path that does not exist yet)")
    src = "TIFF file or glob, or FILE.h5:/dataset"
    i.add_argument("--projections", nargs="+", help=f"sample frames, one {src} per diffuser position")
    i.add_argument("--reference", nargs="+", help=f"diffuser frames without the sample ({src}), per position")
    i.add_argument("--flat", help=f"beam without diffuser and sample ({src}; several frames are averaged)")
    i.add_argument("--dark", help=f"dark frames ({src}; averaged)")
    i.add_argument("--dxchange", metavar="FILE.h5", help="take the above from tomopy's DXchange layout")
    i.add_argument("--angles", type=float, nargs=2, metavar=("START", "STOP"), help="evenly spaced, inclusive")
    i.add_argument("--angles-from", metavar="FILE", help="a text file of angles or FILE.h5:/dataset")
    i.add_argument("--angles-unit", default="deg", choices=["deg", "rad"], help="unit of the angles given")
    i.add_argument("--energy-eV", type=float, required=True, help="photon energy in eV (e.g. 20000)")
    i.add_argument("--pixel-size-m", type=float, required=True, help="effective pixel size in m (e.g. 6.5e-6)")
    i.add_argument("--sample-diffuser-distance-m", type=float, required=True, help="L1 (0: diffuser upstream)")
    i.add_argument("--diffuser-detector-distance-m", type=float, required=True, help="L2")
    i.add_argument(
        "--diffuser-upstream-m",
        type=float,
        default=0.0,
        help="with L1 = 0: the diffuser this far upstream of the sample (recorded for PWF)",
    )
    i.add_argument(
        "--full-scale-counts",
        type=float,
        help="raw counts at which the detector saturates, e.g. 4095 for a 12-bit camera (default: the "
        "frames' integer type maximum); PWF leaves such pixels out of its fit",
    )
    i.add_argument("--coherence-length-x-m", type=float, help="known coherence lengths (else calibrated)")
    i.add_argument("--coherence-length-y-m", type=float, help="(give both, or neither to calibrate)")
    i.add_argument("--flat-dark-corrected", action="store_true", help="the frames are already (I - dark)/(flat - dark)")
    i.set_defaults(func=_ingest)


def _retrieve_command(command) -> None:
    r = command("retrieve", "phase and attenuation of every projection (resumable)")
    r.add_argument("scan", help="the scan store (docs/scan-format.md §1)")
    r.add_argument("recon", help="the reconstruction store: created, or resumed with the same options")
    add_retrieval_options(r)
    _compute_options(r)
    r.set_defaults(func=_retrieve)


def _tomo_command(command) -> None:
    t = command("tomo", "delta and beta tomograms by FBP (resumable)")
    t.add_argument("recon", help="a reconstruction store whose projections are retrieved")
    add_tomo_options(t)
    _compute_options(t)
    t.set_defaults(func=_tomo)


def _fsc_command(command) -> None:
    f = command("fsc", "Fourier shell correlation and resolution")
    f.add_argument("recon", help="a reconstruction store with tomograms")
    _split_option(f)
    f.add_argument("--criterion", default="1/4", choices=["1/4", "1/7", "half-bit", "1/2"], help="FSC threshold")
    f.set_defaults(func=_fsc)


def _run_command(command) -> None:
    u = command("run", "retrieve + tomo + fsc + preview figures (resumable)")
    u.add_argument("scan", help="the scan store (docs/scan-format.md §1)")
    u.add_argument("recon", help="the reconstruction store: created, or resumed with the same options")
    _split_option(u)
    add_tomo_options(u)
    u.add_argument(
        "--figures", metavar="DIR", help="where `run` writes its figures (default: RECON's folder/NAME_figures)"
    )
    add_retrieval_options(u)
    _compute_options(u)
    u.set_defaults(func=_run)


def _estimate_command(command) -> None:
    from pwf_dask.pipeline import estimate  # its defaults (NumPy only: cheap at parse time)

    m = command("estimate", "peak memory per worker and time of each stage, predicted before a run")
    m.add_argument("scan", help="the scan store (only its metadata is read)")
    m.add_argument("--workers", type=int, default=1, help="single-threaded workers the time is divided over")
    m.add_argument(
        "--iterations",
        type=int,
        default=estimate.DEFAULT_ITERATIONS,
        help="PWF iterations per projection (the mean of the full-width bench of the paper's optics)",
    )
    m.add_argument(
        "--field-upsample",
        type=_field_upsample,
        default=estimate.DEFAULT_FIELD_UPSAMPLE,
        help="the sample field's grid factor (run's option; 1.5: what coarse diffusers such as P3000 take, "
        "1: fine grains; auto plans for 1.5)",
    )
    m.add_argument(
        "--fbp", default="auto", choices=["auto", "gridrec", "backproject"], help="tomo's FBP (run's option)"
    )
    m.set_defaults(func=_estimate)


def _verify_command(command) -> None:
    w = command("verify", "read every chunk of a scan or reconstruction store: missing or damaged ones (exit 1)")
    w.add_argument("store", help="a scan or reconstruction store")
    w.add_argument(
        "--repair",
        action="store_true",
        help="mark damaged projections and row blocks not done (their chunks removed): 'run' then recomputes them",
    )
    w.set_defaults(func=_verify)


def _preview_command(command) -> None:
    v = command("preview", "figures of a reconstruction: projection panels, delta/beta slices, FSC")
    v.add_argument("recon", help="a reconstruction store (figures of whatever stages it holds)")
    v.add_argument("dir", nargs="?", help="output folder (default: RECON_figures beside the store)")
    v.set_defaults(func=_preview)


def _export_command(command) -> None:
    e = command("export", "delta and beta tomograms to float32 TIFF (voxel size in the resolution tags)")
    e.add_argument("recon", help="a reconstruction store with tomograms")
    e.add_argument("dir", help="output folder (created; existing files of the same names are refused)")
    e.add_argument("--format", default="tiff", choices=["tiff"], help="file format")
    e.add_argument(
        "--layout",
        default="stack",
        choices=["stack", "slices"],
        help="stack: one multi-page file per volume; slices: a folder per volume, one file per slice",
    )
    e.set_defaults(func=_export)


def _demo_command(command) -> None:
    d = command("demo", "simulate a small scan, reconstruct it, write figures")
    d.add_argument("dir", nargs="?", default="pwf-dask-demo", help="output folder (default ./pwf-dask-demo)")
    d.add_argument("--max-iter", type=int, default=DEMO_MAX_ITER, help="PWF iterations per projection at most")
    d.add_argument("--phase-scale", type=float, default=1.0, help="metric scale kappa of the phase block")
    d.add_argument("--seed", type=int, default=0, help="random seed of the simulated scan")
    _compute_options(d)
    d.set_defaults(func=_scan_demo)


def _bench_command(command) -> None:
    b = command("bench", "benchmarks (from a source checkout); results to benchmarks/results/")
    b.add_argument(
        "what",
        choices=["iteration", "scan", "fbp", "perscan", "fullwidth", "accuracy", "stability"],
        help="iteration: PWF iteration / FFT time; scan: throughput per worker; fbp: gridrec vs backprojector; "
        "perscan: calibration, diffuser fit and model build against one retrieval; "
        "fullwidth: 801 x 32 x 2560 scan through pwf-dask run, full scan modelled; "
        "accuracy: speed vs error; "
        "stability: where each method fails",
    )
    b.add_argument("--device", default="cpu", choices=["cpu", "gpu", "auto"], help="NumPy or CuPy numerics")
    b.add_argument("--out", default="benchmarks/results", help="folder of the result files")
    b.add_argument("--quick", action="store_true", help="one small size or scene (smoke test)")
    b.add_argument(
        "--work-dir",
        default=None,
        help="fullwidth: folder of its scan and reconstruction (default: a new temporary one); given again, an "
        "interrupted run resumes there",
    )
    b.add_argument(
        "--preset",
        default="demo",
        help="accuracy: the scene, demo (speed_accuracy.*) or beads (the default scan's paper-sized bead; "
        "speed_accuracy_beads.*)",
    )
    b.add_argument(
        "--axes",
        nargs="+",
        metavar="AXIS",
        help="stability: re-measure only these axes, keep the others of the map in --out",
    )
    b.set_defaults(func=_bench)


def build_parser() -> argparse.ArgumentParser:
    """The whole command line: global flags, then one sub-command per stage (each added by its ``_NAME_command``)."""
    from pwf_dask import __version__

    p = argparse.ArgumentParser(
        prog="pwf-dask",
        description="Single-shot speckle X-ray phase tomography by preconditioned Wirtinger flow.",
        formatter_class=_HelpFormatter,
    )
    p.add_argument("--version", action="version", version=f"pwf-dask {__version__}")
    loud = p.add_mutually_exclusive_group()
    loud.add_argument("-v", "--verbose", action="store_true", help="debug messages too")
    loud.add_argument("-q", "--quiet", action="store_true", help="warnings and errors only: no progress lines")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def command(name: str, text: str) -> argparse.ArgumentParser:
        return sub.add_parser(name, help=text, description=text, formatter_class=_HelpFormatter)

    for add in (
        _simulate_command,
        _ingest_command,
        _retrieve_command,
        _tomo_command,
        _fsc_command,
        _run_command,
        _estimate_command,
        _verify_command,
        _preview_command,
        _export_command,
        _demo_command,
        _bench_command,
    ):
        add(command)
    return p


def _interrupted_message(args) -> str:
    """What Ctrl-C leaves: the projections the reconstruction store holds, and how to go on."""
    recon = getattr(args, "recon", None)
    saved = ""
    if recon is not None and args.command in ("retrieve", "run"):
        try:
            import zarr

            done = zarr.open_group(str(recon), mode="r", use_consolidated=False)["iterations"][...] >= 0
            saved = f": {int(done.sum())} of {done.size} projections saved"
        except Exception:  # noqa: BLE001 - interrupted before the store existed: nothing saved
            saved = ": no projection saved yet"
    return f"pwf-dask {args.command}: interrupted{saved}; run the same command to resume"


def _one_line_warning(message, category, filename, lineno, file=None, line=None) -> None:
    # a library's warning may run over several lines (xarray's advice lists): its first says what
    first = str(message).strip().splitlines()[0] if str(message).strip() else category.__name__
    print(f"pwf-dask: warning: {first}", file=sys.stderr if file is None else file)


def main(argv: list[str] | None = None) -> int:
    from pwf_dask.log import configure

    args = build_parser().parse_args(argv)
    configure(1 if args.verbose else -1 if args.quiet else 0)
    warnings.showwarning = _one_line_warning
    try:
        return int(args.func(args) or 0)
    except (ValueError, OSError, RuntimeError) as exc:
        print(f"pwf-dask {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(_interrupted_message(args), file=sys.stderr, flush=True)
        sys.stdout.flush()
        if threading.active_count() > 1:
            # the scheduler's worker threads would finish their chains first (~15 s); every
            # projection is marked done only after its arrays are written, so leaving now
            # loses at most the projections in flight
            os._exit(130)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
