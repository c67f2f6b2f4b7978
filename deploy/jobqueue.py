"""Reconstruct a scan on SLURM or PBS GPU nodes with dask-jobqueue.

    python deploy/jobqueue.py slurm /shared/scan.zarr /shared/recon.zarr --jobs 8 \\
        --queue gpu --account abc123 --walltime 04:00:00 --cores 8 --memory 64GB \\
        --activate "source /shared/envs/pwf/bin/activate" --max-iter 1500 --alpha discrepancy

Each batch job holds one GPU and runs one single-threaded Dask worker that advertises the
resource ``GPU=1``; the batch system's CUDA_VISIBLE_DEVICES pins the worker to its GPU, and
every retrieval task asks for one GPU. The workers activate the environment given by
``--activate`` before they start. Every option of ``pwf-dask run`` is accepted and passed
through unchanged (``--help`` lists them). The store is resumable: if jobs are pre-empted,
run the same command again.

Needs ``dask-jobqueue`` where this script runs (``pip install dask-jobqueue``); it is not a
dependency of pwf-dask.
"""

from __future__ import annotations

import argparse
import sys

from pwf_dask.cli import add_retrieval_options, add_tomo_options, retrieval_kwargs
from pwf_dask.retrieval import check_solver_options, parse_alpha

SYSTEMS = {"slurm": "SLURMCluster", "pbs": "PBSCluster"}


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        description="pwf-dask run on GPU batch jobs (dask-jobqueue)",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("system", choices=sorted(SYSTEMS), help="the batch system")
    p.add_argument("scan", help="the scan store, on a file system every node sees")
    p.add_argument("recon", help="the reconstruction store, on a file system every node sees")
    jobs = p.add_argument_group("batch jobs (one GPU worker each)")
    jobs.add_argument("--jobs", type=int, default=4, help="GPU workers, one batch job each")
    jobs.add_argument("--queue", default="gpu", help="partition (SLURM) or queue (PBS)")
    jobs.add_argument("--account", help="account or project to charge")
    jobs.add_argument("--walltime", default="02:00:00", help="per job, HH:MM:SS")
    jobs.add_argument("--cores", type=int, default=4, help="CPU cores per job (reading, correction, compression)")
    jobs.add_argument("--memory", default="32GB", help="host memory per job")
    jobs.add_argument("--gpu-directive", help="the GPU request (default: --gres=gpu:1 or ngpus=1)")
    jobs.add_argument("--activate", help="shell line the workers run first, e.g. 'module load cuda; source env'")
    jobs.add_argument("--local-directory", default="/tmp", help="workers' scratch space on the node")
    run = p.add_argument_group("reconstruction (the options of `pwf-dask run`)")
    run.add_argument("--split", default="auto", choices=["auto", "positions", "even-odd"], help="FSC halves")
    add_tomo_options(run)
    add_retrieval_options(run)
    return p


def make_cluster(args: argparse.Namespace):
    import dask_jobqueue

    gpu = args.gpu_directive or ("--gres=gpu:1" if args.system == "slurm" else "-l ngpus=1")
    return getattr(dask_jobqueue, SYSTEMS[args.system])(
        queue=args.queue,
        account=args.account,
        cores=args.cores,
        processes=1,
        memory=args.memory,
        walltime=args.walltime,
        local_directory=args.local_directory,
        job_extra_directives=[gpu],
        job_script_prologue=[args.activate] if args.activate else [],
        worker_extra_args=["--nthreads", "1", "--resources", "GPU=1"],
    )


def main(argv: list[str] | None = None) -> int:
    from distributed import Client

    from pwf_dask.pipeline.workflow import run_scan

    args = parser().parse_args(argv)
    kwargs = retrieval_kwargs(args)
    # refuse a bad number before any job is queued
    check_solver_options(kwargs["max_iter"], kwargs["tol"], kwargs["gamma"], 1.0, kwargs["phase_scale"])
    parse_alpha(kwargs["alpha"])
    cluster = make_cluster(args)
    print(cluster.job_script(), file=sys.stderr)
    cluster.scale(jobs=args.jobs)
    print(f"dashboard: {cluster.dashboard_link}", file=sys.stderr)
    try:
        with Client(cluster) as client:
            client.wait_for_workers(1)
        center = None if args.center_um is None else args.center_um * 1e-6
        run_scan(
            args.scan,
            args.recon,
            scheduler=cluster.scheduler_address,
            device="gpu",
            split=args.split,
            center_m=center,
            fbp=args.fbp,
            **kwargs,
        )
    finally:
        cluster.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
