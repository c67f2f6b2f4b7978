"""Reconstruct a scan on SLURM GPU nodes with dask-jobqueue (a template: edit the site values).

    python deploy/slurm_gpu.py /shared/scan.zarr /shared/recon.zarr --jobs 8

Each SLURM job holds one GPU and runs one single-threaded Dask worker that advertises the
resource ``GPU=1``; SLURM's CUDA_VISIBLE_DEVICES pins the worker to its GPU. pwf-dask connects
to the scheduler started here like to any other ``tcp://`` scheduler.
"""

from __future__ import annotations

import argparse

from dask_jobqueue import SLURMCluster
from distributed import Client

from pwf_dask.workflow import run_scan


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("scan")
    p.add_argument("recon")
    p.add_argument("--jobs", type=int, default=4, help="GPU workers (one SLURM job each)")
    p.add_argument("--partition", default="gpu")
    p.add_argument("--account", default=None)
    p.add_argument("--walltime", default="02:00:00")
    p.add_argument("--max-iter", type=int, default=2000)
    args = p.parse_args()
    cluster = SLURMCluster(
        queue=args.partition,
        account=args.account,
        cores=4,  # CPU cores per job: ingest, flat/dark correction, Zarr compression
        processes=1,
        memory="32GB",
        walltime=args.walltime,
        job_extra_directives=["--gres=gpu:1"],
        worker_extra_args=["--nthreads", "1", "--resources", "GPU=1"],
    )
    cluster.scale(jobs=args.jobs)
    print(f"dashboard: {cluster.dashboard_link}")
    try:
        with Client(cluster) as client:
            client.wait_for_workers(1)
        run_scan(args.scan, args.recon, scheduler=cluster.scheduler_address, device="gpu", max_iter=args.max_iter)
    finally:
        cluster.close()


if __name__ == "__main__":
    main()
