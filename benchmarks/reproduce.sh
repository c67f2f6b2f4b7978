#!/usr/bin/env bash
# Reproduce the committed results in benchmarks/results/ (run from the repository root after
# the README's install command). Each line is one benchmark; run any of them alone.
#   speed_accuracy.*   ~10 min on 2 cores: PWF, LCS K=3/6/12, UMPA, GF, MIST K=4/12 on the demo scan
#   speed_accuracy_beads.* ~15 min: the same comparison (9 runs) on the default scan's paper-sized bead
#   stability_map.*    ~17 min: where each method fails (one projection, 256 x 256)
#   bench_iteration_*  ~2 min: PWF iteration time / FFT time (add --device gpu on a GPU)
#   bench_scan_cpu.*   ~3 min: projections/s/worker on a LocalCluster, full-scan model
#   bead_contrast.*    ~1 min: the largest bead's phase/attenuation contrast against alpha
#   detector_defects.* ~6 min: PWF with zingers in the images, defect test on and off
#   authors_release.*  ~10 min: pwf-dask against the authors' released choices, 4 scenes
#   drift_baselines.*  ~1 min: UMPA and LCS with a drifting diffuser, correction off and on
#   calibration_dose.* ~25 min: coherence calibration (template, Gaussian) and PWF against dose
#   calibration_sweep.* ~3 min: the template fit against the Gaussian over 80 diffusers and geometries
#   geometry_sweep.*   ~2 min: PWF on other energies, pixels, coherence lengths and distances
#   frame_size.*       ~12 min: phase gain at 256^2-1024^2 and on wide 25 keV strips of PMMA rods
set -euo pipefail
PWF=${PWF:-.venv/bin/pwf-dask}
OUT=${OUT:-benchmarks/results}
case "${1:-all}" in
  accuracy) "$PWF" bench accuracy --out "$OUT" ;;
  accuracy-beads) "$PWF" bench accuracy --preset beads --out "$OUT" ;;
  stability) "$PWF" bench stability --out "$OUT" ;;
  iteration) "$PWF" bench iteration --out "$OUT" ;;
  scan) "$PWF" bench scan --out "$OUT" ;;
  bead) "$(dirname "$PWF")/python" benchmarks/bead_contrast.py --out "$OUT" ;;
  defects) "$(dirname "$PWF")/python" benchmarks/detector_defects.py --out "$OUT" ;;
  authors) "$(dirname "$PWF")/python" benchmarks/authors_release.py --out "$OUT" ;;
  drift) "$(dirname "$PWF")/python" benchmarks/drift_baselines.py --out "$OUT" ;;
  calibration) "$(dirname "$PWF")/python" benchmarks/calibration_dose.py --out "$OUT" ;;
  calibration-sweep) "$(dirname "$PWF")/python" benchmarks/calibration_sweep.py --out "$OUT" ;;
  geometry) "$(dirname "$PWF")/python" benchmarks/geometry_sweep.py --out "$OUT" ;;
  frame-size) "$(dirname "$PWF")/python" benchmarks/frame_size.py --truth-start --out "$OUT" ;;
  all)
    for b in accuracy accuracy-beads stability iteration scan bead defects authors drift calibration calibration-sweep geometry frame-size; do "$0" "$b"; done ;;
  *) echo "usage: $0 [accuracy|accuracy-beads|stability|iteration|scan|bead|defects|authors|drift|calibration|calibration-sweep|geometry|frame-size|all]" >&2; exit 2 ;;
esac
