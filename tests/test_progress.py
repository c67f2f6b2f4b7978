"""Progress of long stages (issue #28): per item, with the time left, quiet into a file."""

import io
import threading

from pwf_dask.pipeline.cluster import Runner
from pwf_dask.progress import Progress, format_seconds


def test_format_seconds():
    assert format_seconds(5) == "0:05" and format_seconds(125) == "2:05" and format_seconds(3725) == "1:02:05"


def test_into_a_file_one_line_per_step_and_the_time_left():
    """Not a terminal: a line at 0 %, at each 10 % crossed and none between; the rate counts
    only what this run did (a resumed run starts at 4 of 20)."""
    done = [4]
    stream = io.StringIO()
    with Progress("retrieve", 20, lambda: done[0], unit="projections", stream=stream, interval_s=0.01) as bar:
        assert bar.line(4, 10.0).endswith("0:10 elapsed")  # nothing done in this run: no estimate
        assert bar.line(8, 10.0).endswith("0:30 left")  # 4 in 10 s, 12 to go
        for n in range(5, 21):
            done[0] = n
            threading.Event().wait(0.03)
    lines = stream.getvalue().splitlines()
    assert lines[0].startswith("retrieve: 4/20 projections ( 20 %)")
    assert lines[-1].startswith("retrieve: 20/20 projections (100 %)")
    steps = [int(line.split("(")[1].split("%")[0]) // 10 for line in lines]
    assert steps == sorted(set(steps)) and "\r" not in stream.getvalue()


def test_runner_map_reports_each_item_as_it_lands(capsys):
    """The count is what has landed, finer than a task: here each task lands two items."""
    landed = []

    def task(i):
        landed.extend([i, i])
        return i * i

    with Runner("threads", workers=2) as runner:
        out = runner.map(task, list(range(6)), label="work", unit="items", count=lambda: len(landed), total=12)
    assert out == [i * i for i in range(6)]
    err = capsys.readouterr().err.splitlines()
    assert err[0].startswith("work: 0/12 items") and err[-1].startswith("work: 12/12 items (100 %)")


def test_quiet_and_verbose_flags_set_what_the_library_says(tmp_path, capsys):
    """Issue #30: the library logs (``pwf_dask`` loggers) and the CLI configures it: `-q`
    leaves warnings and errors only, no progress lines; the default shows both."""
    from pwf_dask import cli

    scan = tmp_path / "s.zarr"
    assert cli.main(["-q", "simulate", str(scan), "--preset", "demo", "--shape", "32", "32", "--angles", "2"]) == 0
    assert capsys.readouterr().err == ""
    assert cli.main(["-q", "retrieve", str(scan), str(tmp_path / "r.zarr"), "--max-iter", "5"]) == 0
    assert capsys.readouterr().err == ""
    assert cli.main(["retrieve", str(scan), str(tmp_path / "r2.zarr"), "--max-iter", "5"]) == 0
    err = capsys.readouterr().err
    assert "retrieve: 4 of 4 projections to compute" in err and "projections (100 %)" in err
