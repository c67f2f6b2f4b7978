"""Progress of a long stage on stderr: items done of the total, rate and time left.

The count comes from where the results land (the reconstruction store's ``iterations`` array
for projections, ``tomo_done`` for slice blocks), so it moves as each projection is saved,
whatever the scheduler and however projections are grouped into tasks, and it counts what a
resumed run already holds. On a terminal the line is redrawn in place about once a second;
into a file or pipe it writes one line at every ``quiet_step_percent`` and at the end, so a
log of a day-long scan stays readable.
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Callable
from typing import TextIO


def format_seconds(seconds: float) -> str:
    """``h:mm:ss`` (or ``m:ss`` under an hour)."""
    s = int(round(max(seconds, 0.0)))
    h, rest = divmod(s, 3600)
    m, s = divmod(rest, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


class Progress:
    """``with Progress(label, total, count):`` reports ``count()`` (items done, including any
    done before this run) until the block ends. ``count`` is polled from a thread every
    ``interval_s``; its exceptions (a store being written) skip that poll. Without a
    ``stream`` it writes to stderr only where the ``pwf_dask`` logger shows INFO
    (:func:`pwf_dask.log.configure`; the CLI's default, off with ``-q``)."""

    def __init__(
        self,
        label: str,
        total: int,
        count: Callable[[], int],
        *,
        unit: str = "items",
        stream: TextIO | None = None,
        interval_s: float = 1.0,
        quiet_step_percent: float = 10.0,
    ):
        from pwf_dask.log import progress_enabled

        self.label, self.total, self.count, self.unit = label, int(total), count, unit
        self.enabled = stream is not None or progress_enabled()
        self.stream = stream if stream is not None else sys.stderr
        self.interval_s = interval_s
        self.quiet_step = quiet_step_percent
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._start_count = 0
        self._t0 = 0.0
        self._last_step = -1

    def line(self, done: int, elapsed_s: float) -> str:
        """One progress line; the rate counts only the items done in this run."""
        pct = 100.0 * done / self.total if self.total else 100.0
        text = f"{self.label}: {done}/{self.total} {self.unit} ({pct:3.0f} %), {format_seconds(elapsed_s)} elapsed"
        new = done - self._start_count
        if 0 < new and done < self.total:
            text += f", {format_seconds(elapsed_s / new * (self.total - done))} left"
        return text

    def _safe_count(self) -> int | None:
        try:
            return int(self.count())
        except Exception:  # noqa: BLE001 - a store mid-write or gone: try at the next poll
            return None

    def _report(self, done: int, final: bool = False) -> None:
        elapsed = time.perf_counter() - self._t0
        if self.tty:
            self.stream.write("\r" + self.line(done, elapsed) + ("\n" if final else ""))
        else:
            step = int(100.0 * done / self.total // self.quiet_step) if self.total else 0
            if step == self._last_step:
                return
            self._last_step = step
            self.stream.write(self.line(done, elapsed) + "\n")
        self.stream.flush()

    def _poll(self) -> None:
        while not self._stop.wait(self.interval_s):
            done = self._safe_count()
            if done is not None:
                self._report(done)

    def __enter__(self) -> Progress:
        if not self.enabled:
            return self
        self._t0 = time.perf_counter()
        self._start_count = self._safe_count() or 0
        self._report(self._start_count)
        self._thread = threading.Thread(target=self._poll, name="pwf-dask-progress", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, exc_type, *exc) -> None:
        if not self.enabled:
            return
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        done = self._safe_count()
        if done is not None and exc_type is None:
            self._report(done, final=True)
        elif self.tty:
            self.stream.write("\n")
            self.stream.flush()
