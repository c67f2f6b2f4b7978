"""Where tasks run: the schedulers of docs/scan-format.md §3, all existing Dask deployments.

``threads`` (default: the local threaded scheduler, nothing to start), ``processes`` and
``local`` (a distributed LocalCluster of worker processes under nannies; ``local`` with its
dashboard on 127.0.0.1), ``local-cuda`` (dask-cuda's LocalCUDACluster, one worker per GPU,
tasks ask for ``resources={"GPU": 1}``) or a scheduler address ``tcp://HOST:PORT`` /
``tls://HOST:PORT`` (with ``security``) of a running cluster (dask-jobqueue, Kubernetes, ...;
when its workers advertise a ``GPU`` resource, every task asks for one).

Tasks go through :meth:`Runner.map`, which shows progress (per projection, with the time
left) and returns results in order. On distributed, tasks are submitted one by one with
``client.submit`` so that resource annotations survive (graph optimisation would drop them).
CPU tasks get an FFT thread budget of cores / concurrent tasks, so FFT threads never
oversubscribe the machine.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pwf_dask.backend import default_fft_workers

SCHEDULERS = ("threads", "processes", "local", "local-cuda")
ADDRESS_PREFIXES = ("tcp://", "tls://", "ucx://")
#: the LocalCluster dashboard's default bind: this host only (issue #29: ":0" answered from
#: other machines, unauthenticated)
DEFAULT_DASHBOARD_ADDRESS = "127.0.0.1:0"


def cpu_count() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover
        return max(1, os.cpu_count() or 1)


def check_scheduler(scheduler: str, security: str | None = None) -> None:
    """Refuse, in one line and before anything is written, a scheduler that cannot be used:
    an unknown name, or ``tls://`` with neither ``security`` nor Dask's TLS configuration."""
    if scheduler not in SCHEDULERS and not scheduler.startswith(ADDRESS_PREFIXES):
        raise ValueError(f"unknown scheduler {scheduler!r}: use {', '.join(SCHEDULERS)} or tcp://HOST:PORT")
    if security is not None and not Path(security).is_file():
        raise ValueError(f"--security {security}: no such file (a YAML of tls_ca_file, tls_client_cert, ...)")
    if scheduler.startswith("tls://") and security is None:
        import dask

        if not dask.config.get("distributed.comm.tls.ca-file", None):
            raise ValueError(
                "a tls:// scheduler needs --security FILE (tls_ca_file, tls_client_cert, tls_client_key) "
                "or Dask's distributed.comm.tls configuration (docs/clusters.md)"
            )


def load_security(path: str | None):
    """A :class:`distributed.Security` from a YAML file of its keyword arguments, or None."""
    if path is None:
        return None
    import yaml
    from distributed import Security

    with open(path) as f:
        options = yaml.safe_load(f) or {}
    if not isinstance(options, dict):
        raise ValueError(f"--security {path}: expected a mapping of Security options, got {type(options).__name__}")
    try:
        return Security(**options)
    except TypeError as exc:
        raise ValueError(f"--security {path}: {exc}") from None


@dataclass
class Runner:
    """A connection to one scheduler; use as a context manager (closes what it started).

    ``processes`` and ``local`` are both a distributed LocalCluster of single-threaded worker
    processes under nannies (a lost worker is restarted and its tasks retried; workers end
    with the run); only ``local`` serves the dashboard, on ``dashboard_address``.
    """

    scheduler: str = "threads"
    workers: int | None = None
    gpu: bool = False
    client: Any = None
    dashboard_address: str = DEFAULT_DASHBOARD_ADDRESS
    security: str | None = None
    _owned: list = field(default_factory=list)

    def __post_init__(self):
        s = self.scheduler
        check_scheduler(s, self.security)
        if s in ("local", "processes"):
            from distributed import Client, LocalCluster

            n = self.workers or cpu_count()
            dashboard = self.dashboard_address if s == "local" else None
            cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=dashboard)
            self.client = Client(cluster)
            self._owned += [self.client, cluster]
            where = f"; dashboard {self.client.dashboard_link}" if dashboard else ""
            logging.getLogger(__name__).info(f"LocalCluster with {n} worker processes{where}")
        elif s == "local-cuda":
            try:
                from dask_cuda import LocalCUDACluster
            except ImportError:
                raise ValueError("--scheduler local-cuda needs dask-cuda: pip install 'pwf-dask[gpu]'") from None
            from distributed import Client

            cluster = LocalCUDACluster(resources={"GPU": 1}, dashboard_address=self.dashboard_address)
            self.client = Client(cluster)
            self._owned += [self.client, cluster]
            self.gpu = True
        elif s.startswith(ADDRESS_PREFIXES):
            from distributed import Client

            try:
                self.client = Client(s, security=load_security(self.security), timeout="30s")
            except OSError as exc:
                raise ValueError(f"cannot reach the scheduler at {s}: {_first_line(exc)}") from None
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
        """FFT threads per task: cores / tasks at once (None: let each worker decide).

        ``local`` and ``processes`` workers share this machine's cores, so they count too: with
        each worker deciding alone (cores / its own threads), two single-threaded workers on 2
        cores ran 2 FFT threads each, and MKL's OpenMP, oversubscribed, took a full-width
        projection from ~14 to 32 s (a third of the CPU time in the kernel; session 43)."""
        if self.client is not None and self.scheduler not in ("local", "processes"):
            return None
        return max(1, cpu_count() // self.concurrency)

    def map(
        self,
        fn: Callable,
        items: Sequence,
        *,
        label: str = "tasks",
        unit: str = "tasks",
        count: Callable[[], int] | None = None,
        total: int | None = None,
        **kwargs,
    ) -> list:
        """``[fn(item, **kwargs) for item in items]`` on the scheduler, in order, with progress
        on stderr (:class:`~pwf_dask.progress.Progress`): ``count()`` of ``total`` when given
        (what has landed in the store, finer than a task), else the tasks finished."""
        from pwf_dask.progress import Progress

        if not items:
            return []
        if self.client is not None:
            res = {"GPU": 1} if self.gpu else None
            futures = [self.client.submit(fn, it, pure=False, resources=res, **kwargs) for it in items]
            with Progress(label, total or len(futures), count or (lambda: sum(f.done() for f in futures)), unit=unit):
                return self.client.gather(futures)
        import dask
        from dask.callbacks import Callback

        tasks = [dask.delayed(fn, pure=False)(it, **kwargs) for it in items]
        keys = {t.key for t in tasks}
        finished = [0]

        class _Finished(Callback):
            def _posttask(self, key, result, dsk, state, worker_id):
                finished[0] += key in keys

        with _Finished(), Progress(label, total or len(tasks), count or (lambda: finished[0]), unit=unit):
            return list(dask.compute(*tasks, scheduler=self.scheduler, num_workers=self.concurrency))


def _first_line(exc: Exception) -> str:
    return (str(exc).splitlines() or [type(exc).__name__])[0]


def worker_fft_threads(default: int | None) -> int | None:
    """``default``, else inside a worker of a cluster given by address: ``PWF_DASK_FFT_WORKERS``
    from its environment, or its cores / its threads (one worker per host or per allotment of
    cores: several worker processes sharing a host's cores need the variable set)."""
    if default is not None:
        return default
    try:
        from distributed import get_worker

        w = get_worker()
    except (ImportError, ValueError, AttributeError):
        return None
    if os.environ.get("PWF_DASK_FFT_WORKERS"):
        return default_fft_workers()
    return max(1, cpu_count() // max(1, getattr(getattr(w, "state", None), "nthreads", 1)))
