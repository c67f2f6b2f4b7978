"""`pwf-dask bench` from the command line: files written, ratios measured in the same run."""

import csv

import pytest

from pwf_dask import cli


def test_bench_iteration_quick_writes_its_files(tmp_path, capsys):
    assert cli.main(["bench", "iteration", "--quick", "--out", str(tmp_path)]) == 0
    rows = list(csv.DictReader(open(tmp_path / "bench_iteration_cpu.csv")))
    assert {r["variant"].split(",")[0] for r in rows} == {"L1>0", "L1=0"}
    for r in rows:
        # a ratio, not a timing: both sides measured in the same run
        assert float(r["ratio"]) == pytest.approx(float(r["iteration_ms"]) / float(r["fft_ms"]), rel=1e-6)
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
    assert (tmp_path / "bench_iteration_gpu.md").exists()
