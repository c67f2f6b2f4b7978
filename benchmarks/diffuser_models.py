"""Both diffuser models on the random geometries: where ``diffuser_model="auto"`` picks the worse one.

``"auto"`` chooses the diffuser model from the diffuser's absorption alone
(:func:`pwf_dask.calibration.choose_diffuser_model`: the single-material fit where silicon
carbide absorbs at least 5 /mm, about 11.4 keV, else the paper's zero-phase estimate). Here
each of :mod:`benchmarks.random_scenes`' scenes (the same draws and seeds) is retrieved with
each model, given the true coherence lengths so that the calibration does not blur the
comparison, and the data residual of each is reported beside its phase error.

``"auto"`` is scored as built: the absorption rule, and where it gives zero phase a probe of
:data:`pwf_dask.retrieval.DIFFUSER_PROBE_ITER` iterations of each model that takes the
single-material fit where its data residual is under
:data:`pwf_dask.retrieval.DIFFUSER_PROBE_RATIO` of zero phase's
(:func:`pwf_dask.retrieval.choose_diffuser`, timed against the zero-phase retrieval). Beside
it, the absorption rule alone (``"auto"`` before the probe) and, for reference, a rule no
retrieval can run: the other model where its final data residual is under half.

    python -m benchmarks.diffuser_models [--scenes 80] [--calibrated] [--out benchmarks/results]

Writes ``diffuser_models.md`` and ``.csv`` (about 55 min for 80 scenes on 2 cores); with
``--calibrated`` each retrieval calibrates its coherence lengths from the reference, as a
user's run does, into ``diffuser_models_calibrated.md`` and ``.csv`` (about 30 min with
``--scenes 40``).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from benchmarks.random_scenes import draw_scene
from benchmarks.reporting import device_name, write_rows_csv
from benchmarks.stability import PHASE_ERROR_THRESHOLD, errors
from pwf_dask.options import DEFAULTS
from pwf_dask.retrieval import DIFFUSER_PROBE_ITER, choose_diffuser, chosen_diffuser_model, retrieve_projection

MODELS = ("zero-phase", "single-material")
#: the rule scored: the other model where its data residual is under this fraction of auto's
SWITCH_RATIO = 0.5


def scene_row(i: int, calibrated: bool = False) -> dict:
    """Scene ``i`` of :mod:`benchmarks.random_scenes` with each model: error, gain, residual;
    given the true coherence lengths, or ``calibrated`` from the reference as a user's run is."""
    setup, sim, background = draw_scene(i)
    options = dict(**sim.geometry(), background_mask=background)
    if not calibrated:
        options.update(coherence_length_x_m=setup.coherence_length_x_m, coherence_length_y_m=setup.coherence_length_y_m)
    if setup.diffuser_upstream_m:
        options["diffuser_upstream_m"] = setup.diffuser_upstream_m
    auto = chosen_diffuser_model("auto", DEFAULTS.diffuser_material, None, setup.energy_eV)[0]
    row = {
        "scene": i,
        "energy_keV": setup.energy_eV / 1e3,
        "pixel_um": setup.pixel_size_m * 1e6,
        "l1_mm": setup.sample_diffuser_distance_m * 1e3,
        "upstream_mm": setup.diffuser_upstream_m * 1e3,
        "l2_mm": setup.diffuser_detector_distance_m * 1e3,
        "grain_radius_um": setup.diffuser_radius_median_m * 1e6,
        "photons": setup.photons,
        "visibility": float(sim.reference.std() / sim.reference.mean()),
        "auto": auto,
        "refused": "",
        "probe": "",
        "probe_zp_residual": float("nan"),
        "probe_sm_residual": float("nan"),
        "probe_s": 0.0,
    }
    for model in MODELS:
        key = "zp" if model == "zero-phase" else "sm"
        t0 = time.perf_counter()
        try:
            res = retrieve_projection(sim.sample, sim.reference, **options, diffuser_model=model)
        except ValueError as exc:  # the calibration's refusal (--calibrated): both models alike
            return {**row, "refused": str(exc).split(";")[0]}
        err = errors(res.phase, res.attenuation, sim.phase, sim.attenuation, background)
        row[f"{key}_error"] = err["phase_error"]
        row[f"{key}_gain"] = err["phase_gain"]
        row[f"{key}_residual"] = res.residual_rmse
        row[f"{key}_s"] = time.perf_counter() - t0
        row[f"{key}_iterations"] = res.iterations
        row[f"{key}_alpha"] = res.parameters["alpha"]
    # the same S for both models: the rule reads the reference alone; the fit keeps the default
    # alpha where its probe residual is over zero phase's (retrieval.alpha_rule_holds)
    row["phase_sensitivity"] = res.parameters.get("phase_sensitivity", float("nan"))
    row["alpha"] = row["zp_alpha"]
    row["sm_model_ratio"] = res.parameters.get("alpha_rule_model_ratio", float("nan"))
    if calibrated:  # the lengths the retrievals calibrated, as the probe's retrieval would
        options.update(coherence_length_x_m=res.coherence_length_x_m, coherence_length_y_m=res.coherence_length_y_m)
    t0 = time.perf_counter()
    choice = choose_diffuser(sim.sample, sim.reference, **{k: v for k, v in options.items() if k != "background_mask"})
    row["probe_s"] = time.perf_counter() - t0
    row["probe"] = choice.model
    if choice.residuals_pct:
        row["probe_zp_residual"] = choice.residuals_pct["zero-phase"]
        row["probe_sm_residual"] = choice.residuals_pct["single-material"]
    return row


def rule_errors(rows: list[dict]) -> list[tuple[float, bool]]:
    """(phase error, switched) per scene under the rule no retrieval can run: the absorption
    rule's model, or the other where its final residual is under :data:`SWITCH_RATIO` of it."""
    out = []
    for r in rows:
        mine, other = ("zp", "sm") if r["auto"] == "zero-phase" else ("sm", "zp")
        switch = r[f"{other}_residual"] < SWITCH_RATIO * r[f"{mine}_residual"]
        out.append((r[f"{other if switch else mine}_error"], bool(switch)))
    return out


def probe_errors(rows: list[dict]) -> list[tuple[float, bool]]:
    """(phase error, switched from the absorption rule) per scene with ``"auto"`` as built."""
    return [(r["zp_error"] if r["probe"] == "zero-phase" else r["sm_error"], r["probe"] != r["auto"]) for r in rows]


def _summary(name: str, errs: list[float], switched: int | str = "") -> str:
    e = np.asarray(errs)
    held = int(np.sum(e < PHASE_ERROR_THRESHOLD))
    return f"| {name} | {held} | {np.median(e):.3f} | {np.mean(e):.3f} | {switched} |"


def _kept_default(r: dict) -> bool:
    """Whether the single-material fit ran at the default alpha where the rule lowers it for
    zero phase: the alpha rule's model probe found the fit misfitting more."""
    return "sm_alpha" in r and r["sm_alpha"] != r["zp_alpha"]


def _default_mark(r: dict) -> str:
    return " (default alpha)" if _kept_default(r) else ""


def _alpha_guard_sentence(rows: list[dict]) -> str:
    """How often the alpha rule's model probe kept the fit at the default alpha."""
    checked = [r for r in rows if np.isfinite(r.get("sm_model_ratio", float("nan")))]
    if not checked:
        return "The alpha rule's model probe ran in no scene."
    kept = [r for r in checked if _kept_default(r)]
    auto = [str(r["scene"]) for r in kept if r["auto"] == "single-material"]
    scenes = ("scenes " if len(auto) > 1 else "scene ") + ", ".join(auto)
    took = (
        f'In {len(auto)} of them ({scenes}) `"auto"` had taken the fit by the grains\' absorption: it takes '
        'zero phase at the rule\'s alpha instead (since session 101; the `"auto"` row).'
        if auto
        else '`"auto"` had taken the fit by the grains\' absorption in none of them.'
    )
    return (
        f"The alpha rule's model probe ran in {len(checked)} scenes (S under 0.015, the single-material fit): "
        f"in {len(kept)} the fit misfit the sample more than zero phase (probe residual ratio over 1) and kept "
        f"the default alpha, marked (default alpha) below. {took}"
    )


def write_report(rows: list[dict], out_dir: str | Path, device: str, name: str) -> None:
    refused = [r for r in rows if r["refused"]]
    rows = [r for r in rows if not r["refused"]]
    zp = [r["zp_error"] for r in rows]
    sm = [r["sm_error"] for r in rows]
    auto = [r["zp_error"] if r["auto"] == "zero-phase" else r["sm_error"] for r in rows]
    final = rule_errors(rows)
    probe = probe_errors(rows)
    probed = [r for r in rows if r["probe_s"] and np.isfinite(r["probe_zp_residual"])]
    cost = [r["probe_s"] / r["zp_s"] for r in probed]
    lines = [
        f"# Diffuser models on {len(rows)} random geometries ({device})",
        "",
        "`python -m benchmarks.diffuser_models`: the scenes of `benchmarks.random_scenes` (same draws and",
        "seeds), each retrieved with the zero-phase estimate and with the single-material fit, "
        + ("coherence lengths calibrated from each reference (`--calibrated`)." if "calibrated" in name else "true")
        + ("" if "calibrated" in name else "\ncoherence lengths.")
        + f" A model holds below a phase error of {PHASE_ERROR_THRESHOLD}."
        + ' Alpha is the default rule\'s (`alpha="sensitivity"`: Im(alpha) 0.05 scaled down where the'
        + " reference's phase sensitivity S is under 0.015); S per scene in the CSV and the table below.",
        f"The absorption rule takes the single-material fit in {sum(r['auto'] != 'zero-phase' for r in rows)} scenes."
        + (f" The calibration refused {len(refused)} scenes (left out)." if refused else ""),
        "",
        "| choice | holds | median error | mean error | scenes switched from auto |",
        "|---|---:|---:|---:|---:|",
        _summary("zero phase everywhere", zp),
        _summary("single material everywhere", sm),
        _summary('the absorption rule alone (`"auto"` before the probe)', auto),
        _summary(
            '`"auto"` as built: the absorption rule, then where it gives zero phase '
            f"the probe ({DIFFUSER_PROBE_ITER} iterations each)",
            [e for e, _ in probe],
            sum(s for _, s in probe),
        ),
        _summary(
            f"(no retrieval can run it) the other model where its final residual < {SWITCH_RATIO}x",
            [e for e, _ in final],
            sum(s for _, s in final),
        ),
        _summary("the better model of each scene (oracle)", np.minimum(zp, sm).tolist()),
        "",
        _alpha_guard_sentence(rows),
        "",
        f"The probe ran in {len(probed)} scenes: {np.median(cost):.2f}x the zero-phase retrieval's time "
        f"(median; {min(cost):.2f}-{max(cost):.2f}), which it adds to a single projection's retrieval"
        " (a scan pays it once per diffuser position)."
        if probed
        else "The probe ran in no scene.",
        "",
        "Scenes where the two models differ by more than 0.05 in phase error, or a rule switches:",
        "",
        "| scene | keV | pixel µm | L1 mm | upstream mm | L2 mm | grain µm | visibility | S | auto "
        "| zero phase: error / gain / residual % | single material: error / gain / residual % "
        "| probe residual ratio (single / zero) | switched (probe / final) |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---|---|---:|---|",
    ]
    for r, (_, fs), (_, ps) in zip(rows, final, probe):
        if abs(r["zp_error"] - r["sm_error"]) <= 0.05 and not (fs or ps):
            continue
        ratio = r["probe_sm_residual"] / r["probe_zp_residual"]
        lines.append(
            f"| {r['scene']} | {r['energy_keV']:.1f} | {r['pixel_um']:.2f} | {r['l1_mm']:.1f} | "
            f"{r['upstream_mm']:.1f} | {r['l2_mm']:.0f} | {r['grain_radius_um']:.1f} | {r['visibility']:.3f} | "
            f"{r['phase_sensitivity']:.1e} | "
            f"{r['auto']} | {r['zp_error']:.3f} / {r['zp_gain']:.2f} / {r['zp_residual']:.2f} | "
            f"{r['sm_error']:.3f} / {r['sm_gain']:.2f} / {r['sm_residual']:.2f}{_default_mark(r)} | "
            f"{'-' if np.isnan(ratio) else f'{ratio:.2f}'} | "
            f"{'yes' if ps else 'no'} / {'yes' if fs else 'no'} |"
        )
    Path(out_dir, f"{name}.md").write_text("\n".join(lines) + "\n")


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=80)
    ap.add_argument("--out", default="benchmarks/results")
    ap.add_argument("--calibrated", action="store_true", help="coherence lengths calibrated, not given")
    args = ap.parse_args(argv)
    name = "diffuser_models_calibrated" if args.calibrated else "diffuser_models"
    rows = []
    for i in range(args.scenes):
        rows.append(scene_row(i, args.calibrated))
        r = rows[-1]
        done = r["refused"] or (
            f"auto {r['auto']} -> {r['probe']}, zero phase {r['zp_error']:.3f}, single {r['sm_error']:.3f}"
        )
        print(f"scene {i}: {done}", flush=True)
    out = write_rows_csv(args.out, f"{name}.csv", [r for r in rows if not r["refused"]])
    write_report(rows, out, device_name(np), name)
    return rows


if __name__ == "__main__":
    main()
