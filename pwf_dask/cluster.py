"""Where tasks run: the schedulers of CONTRACT §3, all existing Dask deployments.

``threads`` (default: the local threaded scheduler, nothing to start), ``processes``,
``local`` (a distributed LocalCluster, dashboard on localhost), ``local-cuda`` (dask-cuda's
LocalCUDACluster, one worker per GPU, tasks ask for ``resources={"GPU": 1}``) or a scheduler
address ``tcp://HOST:PORT`` of a running cluster (dask-jobqueue, Kubernetes, ...; when its
workers advertise a ``GPU`` resource, every task asks for one).

Tasks go through :meth:`Runner.map`, which shows progress and returns results in order. On
distributed, tasks are submitted one by one with ``client.submit`` so that resource
annotations survive (graph optimisation would drop them). CPU tasks get an FFT thread budget
of cores / concurrent tasks, so FFT threads never oversubscribe the machine.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

SCHEDULERS = ("threads", "processes", "local", "local-cuda")


def cpu_count() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover
        return max(1, os.cpu_count() or 1)


@dataclass
class Runner:
    """A connection to one scheduler; use as a context manager (closes what it started)."""

    scheduler: str = "threads"
    workers: int | None = None
    gpu: bool = False
    client: Any = None
    _owned: list = field(default_factory=list)

    def __post_init__(self):
        s = self.scheduler
        if s not in SCHEDULERS and not s.startswith(("tcp://", "tls://", "ucx://")):
            raise ValueError(f"unknown scheduler {s!r}: use {', '.join(SCHEDULERS)} or tcp://HOST:PORT")
        if s == "local":
            from distributed import Client, LocalCluster

            n = self.workers or cpu_count()
            cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=":0")
            self.client = Client(cluster)
            self._owned += [self.client, cluster]
            print(f"LocalCluster with {n} workers; dashboard {self.client.dashboard_link}", file=sys.stderr)
        elif s == "local-cuda":
            try:
                from dask_cuda import LocalCUDACluster
            except ImportError:
                raise ValueError("--scheduler local-cuda needs dask-cuda: pip install 'pwf-dask[gpu]'") from None
            from distributed import Client

            cluster = LocalCUDACluster(resources={"GPU": 1})
            self.client = Client(cluster)
            self._owned += [self.client, cluster]
            self.gpu = True
        elif s.startswith(("tcp://", "tls://", "ucx://")):
            from distributed import Client

            self.client = Client(s)
            self._owned.append(self.client)
            # workers started with --resources GPU=1 (dask-jobqueue, Kubernetes): ask for one
            workers = self.client.scheduler_info().get("workers", {})
            self.gpu = bool(workers) and all("GPU" in w.get("resources", {}) for w in workers.values())

    def __enter__(self) -> Runner:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        for obj in self._owned:
            try:
                obj.close()
            except Exception:  # closing is best effort
                pass
        self._owned.clear()

    @property
    def concurrency(self) -> int:
        if self.client is not None:
            return max(1, sum(self.client.nthreads().values()))
        return self.workers or cpu_count()

    def fft_workers(self) -> int | None:
        """FFT threads per task: cores / tasks at once (None: let each worker decide)."""
        if self.client is not None:
            return None
        return max(1, cpu_count() // self.concurrency)

    def map(self, fn: Callable, items: Sequence, *, label: str = "tasks", **kwargs) -> list:
        """``[fn(item, **kwargs) for item in items]`` on the scheduler, with progress."""
        if not items:
            return []
        if self.client is not None:
            from distributed import progress

            res = {"GPU": 1} if self.gpu else None
            futures = [self.client.submit(fn, it, pure=False, resources=res, **kwargs) for it in items]
            print(f"{label}: {len(futures)}", file=sys.stderr)
            progress(futures, notebook=False)
            print(file=sys.stderr)
            return self.client.gather(futures)
        import dask
        from dask.diagnostics import ProgressBar

        tasks = [dask.delayed(fn, pure=False)(it, **kwargs) for it in items]
        print(f"{label}: {len(tasks)}", file=sys.stderr)
        with ProgressBar(out=sys.stderr):
            return list(dask.compute(*tasks, scheduler=self.scheduler, num_workers=self.concurrency))


def worker_fft_threads(default: int | None) -> int | None:
    """Inside a distributed worker: cores / that worker's threads; else ``default``."""
    if default is not None:
        return default
    try:
        from distributed import get_worker

        w = get_worker()
        return max(1, cpu_count() // max(1, w.state.nthreads))
    except (ImportError, ValueError, AttributeError):
        return None
