"""`pwf-dask bench` from the command line: files written, ratios measured in the same run."""

import csv

import numpy as np
import pytest

from pwf_dask import cli


def test_bench_iteration_quick_writes_its_files(tmp_path, capsys):
    assert cli.main(["bench", "iteration", "--quick", "--out", str(tmp_path)]) == 0
    rows = list(csv.DictReader(open(tmp_path / "bench_iteration_cpu.csv")))
    assert {r["variant"].split(",")[0] for r in rows} == {"L1>0", "L1=0"}
    for r in rows:
        # a ratio, not a timing: both sides measured in the same run
        assert float(r["ratio"]) == pytest.approx(float(r["iteration_ms"]) / float(r["fft_ms"]), rel=1e-6)
        # both yardsticks of issue #31: the library in use and scipy's pocketfft
        assert r["fft_library"] in ("mkl", "scipy")
        assert float(r["scipy_ratio"]) == pytest.approx(float(r["iteration_ms"]) / float(r["scipy_fft_ms"]), rel=1e-6)
        # the line-by-line port of Algorithms S1/S2, timed in the same rounds
        assert float(r["literal_ratio"]) == pytest.approx(float(r["literal_ms"]) / float(r["fft_ms"]), rel=1e-6)
    assert (tmp_path / "bench_iteration_cpu.png").stat().st_size > 1000
    assert "results written" in capsys.readouterr().out


def test_bench_unknown_name_is_refused():
    with pytest.raises(SystemExit):
        cli.main(["bench", "nonsense"])


def test_bench_stability_axes_unknown_or_without_a_map_exit_with_one_line(tmp_path, capsys):
    assert cli.main(["bench", "stability", "--axes", "wind", "--out", str(tmp_path)]) == 2
    assert cli.main(["bench", "stability", "--axes", "dose", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "unknown stability axis 'wind'" in err[0] and "does not exist" in err[1]


@pytest.mark.gpu
def test_bench_iteration_on_cupy_names_the_device(cupy, tmp_path):
    """The GPU branch of the benchmark (device name, stream sync, its own file)."""
    assert cli.main(["bench", "iteration", "--quick", "--device", "gpu", "--out", str(tmp_path)]) == 0
    rows = list(csv.DictReader(open(tmp_path / "bench_iteration_gpu.csv")))
    assert len(rows) == 2 and all(float(r["ratio"]) > 0 for r in rows)
    assert rows[0]["device"] == cupy.cuda.runtime.getDeviceProperties(0)["name"].decode()
    assert all(float(r["cuda_kernels_ms"]) > 0 for r in rows)  # the CUDA kernels timed beside
    table = (tmp_path / "bench_iteration_gpu.md").read_text()
    assert "with CUDA kernels (ms) | kernels' gain" in table and "scipy" not in table


@pytest.mark.gpu
def test_gpu_checks_tomo_part_reconstructs_its_discs_on_both_sides(cupy):
    """``gpu_checks OUT tomo``: the device's FBPs (the backprojector, its kernel, gridrec by the
    package's own NUFFT) and the host's gridrec all give the exact disc sinograms' slices back
    (a wrong angle or axis convention reads ~100 % off) and agree; each slice's background fit
    is timed on both sides."""
    from benchmarks import gpu_checks
    from pwf_dask.tomo import gridrec

    if not gridrec.available():
        pytest.skip("finufft is not installed")
    rows = gpu_checks.tomo_rows(cupy, rows=2, angles=121, width=128)
    host, device, kernel, gridded = rows[:4]
    assert (host["where"], host["fbp"], device["where"], device["fbp"]) == ("host", "gridrec", "device", "backproject")
    assert (kernel["fbp"], kernel["cuda_kernel"], device["cuda_kernel"]) == ("backproject", True, False)
    assert (gridded["where"], gridded["fbp"]) == ("device", "gridrec")
    for row in (host, device, kernel, gridded):
        assert row["relative_rms_error_to_truth"] < 0.15
    stages = [(r["where"], r["stage"]) for r in rows if "stage" in r]
    assert stages == [("device", "background"), ("host", "background")]
    agreement = next(row for row in rows if "device_backproject_vs_host_gridrec_relative_rms" in row)
    assert agreement["device_backproject_vs_host_gridrec_relative_rms"] < 0.08
    assert agreement["cuda_kernel_vs_backproject_max_relative"] < 1e-4  # the emulator's: C++
    assert agreement["device_gridrec_vs_host_gridrec_max_relative"] < 5e-4  # two NUFFTs at 1e-4


def test_bench_accuracy_writes_one_row_per_run_with_errors_against_the_truth(tmp_path, capsys):
    """One cheap run (GF on the demo scene) through the whole accuracy bench; a preset without
    a scene exits with one line and writes nothing."""
    from benchmarks import speed_accuracy

    rows = speed_accuracy.run_accuracy_benchmark(tmp_path / "out", tmp_path / "work", runs=[("GF K=1", "gf", 1, {})])
    assert [r["label"] for r in rows] == ["GF K=1"]
    # GF has no attenuation (its beta is zero): the bead's beta error is -1 exactly
    assert rows[0]["bead_beta_err"] == pytest.approx(-1.0)
    assert rows[0]["wall_s"] >= rows[0]["retrieval_s"] > 0 and rows[0]["fsc_truth_delta_um"] > 0
    table = (tmp_path / "out" / "speed_accuracy.md").read_text()
    assert "--preset demo" in table and "| GF K=1* | 1 |" in table
    assert (tmp_path / "out" / "speed_accuracy.png").stat().st_size > 1000
    capsys.readouterr()
    assert cli.main(["bench", "accuracy", "--preset", "paper", "--out", str(tmp_path / "none")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "no scene for preset 'paper'" in err
    assert not (tmp_path / "none").exists()


def test_bench_fbp_quick_times_both_fbps_side_by_side(tmp_path):
    assert cli.main(["bench", "fbp", "--quick", "--out", str(tmp_path)]) == 0
    (row,) = list(csv.DictReader(open(tmp_path / "bench_fbp_cpu.csv")))
    assert float(row["speedup"]) == pytest.approx(float(row["backproject_s"]) / float(row["gridrec_s"]), rel=1e-6)
    assert "with two threads" in (tmp_path / "bench_fbp_cpu.md").read_text()


@pytest.mark.slow
def test_bench_perscan_quick_measures_each_part_against_one_retrieval(tmp_path):
    """Issue #31's per-scan work: calibration, diffuser fit and model build, each as a share of one
    projection's retrieval timed in the same run."""
    assert cli.main(["bench", "perscan", "--quick", "--out", str(tmp_path)]) == 0
    (row,) = list(csv.DictReader(open(tmp_path / "bench_per_scan_cpu.csv")))
    for part in ("calibration", "diffuser_fit", "model_build"):
        share = 100 * float(row[f"{part}_s"]) / float(row["retrieval_s"])
        assert float(row[f"{part}_pct"]) == pytest.approx(share, rel=1e-6)
    assert int(row["iterations"]) > 0


def test_random_scenes_draw_every_parameter_inside_its_stated_range():
    """The random-geometry study (benchmarks/random_scenes.py) is only as wide as its draws: 400
    set-ups stay inside the ranges its report states, span most of each, and an upstream
    diffuser always comes with L1 = 0."""
    import numpy as np

    from benchmarks.random_scenes import DRAW_SEED, draw_setup

    setups = [draw_setup(np.random.default_rng(DRAW_SEED + i)) for i in range(400)]
    ranges = {
        "energy_eV": (8e3, 30e3),
        "pixel_size_m": (0.3e-6, 3e-6),
        "diffuser_detector_distance_m": (5e-3, 200e-3),
        "coherence_length_x_m": (1e-6, 8e-6),
        "photons": (1e2, 1e6),
        "diffuser_radius_median_m": (0.8e-6, 6e-6),
    }
    for name, (lo, hi) in ranges.items():
        values = np.array([getattr(s, name) for s in setups])
        assert lo <= values.min() and values.max() <= hi, name
        assert np.log(values.max() / values.min()) > 0.8 * np.log(hi / lo), name
    assert all(64 <= n <= 259 for s in setups for n in s.shape)
    upstream = [s for s in setups if s.diffuser_upstream_m > 0]
    assert 60 < len(upstream) < 140 and all(s.sample_diffuser_distance_m == 0 for s in upstream)
    assert {s.diffuser_grain_shape for s in setups} == {"spheres", "faceted", "mixed"}


def test_sensitivity_check_counts_each_set_apart_and_leaves_refusals_out():
    """The warning's confusion table (benchmarks/sensitivity_check.py) counts per set of
    scenes, flagged holds apart from flagged failures, and a refused calibration in neither."""
    from benchmarks.sensitivity_check import summary_rows

    def row(scene, error, flagged, shift=0.1, refused=""):
        return {
            "scene": scene,
            "refused": refused,
            "phase_error": error,
            "phase_gain": 1 - error,
            "holds": error < 0.25,
            "flagged": flagged,
            "speckle_shift_over_grain": shift,
        }

    rows = [row(0, 0.1, False, 0.05), row(1, 0.9, True), row(2, 0.5, False), row(3, 0.9, False, refused="no")]
    rows += [row(130, 0.2, True, 0.02), row(131, 0.1, False, 0.3)]
    first, held_out = summary_rows(rows)
    assert (first["retrieved"], first["refused"], first["holds"], first["fails"]) == (3, 1, 1, 2)
    assert (first["flagged_holds"], first["flagged_fails"], first["nearest_hold"]) == (0, 1, 0.05)
    assert (first["gain_flagged"], first["gain_unflagged_fails"]) == ("0.10", "0.50")
    assert (
        held_out["set"].endswith("(held out)") and held_out["flagged_holds"] == 1 and held_out["nearest_hold"] == 0.02
    )


def test_a_held_out_set_runs_beside_the_kept_rows_and_is_counted_apart(tmp_path, monkeypatch):
    """``random_scenes --first N`` names its files by its scenes, and ``sensitivity_check
    --add-scenes`` (``run_and_report`` with ``kept`` rows) runs only the scenes the kept rows
    lack, reports both, and counts session 102's held-out scenes 160-239 as a set of their own."""
    import benchmarks.random_scenes as random_scenes
    from benchmarks.reporting import read_rows_csv
    from benchmarks.sensitivity_check import summary_rows

    assert random_scenes.results_name(0, 80) == "random_scenes"
    assert random_scenes.results_name(160, 80) == "random_scenes_160-239"

    def row(scene, error):
        return {"scene": scene, "method": "pwf", "refused": "", "phase_error": error, "phase_gain": 1 - error}

    ran = []
    monkeypatch.setattr(random_scenes, "scene_row", lambda i, methods: ran.append(i) or [row(i, 0.1 * (i % 3))])
    monkeypatch.setattr(random_scenes, "device_name", lambda xp: "test device")
    reported = []
    kept = [row(0, 0.2), row(1, 0.4)]
    rows = random_scenes.run_and_report(
        range(3),
        ("pwf",),
        tmp_path,
        "check",
        lambda rows, out, device: reported.append(len(rows)),
        lambda *a: None,
        kept,
    )
    assert ran == [2] and [r["scene"] for r in rows] == [0, 1, 2] and reported == [3]
    assert [r["scene"] for r in read_rows_csv(tmp_path, "check.csv")] == [0, 1, 2]

    def checked(scene, error, flagged):
        return row(scene, error) | {"holds": error < 0.25, "flagged": flagged, "speckle_shift_over_grain": 0.1}

    sets = summary_rows([checked(150, 0.1, False), checked(170, 0.1, True), checked(239, 0.9, False)])
    assert [s["set"] for s in sets] == ["120-159 (held out)", "160-239 (held out, session 102)"]
    assert (sets[1]["holds"], sets[1]["flagged_holds"], sets[1]["fails"]) == (1, 1, 1)


def test_stability_points_carry_the_check_only_where_pwf_measured_it():
    """The stability map's rows carry PWF's own check (benchmarks/stability.py), NaN and
    unflagged for a method that does not measure it, and the check's table of the map's points
    (benchmarks/sensitivity_check.py) counts flagged failures apart from flagged holds."""
    import math

    from benchmarks.sensitivity_check import stability_lines
    from benchmarks.stability import sensitivity_columns

    measured = sensitivity_columns(
        {
            "speckle_shift_over_grain": 0.01,
            "speckle_visibility": 0.2,
            "sample_misfit": 1.6,
            "phase_sensitivity": 2e-5,
            "sensitivity_warning": "faint",
        }
    )
    assert measured == {
        "speckle_shift_over_grain": 0.01,
        "speckle_visibility_measured": 0.2,
        "sample_misfit": 1.6,
        "phase_sensitivity": 2e-5,
        "flagged": True,
    }
    blank = sensitivity_columns({})
    assert math.isnan(blank["speckle_shift_over_grain"]) and blank["flagged"] is False

    def row(value, error, flagged):
        check = {"speckle_shift_over_grain": 0.1, "speckle_visibility": 0.3, "sensitivity_warning": flagged}
        point = {"axis": "dose", "value": value, "phase_error": error, "phase_gain": 1 - error, "holds": error < 0.25}
        return point | sensitivity_columns(check)

    lines = stability_lines([row(1e2, 0.6, "faint"), row(1e3, 0.4, ""), row(1e4, 0.1, ""), row(1e5, 0.1, "faint")])
    assert "2 of 4 points fail, the warning flags 1 of them and 1 holding points" in " ".join(lines)
    # the misfit's column is blank where a row did not measure it
    assert lines[-4].endswith("|  | yes |  |") and lines[-1].endswith("|  | yes | yes |")


def test_coarse_start_bins_and_interpolates_on_the_detectors_pixel_centres():
    """The coarse-to-fine start (benchmarks/coarse_start.py) is only a fair trial if its binned
    frame and the interpolation back keep the pixel centres: a plane binned 2 x 2 and
    interpolated back is the same plane (but for the outermost rows and columns, held at the
    edge), and an odd frame is trimmed to whole blocks and padded back to its shape."""
    import numpy as np

    from benchmarks.coarse_start import binned, upsampled

    y, x = np.mgrid[0:64, 0:96].astype(float)
    plane = 0.3 * y - 0.7 * x + 2.0
    b = binned(plane)
    assert b.shape == (32, 48)
    assert b[3, 5] == plane[6:8, 10:12].mean()
    back = upsampled(b, 2, plane.shape)
    assert np.allclose(back[1:-1, 1:-1], plane[1:-1, 1:-1], atol=1e-12)
    odd_plane = plane[:63, :95]
    odd = upsampled(binned(odd_plane), 2, odd_plane.shape)
    assert odd.shape == (63, 95) and np.allclose(odd[1:-2, 1:-2], odd_plane[1:-2, 1:-2], atol=1e-12)


def test_cylinder_measures_read_a_lost_rim_step_and_a_scaled_phase():
    """The cylinder sweep's measures (benchmarks/cylinder_rows.py) on a cylinder's exact
    phase: the truth itself reads gain 1 and no step; scaled by 0.9, gain 0.9; with the
    left rim's step lost (everything left of the cylinder 1.5 rad down, the inside right),
    the sample-free level difference reads -1.5 rad and the gain is counted after the
    median background level is taken off, as the sweep states."""
    import numpy as np

    from benchmarks.cylinder_rows import cylinder_measures

    x = np.arange(128) - 63.5
    chord = np.sqrt(np.clip(46.0**2 - x**2, 0, None))
    truth = np.tile(-8.0 * chord / chord.max(), (48, 1))
    exact = cylinder_measures(truth, truth)
    assert exact["gain"] == pytest.approx(1.0) and exact["left_minus_right_rad"] == 0.0
    assert exact["band_gain_spread"] == pytest.approx(0.0, abs=1e-12)
    assert cylinder_measures(0.9 * truth, truth)["gain"] == pytest.approx(0.9)
    lost = truth.copy()
    lost[:, x < -46] -= 1.5
    m = cylinder_measures(lost, truth)
    assert m["left_minus_right_rad"] == pytest.approx(-1.5)
    free = truth > -1e-3
    level = np.median(lost[free])
    inside = truth < -0.3
    assert m["gain"] == pytest.approx(np.sum((lost - level)[inside] * truth[inside]) / np.sum(truth[inside] ** 2))


def test_benchmarks_calibrate_the_lengths_a_run_calibrates():
    """Benchmarks that calibrate once for several runs (bead_contrast, cylinder_rows) pass the
    lengths :func:`retrieve_projection` would calibrate itself, and say that they exclude the
    pixel's blur as the template fit's do (before session 74 bead_contrast took the Gaussian
    alone, 10-20 % long with that blur counted twice): the same lengths and the same phase."""
    import numpy as np

    from benchmarks.stability import calibrated_lengths
    from pwf_dask.retrieval import retrieve_projection
    from pwf_dask.simulation import SpeckleSetup, simulate_projection

    setup = SpeckleSetup(shape=(64, 64))
    sim = simulate_projection(setup, seed=1)
    lengths = calibrated_lengths(sim.reference, setup)
    itself = retrieve_projection(sim.sample, sim.reference, max_iter=30, tol=0, **setup.geometry())
    given = retrieve_projection(sim.sample, sim.reference, max_iter=30, tol=0, **setup.geometry(), **lengths)
    assert lengths["coherence_includes_pixel_blur"] is False
    assert (itself.coherence_length_x_m, itself.coherence_length_y_m) == (
        lengths["coherence_length_x_m"],
        lengths["coherence_length_y_m"],
    )
    assert abs(lengths["coherence_length_x_m"] / setup.coherence_length_x_m - 1) < 0.1
    np.testing.assert_array_equal(np.asarray(given.phase), np.asarray(itself.phase))


@pytest.mark.gpu
def test_gpu_checks_warm_part_starts_the_second_frame_from_the_first(cupy):
    """``gpu_checks OUT warm`` on a small frame: frame 0 from zero (calibrating, then with its
    lengths given: the same run), frame 1 from frame 0 and from zero under either stop rule;
    the warm starts need fewer iterations than the cold ones and read the same phase."""
    from benchmarks import gpu_checks

    rows = gpu_checks.warm_rows(cupy, shape=(64, 96))
    assert [r["run"].split(" (")[0] for r in rows] == [
        "frame 0 from zero, calibrating",
        "frame 0 from zero",
        "frame 1 from frame 0",
        "frame 1 from frame 0",
        "frame 1 from zero",
        "frame 1 from zero",
    ]
    assert [r["stationary_terms"] for r in rows[2:]] == ["j-or-data", "j", "j-or-data", "j"]
    assert rows[0]["iterations"] == rows[1]["iterations"]
    warm, cold = rows[3], rows[5]  # the default rule
    assert warm["iterations"] < cold["iterations"]
    assert abs(warm["phase_gain"] - cold["phase_gain"]) < 0.05


def test_cylinder_draws_reads_each_position_and_their_mean_against_the_truth():
    """The draw benchmark's measure (benchmarks/cylinder_draws.py) on true tomograms: the
    phantom's own delta and beta read 0 at every position (the cylinder's core to its voxels'
    averaging, the largest bead's exactly); scaled by 0.9 at position 0 and 1.1 at position 1
    they read -10 % / +10 % each and 0 in the positions' mean, the mean of the two tomograms."""
    import numpy as np
    import xarray as xr

    from benchmarks.cylinder_draws import core_errors, dose, spread
    from pwf_dask.simulation import phantom_to_json, refractive_index_volume, scan_phantom

    p, e = 1e-6, 10e3
    ph = scan_phantom((24, 64), p, seed=0)
    y = (np.arange(24) - 11.5) * p
    u = (np.arange(64) - 31.5) * p
    d, b = refractive_index_volume(ph, y, u, u, e)
    scale = np.array([0.9, 1.1])[:, None, None, None]
    ds = xr.Dataset(
        {"delta": (("position", "y", "v", "u"), scale * d), "beta": (("position", "y", "v", "u"), scale * b)},
        coords={"y": y, "v": u, "u": u},
        attrs={"simulation_phantom": phantom_to_json(ph), "pixel_size_m": p, "energy_eV": e},
    )
    errs = core_errors(ds)
    exact = core_errors(ds.isel(position=[0]) / 0.9)
    assert abs(exact["delta_err_p0"]) < 0.02 and abs(exact["beta_err_p0"]) < 0.02
    truth = 1 + exact["delta_err_p0"]
    assert errs["delta_err_p0"] == pytest.approx(0.9 * truth - 1, abs=1e-12)
    assert errs["delta_err_p1"] == pytest.approx(1.1 * truth - 1, abs=1e-12)
    assert errs["delta_err_mean"] == pytest.approx(truth - 1, abs=1e-12)
    # the largest bead's core is glass through and through: exact, then scaled like the cylinder
    assert exact["bead_delta_err_p0"] == pytest.approx(0.0, abs=1e-9)
    assert exact["bead_beta_err_p0"] == pytest.approx(0.0, abs=1e-9)
    assert errs["bead_delta_err_p0"] == pytest.approx(-0.1) and errs["bead_beta_err_p1"] == pytest.approx(0.1)
    assert errs["bead_delta_err_mean"] == pytest.approx(0.0, abs=1e-9)
    assert spread([-0.1, 0.1]) == "+0.0 | 10.0 | -10.0 to +10.0"
    assert [dose(p) for p in (1e3, 1e4, 2.5e5)] == ["1e3", "1e4", "2.5e5"]  # the files' names


def test_cylinder_edge_softens_the_outline_and_keeps_the_body_and_reads_its_core():
    """The --edge benchmark's body and measure (benchmarks/cylinder_draws.py): sigma 0 and depth
    1 give the phantom's psi itself; a softened outline keeps each row's integral of phase and
    attenuation (the same body, blunter) while its steepest step falls several-fold; the core
    reads a profile scaled by 0.8 above any background offset as 0.8."""
    import numpy as np

    from benchmarks.cylinder_draws import core_gain, softened

    x = np.arange(256) - 127.5
    profile = -8 * np.sqrt(np.clip(1 - (x / 60) ** 2, 0, None))
    psi = np.tile(0.01 * profile + 1j * profile, (8, 1))
    assert np.array_equal(softened(psi, 0.0), psi)
    soft = softened(psi, 6.0)
    np.testing.assert_allclose(soft.imag.sum(axis=1), psi.imag.sum(axis=1), rtol=1e-9)
    np.testing.assert_allclose(soft.real.sum(axis=1), psi.real.sum(axis=1), rtol=1e-9)
    steep = np.abs(np.diff(psi.imag, axis=1)).max()
    assert np.abs(np.diff(soft.imag, axis=1)).max() < steep / 3
    np.testing.assert_allclose(softened(psi, 0.0, 0.25), 0.25 * psi)
    truth = psi.imag
    assert core_gain(0.8 * truth + 0.3, truth) == pytest.approx(0.8)
    assert core_gain(truth, truth) == pytest.approx(1.0)


def test_a_benchmarks_header_names_the_command_that_made_it_without_its_output_folder():
    """The results' headers (benchmarks/reporting.command_line): the arguments as given, a
    grain with a space quoted so the line runs as printed, ``--out DIR`` and ``--report-only`` left out."""
    import shlex

    from benchmarks.reporting import command_line

    argv = ["--photons", "1e3", "--out", "/tmp/x", "--grains", "P3000", "1.2 um"]
    line = command_line("benchmarks.cylinder_draws", argv)
    assert line == "python -m benchmarks.cylinder_draws --photons 1e3 --grains P3000 '1.2 um'"
    assert shlex.split(line)[3:] == ["--photons", "1e3", "--grains", "P3000", "1.2 um"]
    assert command_line("benchmarks.cylinder_rows", []) == "python -m benchmarks.cylinder_rows"
    # a report written again from its CSV names the run that made the numbers
    rewritten = command_line("benchmarks.detector_psf", ["--report-only", "--out", "x"])
    assert rewritten == "python -m benchmarks.detector_psf"


def test_position_agreement_reads_equal_phases_as_agreeing_and_a_halved_one_by_its_ratio():
    """Two positions' phases (benchmarks/position_agreement.py): equal ones disagree by 0 with
    rms ratio 1; one half the other disagrees by rms(phi / 2) / rms(3 phi / 4) = 2/3, ratio 1/2,
    over the sample the mean shows (a tenth of its largest |phase|), whatever the background."""
    import numpy as np

    from benchmarks.position_agreement import agreement

    yy, xx = np.mgrid[-32:32, -32:32]
    phase = -np.clip(1 - (xx**2 + yy**2) / 20.0**2, 0, None) * 5.0
    same = agreement(phase, phase.copy())
    assert same == {"disagreement": 0.0, "rms_ratio": 1.0}
    half = agreement(phase, 0.5 * phase)
    assert half["disagreement"] == pytest.approx(2 / 3) and half["rms_ratio"] == pytest.approx(0.5)


def test_diffuser_models_report_scores_each_rule_and_names_each_scenes_sensitivity(tmp_path):
    """benchmarks/diffuser_models.py's table: hold counts per choice (errors under 0.25), the
    probe's switches counted, and the listed scenes (models apart by over 0.05, or switched)
    with the reference's phase sensitivity S that set alpha."""
    from benchmarks.diffuser_models import write_report

    def row(scene, auto, probe, zp, sm, s, ratio):
        geometry = dict(energy_keV=20.0, pixel_um=1.0, l1_mm=0.0, upstream_mm=10.0, l2_mm=100.0)
        return dict(
            scene=scene, auto=auto, probe=probe, refused="", zp_error=zp, sm_error=sm, zp_gain=1.0,
            sm_gain=1.0, zp_residual=1.0, sm_residual=1.0, zp_s=10.0, probe_s=2.0, probe_zp_residual=1.0,
            probe_sm_residual=ratio, grain_radius_um=3.2, visibility=0.1, phase_sensitivity=s, **geometry,
        )  # fmt: skip

    rows = [
        row(0, "zero-phase", "zero-phase", 0.10, 0.50, 8.9e-5, 0.9),
        row(1, "zero-phase", "single-material", 0.60, 0.20, 2.0e-2, 0.3),
        row(2, "single-material", "single-material", 0.10, 0.10, 5.0e-3, float("nan")),
    ]
    # the alpha rule's model probe: scene 0's fit kept the default, scene 2's the rule's alpha
    rows[0].update(zp_alpha="0.1+0.004j", sm_alpha="0.1+0.05j", sm_model_ratio=1.2)
    rows[2].update(zp_alpha="0.1+0.03j", sm_alpha="0.1+0.03j", sm_model_ratio=0.9)
    write_report(rows, tmp_path, "test device", "diffuser_models")
    text = (tmp_path / "diffuser_models.md").read_text()
    assert "| zero phase everywhere | 2 |" in text and "| single material everywhere | 2 |" in text
    assert "the probe (20 iterations each) | 3 | 0.100 | 0.133 | 1 |" in text
    listed = [line for line in text.splitlines() if line.startswith("| 0 |") or line.startswith("| 1 |")]
    assert len(listed) == 2 and "| 8.9e-05 |" in listed[0] and "| 2.0e-02 |" in listed[1]
    assert not any(line.startswith("| 2 |") for line in text.splitlines())
    assert 'alpha="sensitivity"' in text
    assert "model probe ran in 2 scenes" in text and "in 1 the fit misfit the sample more" in text
    assert "(default alpha)" in listed[0] and "(default alpha)" not in listed[1]
    assert "had taken the fit by the grains' absorption in none of them" in text
    rows[2].update(sm_alpha="0.1+0.05j", sm_model_ratio=1.1)  # "auto"'s fit, given up since session 101
    write_report(rows, tmp_path, "test device", "diffuser_models")
    text = (tmp_path / "diffuser_models.md").read_text()
    assert 'In 1 of them (scene 2) `"auto"` had taken the fit' in text and "in 2 the fit misfit" in text


def test_upstream_distance_report_puts_each_selector_where_its_quantity_is_least(tmp_path):
    """benchmarks/upstream_distance.py's summary: per grit and true distance, the mean phase
    error at each assumed distance over the seeds, zero phase's, and per seed the assumed
    distance where the reference fit's residual, PWF's residual and the phase error are least."""
    import math

    from benchmarks.upstream_distance import write_markdown

    def row(seed, assumed, fit, residual, error, model="default"):
        return dict(
            grit="P3000", true_mm=50.0, seed=seed, assumed_mm=assumed, model=model,
            reference_fit_residual=fit, residual_pct=residual, phase_gain=0.9, phase_error=error,
            diffuser_model="zero-phase" if model == "zero-phase" else "single-material", iterations=100, seconds=1.0,
        )  # fmt: skip

    rows = []
    for seed, shift in ((1, 0.0), (2, 0.02)):
        rows += [
            row(seed, 0.0, 0.010, 1.1, 0.10 + shift),
            row(seed, 50.0, 0.012 - shift, 1.3, 0.06 + shift),
            row(seed, math.nan, math.nan, 1.0, 0.08, model="zero-phase"),
        ]
    write_markdown(rows, str(tmp_path / "u.md"), "python -m benchmarks.upstream_distance")
    text = (tmp_path / "u.md").read_text()
    assert "| phase error, assumed: 0 mm | 50 mm | zero phase |" in text
    # errors 0.110 / 0.070 mean over the seeds; the fit's residual least at 0 then at 50 mm
    assert "| P3000 | 50 | 0.110 | 0.070 | 0.080 | 0 / 50 | 0 / 0 | 50 / 50 |" in text
    assert "| P3000 | 50 | 1 | zero-phase |  |  | 1.000 |" in text


def test_source_coherence_report_means_each_scene_and_model_over_the_seeds(tmp_path):
    """benchmarks/source_coherence.py's summary: per scene and coherence model, the means over
    the seeds, and how many runs were warned."""
    from benchmarks.source_coherence import write_markdown

    def row(model, seed, error, misfit, warned):
        return dict(
            scene="50 mm upstream, given", model=model, method="pwf", seed=seed,
            shift_sigma_px=1.08 if model == "source" else 0.0,
            length_x_err=-0.02, length_y_err=0.01, phase_gain=0.9, phase_error=error, attenuation_error=0.2,
            residual_pct=2.0, sample_misfit=misfit, warned=warned, diffuser_model="single-material",
            iterations=100, converged=True, simulate_s=1.0, seconds=2.0,
        )  # fmt: skip

    rows = [row("detector", 1, 0.10, 1.0, False), row("source", 1, 0.14, 1.6, True)]
    rows += [row("detector", 2, 0.12, 1.1, False), row("source", 2, 0.16, 1.2, False)]
    write_markdown(rows, str(tmp_path / "s.md"), "python -m benchmarks.source_coherence")
    text = (tmp_path / "s.md").read_text()
    head = "| 50 mm upstream, given | PWF |"
    assert f"{head} detector | 0.00 | -2.0% / +1.0% | 0.900 | 0.110 | 0.200 | 2.000 | 1.05 | 0/2 |" in text
    assert f"{head} source | 1.08 | -2.0% / +1.0% | 0.900 | 0.150 | 0.200 | 2.000 | 1.40 | 1/2 |" in text


def test_source_coherence_random_report_pairs_each_scene_under_both_models(tmp_path):
    """benchmarks/source_coherence.py --random: per scene its two models side by side, sorted by
    the shift, and the holds and warnings counted over the scenes run under both."""
    from benchmarks.source_coherence import write_random_markdown

    def row(scene, model, shift, error, warned):
        return dict(
            scene=scene, geometry="L1 6.2 mm, L2 14.1 mm", model=model, shift_sigma_px=shift, phase_error=error,
            holds=error < 0.2, sample_misfit=1.0, warned=warned, seconds=1.0,
        )  # fmt: skip

    rows = [row(3, "detector", 0.5, 0.1, False), row(3, "source", 0.5, 0.25, True)]
    rows += [row(9, "detector", 1.7, 0.15, False), row(9, "source", 1.7, 0.12, False)]
    write_random_markdown(rows, str(tmp_path / "r.md"), "python -m benchmarks.source_coherence --random")
    text = (tmp_path / "r.md").read_text()
    assert "Holds: detector 2 of 2, source 1; warned: detector 0, source 1." in text
    assert text.index("| 9 |") < text.index("| 3 |")  # the larger shift first
    assert "| 3 | L1 6.2 mm, L2 14.1 mm | 0.50 | 0.100 / 0.250 | yes / no | 1.00 / 1.00 | no / yes |" in text


def test_field_grid_random_report_splits_the_pairs_by_what_the_alpha_rule_did():
    """benchmarks/field_grid.py's random scenes: only the scenes that ran on both grids are
    paired, each group of the alpha rule's outcome counts its holding scenes and the detector
    grid's wins and losses beyond 0.01, and a capped run is marked."""
    from benchmarks.field_grid import alpha_rule_outcome, random_lines

    def row(scene, where, error, rule, converged=True, grid=1.5):
        return dict(
            scene=scene, shape="64x80", sample_field_grid=where, field_grid=grid, alpha="0.1+0.01j",
            alpha_rule=rule, phase_sensitivity=1e-3, diffuser_model="zero-phase", phase_error=error,
            phase_gain=0.9, iterations=100 if converged else 2000, converged=converged,
            seconds=1.0 if converged else 4.0,
        )  # fmt: skip

    rows = [
        row(1, "field", 0.10, "lowered"),
        row(1, "detector", 0.30, "lowered", converged=False),
        row(2, "field", 0.20, "lowered"),
        row(2, "detector", 0.15, "lowered"),
        row(3, "field", 0.05, "not lowered", grid=1),  # one grid only: not paired
    ]
    text = "\n".join(random_lines(rows))
    assert "2 of 3 took a finer field grid" in text
    # errors 0.10 / 0.20 on the field grid, 0.30 / 0.15 on the detector grid: one better, one worse
    assert "| lowered | 2 | 2 / 1 | 0.150 / 0.225 | 1 / 1 | 100 / 1050 | 2.50 |" in text
    pair = "| 1 | 64x80 | 0.001 | lowered | 1.5x | zero-phase | 0.100 / 0.300 | 0.900 / 0.900 | 100 / 2000 (cap) |"
    assert pair in text
    assert "not lowered" not in text
    assert alpha_rule_outcome({"alpha": "0.1+0.05j"}) == "not lowered"
    assert alpha_rule_outcome({"alpha": "0.1+0.01j"}) == "lowered"
    assert alpha_rule_outcome({"alpha": "0.1+0.05j", "alpha_rule_kept_default": True}) == "kept default"


def test_coherence_sensitivity_reports_another_dose_under_its_own_name(tmp_path):
    """``coherence_sensitivity --photons N`` (session 102's low-dose rows) names its files by the
    dose, keeps the committed name at the default 1e4, and reads per 10 % of length error the
    largest gain change and the phase errors (true lengths, worst in the band, calibrated)."""
    from benchmarks.coherence_sensitivity import results_name, sensitivity, write_markdown

    assert results_name(1e4) == "coherence_sensitivity"
    assert results_name(100.0) == "coherence_sensitivity_100ph"

    def run(scale, gain, error, calibrated=False):
        return {
            "scene": "P3000",
            "scale": scale,
            "scale_y": scale,
            "calibrated": calibrated,
            "phase_gain": gain,
            "phase_gain_origin": gain - 0.05,
            "phase_error": error,
            "bead_contrast_error": 0.01,
            "field_upsample": 1.5,
            "diffuser_model": "zero-phase",
            "iterations": 100,
            "seconds": 1.0,
        }

    rows = [
        run(0.7, 2.0, 0.9),
        run(0.9, 1.2, 0.33),
        run(1.0, 1.1, 0.23),
        run(1.1, 1.15, 0.24),
        run(0.97, 1.1, 0.25, True),
    ]
    s = sensitivity(rows)
    assert s["gain_true"] == 1.1 and abs(s["worst_per_10pct"] - 0.1) < 1e-9  # 0.7 lies outside the band
    write_markdown(rows, str(tmp_path / "x.md"), photons=100.0)
    text = (tmp_path / "x.md").read_text()
    assert "--photons 100`" in text and "100 ph/px" in text
    assert "| 0.230, 0.330, 0.250 |" in text


def test_low_dose_lengths_counts_gains_and_losses_per_factor_and_dose_band(tmp_path):
    """The low-dose lengths study (benchmarks/low_dose_lengths.py) counts, per factor and dose
    band, the scenes that hold at the committed calibrated lengths and scaled, and those gained,
    lost, better and worse."""
    from benchmarks.low_dose_lengths import write_report

    def row(scene, photons, factor, base, new):
        return {
            "scene": scene,
            "photons": photons,
            "factor": factor,
            "phase_error": new,
            "phase_gain": 1.0,
            "iterations": 10,
            "base_error": base,
            "base_gain": 1.0,
        }

    rows = [row(0, 100, 1.1, 0.30, 0.20), row(1, 300, 1.1, 0.20, 0.30), row(2, 900, 1.1, 0.10, 0.11)]
    write_report(rows, str(tmp_path), "test device", "python -m benchmarks.low_dose_lengths")
    text = (tmp_path / "low_dose_lengths.md").read_text()
    assert "| 1.1 | under 500 | 2 | 1 -> 1 | 1 / 1 | 1 / 1 | 0.250 -> 0.250 |" in text
    assert "| 1.1 | 500 and over | 1 | 1 -> 1 | 0 / 0 | 0 / 0 | 0.100 -> 0.110 |" in text
    assert "| 1.1 | all | 3 | 2 -> 2 | 1 / 1 | 1 / 1 |" in text and "committed row" in text
    fresh = "low_dose_lengths_fresh"
    write_report(rows, str(tmp_path), "test device", "python -m benchmarks.low_dose_lengths --fresh 240 60", fresh)
    assert "new random geometries" in (tmp_path / f"{fresh}.md").read_text()
    write_report(
        rows, str(tmp_path), "test device", "python -m benchmarks.low_dose_lengths --scale im-alpha", "low_dose_alpha"
    )
    text = (tmp_path / "low_dose_alpha.md").read_text()
    assert text.startswith("# Im(alpha) raised") and "committed row" in text


def test_low_dose_reference_reports_each_factor_against_the_runs_own_factor_one(tmp_path):
    """With the reference at a higher dose (``--reference-dose``) the report also sets each
    factor against the factor 1 of the same run, so what the long lengths add on top of the
    cleaner reference reads apart from what the reference did."""
    from benchmarks.low_dose_lengths import against_factor_one, write_report

    def row(scene, factor, base, new):
        return {"scene": scene, "photons": 100, "factor": factor, "reference_dose": 10.0, "phase_error": new}

    rows = [row(0, 1.0, 0.30, 0.20), row(0, 1.1, 0.30, 0.27), row(1, 1.0, 0.30, 0.30), row(1, 1.1, 0.30, 0.22)]
    for r in rows:
        r.update(phase_gain=1.0, iterations=10, base_error=0.30, base_gain=1.0)
    on_top = against_factor_one(rows)
    assert [(r["scene"], r["base_error"], r["phase_error"]) for r in on_top] == [(0, 0.20, 0.27), (1, 0.30, 0.22)]
    write_report(rows, str(tmp_path), "test device", "cmd", "low_dose_reference")
    text = (tmp_path / "low_dose_reference.md").read_text()
    assert text.startswith("# A reference at 10x the sample's dose")
    assert "| 1 | all | 2 | 0 -> 1 | 1 / 0 |" in text  # against the committed rows
    assert "| 1.1 | all | 2 | 1 -> 1 | 1 / 1 | 1 / 1 |" in text.split("this run")[1]
    ones = [r | {"nsr_floor": 1e-4} for r in rows if r["factor"] == 1.0]
    write_report(ones, str(tmp_path), "test device", "cmd", "low_dose_reference_100x_floor0.0001")
    text = (tmp_path / "low_dose_reference_100x_floor0.0001.md").read_text()
    assert text.startswith("# A reference at 10x the sample's dose, the Wiener NSR floored at 0.0001, at low dose")
    assert "diffuser_nsr_floor=0.0001" in text and "this run" not in text
    write_report([r | {"nsr_floor": "sample"} for r in ones], str(tmp_path), "test device", "cmd", "low_dose_reference")
    text = (tmp_path / "low_dose_reference.md").read_text()  # the default floor: nothing to name
    assert text.startswith("# A reference at 10x the sample's dose at low dose") and "nsr_floor" not in text
    write_report(ones, str(tmp_path), "test device", "cmd", "high_dose_reference_floor0")
    text = (tmp_path / "high_dose_reference_floor0.md").read_text()  # --min-photons: bright scenes
    assert text.startswith("# A reference at 10x the sample's dose, the Wiener NSR floored at 0.0001, at high dose")
    assert "with a high dose" in text


def test_low_dose_lengths_refuses_a_dose_band_or_floor_without_a_reference_dose(capsys):
    """``--min-photons`` and ``--nsr-floor`` ask about the reference's dose: alone they are refused."""
    from benchmarks.low_dose_lengths import main

    for option in (["--min-photons", "3e4"], ["--nsr-floor", "0"]):
        with pytest.raises(SystemExit):
            main(["--report-only", *option])
        assert "go with --reference-dose" in capsys.readouterr().err


def test_reference_at_dose_is_the_scenes_diffuser_with_noise_falling_as_the_dose_rises():
    """``--reference-dose``'s reference (benchmarks/low_dose_lengths.py) is the scene's own
    reference speckle: noise-free at an infinite dose, and at k times the scene's dose its
    photon noise's variance is 1 / (k x dose) of the mean, drawn apart from the sample's."""
    from benchmarks.low_dose_lengths import reference_at_dose
    from pwf_dask.simulation import SpeckleSetup, simulate_projection

    setup = SpeckleSetup(shape=(64, 64), photons=200.0)
    sim = simulate_projection(setup, seed=3)
    clean = reference_at_dose(setup, 3, np.inf)
    assert np.corrcoef(clean.ravel(), sim.reference.ravel())[0, 1] > 0.3  # the same speckle
    for k in (1.0, 10.0):
        noise = reference_at_dose(setup, 3, k) - clean
        assert np.var(noise) / np.mean(clean) * k * setup.photons == pytest.approx(1.0, rel=0.1)
    assert not np.array_equal(reference_at_dose(setup, 3, 1.0), sim.reference)


def test_absorbing_samples_scales_only_the_beta_and_bounds_it_by_the_most_absorbing_element():
    """The benchmark's scene at its own attenuation range is the random geometry's own, to the
    photon (the noise drawn in the same order); scaled, the phase stays and the attenuation
    spans the range asked. beta / delta bound: the rare earths' 0.197 at 10 keV; the stability
    map's 10x beads (0.10 at 10 keV) lie within it, 500x cellulose at 22 keV beyond."""
    from benchmarks.absorbing_samples import absorbing_scene, largest_beta_over_delta, physical
    from benchmarks.random_scenes import draw_scene

    setup, sim, background = draw_scene(3)
    own = float(sim.attenuation.max() - sim.attenuation.min())
    _, sample, reference, phase, attenuation, mask, factor = absorbing_scene(3, own)
    assert factor == pytest.approx(1.0)
    np.testing.assert_array_equal(sample, sim.sample)
    np.testing.assert_array_equal(reference, sim.reference)
    np.testing.assert_array_equal(mask, background)
    _, dark, _, phase2, attenuation2, _, factor2 = absorbing_scene(3, 2.0)
    assert factor2 == pytest.approx(2.0 / own) and np.ptp(attenuation2) == pytest.approx(2.0)
    np.testing.assert_allclose(phase2, phase)
    assert dark.mean() < 0.8 * sample.mean()
    assert largest_beta_over_delta(10.0) == pytest.approx(0.197, abs=0.003)
    assert physical({"energy_keV": 10.0, "beta_factor": 10.0})
    assert not physical({"energy_keV": 22.1, "beta_factor": 500.0})


def test_holds_by_dose_counts_the_sensitivity_limit_apart_from_the_dose():
    """Per decade of dose: a refused scene counts as refused, a scene below the limit by its
    clean S is kept out of 'hold above it', and a scene whose S as read and clean S fall on
    either side of the limit is listed as misread (a refused one never is)."""
    from benchmarks.holds_by_dose import dose_table, misread_scenes

    def row(scene, photons, holds, own, clean, refused=False):
        return {
            "scene": scene,
            "photons": photons,
            "refused": refused,
            "holds": holds,
            "phase_sensitivity": own,
            "phase_sensitivity_clean": clean,
        }

    rows = [
        row(1, 2e2, True, 1e-3, 1e-3),
        row(2, 2e2, False, 0.0, 4e-4),  # read as none by noise: misread
        row(3, 5e2, False, "", 1e-6, refused=True),
        row(4, 3e5, False, 1e-6, 1e-6),  # below the limit at high dose
        row(5, 3e5, True, 1e-2, 1e-2),
    ]
    table = dose_table(rows, 3e-5)
    assert table[2] == "| 1e+02-1e+03 | 3 | 1 | 1 / 1 | 1 of 2 | 1 of 2 |"
    assert table[5] == "| 1e+05-1e+06 | 2 | 0 | 1 / 1 | 1 of 1 | 1 of 2 |"
    assert misread_scenes(rows, 3e-5) == [2]


def test_a_rerun_keeps_every_other_scenes_rows_and_puts_the_new_ones_back_in_place(tmp_path):
    """``--rerun``: the rows of the scenes named are dropped (run again by run_and_report, which
    sorts the rows back by scene); re-running part of a set that was never written is refused."""
    from benchmarks.random_scenes import rows_kept_but
    from benchmarks.reporting import write_rows_csv

    rows = [{"scene": s, "method": m, "phase_error": 0.1 * s} for s in (1, 2, 3) for m in ("pwf", "umpa")]
    write_rows_csv(tmp_path, "set.csv", rows)
    kept = rows_kept_but(tmp_path, "set.csv", [2])
    assert [(r["scene"], r["method"]) for r in kept] == [(1, "pwf"), (1, "umpa"), (3, "pwf"), (3, "umpa")]
    assert rows_kept_but(tmp_path, "set.csv", []) == []
    with pytest.raises(ValueError, match="does not exist"):
        rows_kept_but(tmp_path, "other.csv", [2])


def test_scan_optics_reads_a_run_against_its_truth_and_lists_its_warnings(tmp_path, monkeypatch):
    """``benchmarks.scan_optics``: the command line run as a user would (simulate, then run with
    the scene's run options), each error against the scan's recorded truth, the report one row
    per run and the warnings ``run`` printed. A run here is the demo preset's, 3 angles."""
    from benchmarks import scan_optics

    monkeypatch.setattr(scan_optics, "ANGLES", 3)
    options = ["--preset", "demo", "--energy-eV", "12000", "--axis-offset-px", "1.5"]
    row = scan_optics.scene_row(tmp_path, "demo, told", "the demo at 12 keV", options, run_options=["--max-iter", "20"])
    assert row["scene"] == "demo, told" and row["pixel_um"] == pytest.approx(0.65)
    assert row["converged"].endswith("/3") and row["iterations_max"] <= 20
    for key in ("bead_delta_err", "cylinder_delta_err", "coherence_x_err", "centre_err_px"):
        assert np.isfinite(row[key])
    assert abs(row["coherence_x_err"]) < 0.5  # calibrated, not given: the scan records only the truth
    warned = {**row, "scene": "warned", "warnings": "the fit leaves over 1.3 times"}
    scan_optics.write_report(tmp_path, [row, warned], argv=[])
    text = (tmp_path / "scan_optics.md").read_text()
    assert "| demo, told |" in text and "- warned: the fit leaves over 1.3 times" in text
    assert len(list(csv.DictReader(open(tmp_path / "scan_optics.csv")))) == 2


def test_fft_library_report_says_what_auto_takes_beside_each_rows_speed_up(tmp_path):
    from benchmarks import fft_library

    rows = [
        {"frame": "512x512", "field_upsample": f, "grid": "560x560", "field_grid": g, "fft_workers": w}
        | {"scipy_iteration_ms": 20.0, "mkl_iteration_ms": 20.0 / s, "mkl_speedup": s, "auto": "mkl"}
        | {"psi_disagreement": 3e-7}
        for f, g, w, s in ((1.0, "560x560", 1, 1.25), (1.5, "840x840", 2, 0.96))
    ]
    fft_library.write_report(tmp_path, rows, argv=[])
    text = (tmp_path / "fft_library.md").read_text()
    assert "| 512x512 | 840x840 (1.5x) | 2 | 20.0 | 20.8 | 0.96 | 3.0e-07 | mkl |" in text
    assert "Speed-up over all rows: 0.96 to 1.25, median 1.10." in text
