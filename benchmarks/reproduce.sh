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
#   calibration_dose.* ~6 min: coherence calibration (template, Gaussian) and PWF against dose
#   calibration_sweep.* ~1 min: the template fit against the Gaussian over 80 diffusers and geometries
#   geometry_sweep.*   ~2 min: PWF on other energies, pixels, coherence lengths and distances
#   random_scenes.*    ~30 min: PWF (calibrated, true lengths) and UMPA K=1 on 80 random geometries
#                      (random_scenes_160-239.*: random-scenes-held-out, ~37 min: the held-out scenes 160-239,
#                      then sensitivity_check --add-scenes takes their PWF rows)
#   diffuser_models.*  ~30 min: both diffuser models and "auto"'s probe on the 80 random geometries
#                      (diffuser_models_calibrated.*: --calibrated --scenes 40, ~14 min)
#   frame_size.*       ~12 min: phase gain at 256^2-1024^2 and on wide 25 keV strips of PMMA rods
#   frame_size_grits.* ~2 min: the 160 x 2220 strip on P1200 and P2000 sandpaper
#   frame_size_defaults.* ~11 min: the strip's crops with every default (zero phase at 25 keV)
#   frame_size_bead_grains.* ~20 min: the bead scene at 256^2-1024^2 on more P3000 draws, 1.2 and 4.5 um grains
#   frame_size_camera.* ~11 min: the paper preset on the camera's whole 2160 x 2560 frame and row crops
#   edge_step.*        ~14 min: where the camera frame's 5 % of phase goes (start, alpha, prior)
#   cylinder_rows.*    ~25 min: a wide weak cylinder's phase at 48-768 rows, three grains, three draws
#                      (cylinder_rows_why.*: --why, ~5 min: two low draws taken apart, noise to regularizer)
#   cylinder_draws.*   ~21 min: the demo scan's cylinder in the slice over 8 seeds, P3000, 1.2 um, P2000
#                      (cylinder_draws_why.*: --why, ~6 min: 8 diffuser draws, estimated and true t, noise-free;
#                      cylinder_draws_1e3.*: at 1e3 ph/px, ~14 min; cylinder_draws_96rows.*: 96 rows, P3000, ~10 min)
#   coherence_sensitivity.* ~12 min: phase gain against coherence-length error (0.7-1.3x), every other default
#                      (coherence_sensitivity_1000ph.*, _100ph.*: coherence-sensitivity-low-dose, ~8 min)
#   low_dose_lengths.* ~16 min: the random geometries' low-dose scenes with the calibrated lengths x1.1 and x1.25
#                      (low_dose_lengths_fresh.*: --fresh 240 60 --factors 1.1, ~24 min: new scenes at a drawn low dose;
#                      low_dose_alpha.*: --scale im-alpha --factors 4, ~8 min: the rule's Im(alpha) x4 instead;
#                      low_dose_reference*.*: low-dose-reference, ~75 min: the reference at 10x and 100x the sample's
#                      dose with the default Wiener floor, then with diffuser_nsr_floor 0 (_floor0) and at 100x 1e-4;
#                      high_dose_reference*.*: the scenes from 3e4 ph/px up at 10x, the default floor and 0)
#   absorbing_samples_0-159.*, _160-239.* ~30 min each: absorbing-samples, the random geometries that hold, their
#                      beta scaled to an attenuation range of 1 and 2: PWF (Re(alpha) by the contrast, and 0.1) and UMPA K=1
#   bead_absorption.*  ~3 min: bead-absorption, the map's scene at 0-10x its beta, PWF by the rule and at fixed Re(alpha)
#   holds_by_dose.*, _misread.csv ~3 min: holds-by-dose, after sensitivity-check: the random geometries' S again at
#                      1e5 ph/px, holds per decade of dose with the sensitivity limit apart, the misread scenes re-run
#   detector_psf.*     ~15 min: PWF (calibrated, given the blurred lengths) and UMPA K=1 under the detector's own blur
#   upstream_distance.* ~15 min: an upstream diffuser (L1 = 0) at 0-100 mm, PWF at each assumed distance: what selects it
#   position_agreement.* ~25 min: two diffuser positions' retrievals of the random geometries: do they agree where PWF fails?
#   alpha_sensitivity.* ~30 min: alpha="sensitivity" against the default alpha: random geometries 0-79, 10-25 keV, the rod strip
#   coarse_start.*     ~25 min: a coarse-to-fine start (2x2 binned solve) against zero and the true psi
#   probe_window.*     ~7 min: "auto"'s diffuser probe on a window of wide frames against the whole frame
#   probe_iterations.* ~25 min: "auto"'s diffuser probe at 10 / 20 / 40 iterations on the random scenes and strips
#   bench_fbp_cpu.*    ~5 min: gridding FBP against the backprojector, 2560 px x 801 angles
#   bench_per_scan_cpu.* ~3 min: calibration, diffuser fit and model build against one retrieval
#   field_grid.*       ~80 min: phase gain and iteration cost of the field grid 1x-2x on P3000 scenes, exp(psi) on either grid (also on the 80 random geometries)
#   fft_lengths.*      ~12 min: an iteration on scipy's fast FFT lengths against fast_len's, 256^2 to 2160 x 2560
#                      (fft_lengths_sizes.*: --part sizes, ~6 min: 2-D transforms by side, the rules weighed)
#   fft_library.*      ~4 min: an iteration with MKL's FFTs against pocketfft's, one and two threads, 512^2 to 2160 x 2560
#   scan_optics.*      ~20 min: whole scans at other beamlines (energy, pixel, L1 / L2, upstream diffuser) through the CLI
#   paper_figures.*    ~1.5 min: the paper's Fig. 2 and Fig. 3 on simulated scenes, PWF beside LCS K=12
#   bench_fullwidth_cpu.* ~2.5 h: 801 angles x 32 x 2560 through pwf-dask run, the full scan modelled
#   warm_stop.*        ~3 min after fullwidth (WORK_DIR=its --work-dir): the stop's jtol against the true phase
set -euo pipefail
PWF=${PWF:-.venv/bin/pwf-dask}
OUT=${OUT:-benchmarks/results}
case "${1:-all}" in
  accuracy) "$PWF" bench accuracy --out "$OUT" ;;
  accuracy-beads) "$PWF" bench accuracy --preset beads --out "$OUT" ;;
  stability) "$PWF" bench stability --out "$OUT" ;;
  iteration) "$PWF" bench iteration --out "$OUT" ;;
  scan) "$PWF" bench scan --out "$OUT" ;;
  bead) "$(dirname "$PWF")/python" -m benchmarks.bead_contrast --out "$OUT" ;;
  defects) "$(dirname "$PWF")/python" -m benchmarks.detector_defects --out "$OUT" ;;
  authors) "$(dirname "$PWF")/python" -m benchmarks.authors_release --out "$OUT" ;;
  drift) "$(dirname "$PWF")/python" -m benchmarks.drift_baselines --out "$OUT" ;;
  calibration) "$(dirname "$PWF")/python" -m benchmarks.calibration_dose --out "$OUT" ;;
  calibration-sweep) "$(dirname "$PWF")/python" -m benchmarks.calibration_sweep --out "$OUT" ;;
  geometry) "$(dirname "$PWF")/python" -m benchmarks.geometry_sweep --out "$OUT" ;;
  frame-size) "$(dirname "$PWF")/python" -m benchmarks.frame_size --truth-start --out "$OUT" ;;
  frame-grits) "$(dirname "$PWF")/python" -m benchmarks.frame_size --scenes grits --out "$OUT" ;;
  frame-defaults) "$(dirname "$PWF")/python" -m benchmarks.frame_size --scenes defaults --out "$OUT" ;;
  frame-bead-grains) "$(dirname "$PWF")/python" -m benchmarks.frame_size --scenes bead-grains --out "$OUT" ;;
  frame-camera) "$(dirname "$PWF")/python" -m benchmarks.frame_size --scenes camera --out "$OUT" ;;
  edge-step) "$(dirname "$PWF")/python" -m benchmarks.edge_step --out "$OUT" ;;
  cylinder-rows) "$(dirname "$PWF")/python" -m benchmarks.cylinder_rows --out "$OUT" ;;
  cylinder-why) "$(dirname "$PWF")/python" -m benchmarks.cylinder_rows --why --out "$OUT" ;;
  cylinder-draws) "$(dirname "$PWF")/python" -m benchmarks.cylinder_draws --out "$OUT" ;;
  cylinder-draws-why) "$(dirname "$PWF")/python" -m benchmarks.cylinder_draws --why --out "$OUT" ;;
  cylinder-draws-edge) "$(dirname "$PWF")/python" -m benchmarks.cylinder_draws --edge --out "$OUT" ;;
  cylinder-draws-single-material) "$(dirname "$PWF")/python" -m benchmarks.cylinder_draws --single-material --grains P3000 --out "$OUT" ;;
  cylinder-draws-1e3) "$(dirname "$PWF")/python" -m benchmarks.cylinder_draws --photons 1e3 --grains P3000 "1.2 um" --out "$OUT" ;;
  cylinder-draws-96rows) "$(dirname "$PWF")/python" -m benchmarks.cylinder_draws --rows 96 --grains P3000 --out "$OUT" ;;
  coherence-sensitivity) "$(dirname "$PWF")/python" -m benchmarks.coherence_sensitivity --out "$OUT" ;;
  low-dose-lengths) "$(dirname "$PWF")/python" -m benchmarks.low_dose_lengths --out "$OUT" && "$(dirname "$PWF")/python" -m benchmarks.low_dose_lengths --fresh 240 60 --factors 1.1 --out "$OUT" && "$(dirname "$PWF")/python" -m benchmarks.low_dose_lengths --scale im-alpha --factors 4 --out "$OUT" ;;
  low-dose-reference) for a in "10 --factors 1" "100 --factors 1" "10 --factors 1 1.1 --nsr-floor 0" "100 --factors 1 --nsr-floor 0" "100 --factors 1 --nsr-floor 1e-4" "10 --factors 1 --min-photons 3e4 --max-photons inf" "10 --factors 1 --min-photons 3e4 --max-photons inf --nsr-floor 0"; do "$(dirname "$PWF")/python" -m benchmarks.low_dose_lengths --reference-dose $a --out "$OUT" || exit 1; done ;;
  coherence-sensitivity-low-dose) for n in 1000 100; do "$(dirname "$PWF")/python" -m benchmarks.coherence_sensitivity --photons $n --out "$OUT" || exit 1; done ;;
  coarse-start) "$(dirname "$PWF")/python" -m benchmarks.coarse_start --curve --out "$OUT" ;;
  probe-window) "$(dirname "$PWF")/python" -m benchmarks.probe_window --out "$OUT" ;;
  probe-iterations) "$(dirname "$PWF")/python" -m benchmarks.probe_iterations --out "$OUT" ;;
  demo-dose) "$(dirname "$PWF")/python" -m benchmarks.demo_dose --out "$OUT" ;;
  random-scenes) "$(dirname "$PWF")/python" -m benchmarks.random_scenes --out "$OUT" ;;
  sensitivity-check) "$(dirname "$PWF")/python" -m benchmarks.sensitivity_check --out "$OUT" ;;
  random-scenes-held-out) "$(dirname "$PWF")/python" -m benchmarks.random_scenes --first 160 --scenes 80 --out "$OUT" && "$(dirname "$PWF")/python" -m benchmarks.sensitivity_check --add-scenes --out "$OUT" ;;
  bead-absorption) "$(dirname "$PWF")/python" -m benchmarks.bead_absorption --out "$OUT" ;;
  holds-by-dose) "$(dirname "$PWF")/python" -m benchmarks.holds_by_dose --out "$OUT" ;;
  absorbing-samples) for r in "0 159" "160 239"; do set -- $r; "$(dirname "$PWF")/python" -m benchmarks.absorbing_samples --first "$1" --last "$2" --out "$OUT" || exit 1; done ;;
  detector-psf) "$(dirname "$PWF")/python" -m benchmarks.detector_psf --out "$OUT" ;;
  upstream-distance) "$(dirname "$PWF")/python" -m benchmarks.upstream_distance --out "$OUT" ;;
  position-agreement) "$(dirname "$PWF")/python" -m benchmarks.position_agreement --out "$OUT" ;;
  alpha-sensitivity) "$(dirname "$PWF")/python" -m benchmarks.alpha_sensitivity --out "$OUT" ;;
  sensitivity-check-stability) "$(dirname "$PWF")/python" -m benchmarks.sensitivity_check --only-stability --out "$OUT" ;;
  diffuser-models) "$(dirname "$PWF")/python" -m benchmarks.diffuser_models --out "$OUT" ;;
  fbp) "$PWF" bench fbp --out "$OUT" ;;
  perscan) "$PWF" bench perscan --out "$OUT" ;;
  fullwidth) "$PWF" bench fullwidth --out "$OUT" ;;
  warm-stop) "$(dirname "$PWF")/python" -m benchmarks.warm_stop "${WORK_DIR:?set WORK_DIR to the fullwidth bench --work-dir}" --out "$OUT" ;;
  field-grid) "$(dirname "$PWF")/python" -m benchmarks.field_grid --out "$OUT" ;;
  fft-lengths) "$(dirname "$PWF")/python" -m benchmarks.fft_lengths --part all --out "$OUT" ;;
  fft-library) "$(dirname "$PWF")/python" -m benchmarks.fft_library --out "$OUT" ;;
  scan-optics) "$(dirname "$PWF")/python" -m benchmarks.scan_optics --out "$OUT" ;;
  source-coherence) "$(dirname "$PWF")/python" -m benchmarks.source_coherence --out "$OUT" && "$(dirname "$PWF")/python" -m benchmarks.source_coherence --random --out "$OUT" ;;
  paper-figures) "$(dirname "$PWF")/python" -m benchmarks.paper_figures --out "$OUT" ;;
  all)
    for b in accuracy accuracy-beads stability iteration scan bead defects authors drift calibration calibration-sweep geometry frame-size frame-grits frame-defaults frame-bead-grains frame-camera edge-step cylinder-rows cylinder-why cylinder-draws cylinder-draws-why cylinder-draws-edge cylinder-draws-single-material cylinder-draws-1e3 cylinder-draws-96rows coherence-sensitivity coherence-sensitivity-low-dose low-dose-lengths low-dose-reference absorbing-samples bead-absorption detector-psf upstream-distance alpha-sensitivity coarse-start probe-window probe-iterations demo-dose random-scenes random-scenes-held-out sensitivity-check holds-by-dose position-agreement diffuser-models fbp perscan field-grid fft-lengths fft-library scan-optics source-coherence paper-figures fullwidth; do "$0" "$b"; done ;;
  *) echo "usage: $0 [accuracy|accuracy-beads|stability|iteration|scan|bead|defects|authors|drift|calibration|calibration-sweep|geometry|frame-size|frame-grits|frame-defaults|frame-bead-grains|frame-camera|edge-step|cylinder-rows|cylinder-why|cylinder-draws|cylinder-draws-why|cylinder-draws-edge|cylinder-draws-single-material|cylinder-draws-1e3|cylinder-draws-96rows|coherence-sensitivity|coherence-sensitivity-low-dose|low-dose-lengths|low-dose-reference|detector-psf|upstream-distance|alpha-sensitivity|position-agreement|coarse-start|probe-window|probe-iterations|demo-dose|random-scenes|random-scenes-held-out|sensitivity-check|sensitivity-check-stability|diffuser-models|fbp|perscan|field-grid|fft-lengths|fft-library|scan-optics|source-coherence|paper-figures|fullwidth|warm-stop|all]" >&2; exit 2 ;;
esac
