"""Dask workers for cscsr as SLURM jobs (dask-jobqueue), then one cscsr command on them.

Run on the cluster's login node, in the environment where cscsr is installed (the jobs run
the same Python, so that environment must be on the shared filesystem):

    pip install dask-jobqueue
    python deploy/slurm.py --jobs 16 -- cscsr reconstruct /shared/x.zarr /shared/out/x.zarr
    python deploy/slurm.py --jobs 4 --gpu --partition gpu -- cscsr reconstruct ...
    python deploy/slurm.py --jobs 16 --print-job-script     # what would be submitted

The scheduler runs in this process; every job is one `dask worker` with the options of the
compose `worker` service (1 process, 1 thread, 4 GiB; `--resources GPU=1` and one GPU with
--gpu). The command after `--` runs with DASK_SCHEDULER_ADDRESS set, so any cscsr command
uses these workers; the jobs end with this script. PBS: the same with dask_jobqueue.PBSCluster
(`resource_spec` instead of `job_extra_directives`).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys

# The compose `worker` service: `dask worker ... --nworkers 1 --nthreads 1 --memory-limit 4GiB`.
CORES = 1
MEMORY = "4GiB"
GPU_RESOURCES = ["--resources", "GPU=1"]


def make_cluster(*, gpu: bool = False, partition: str | None = None, account: str | None = None,
                 walltime: str = "04:00:00", interface: str | None = None, python: str | None = None,
                 **kwargs):
    """A dask_jobqueue.SLURMCluster whose jobs are cscsr workers (no job is submitted yet)."""
    from dask_jobqueue import SLURMCluster

    return SLURMCluster(
        job_name="cscsr-gpu" if gpu else "cscsr",
        cores=CORES, processes=1, memory=MEMORY, walltime=walltime,
        queue=partition, account=account, interface=interface,
        python=python or sys.executable,  # the jobs run this very environment
        worker_extra_args=list(GPU_RESOURCES) if gpu else [],
        job_extra_directives=["--gres=gpu:1"] if gpu else [],
        job_script_prologue=["export OMP_NUM_THREADS=1"],
        **kwargs,
    )


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    command = argv[argv.index("--") + 1:] if "--" in argv else []
    own = argv[:argv.index("--")] if "--" in argv else argv
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--jobs", type=int, default=4, help="worker jobs to submit (default 4)")
    parser.add_argument("--gpu", action="store_true", help="GPU workers: --gres=gpu:1, --resources GPU=1")
    parser.add_argument("--partition")
    parser.add_argument("--account")
    parser.add_argument("--walltime", default="04:00:00")
    parser.add_argument("--interface", help="network interface the jobs reach the scheduler on (e.g. ib0)")
    parser.add_argument("--print-job-script", action="store_true", help="print the job script and exit")
    args = parser.parse_args(own)
    if not command and not args.print_job_script:
        parser.error("give the command to run after `--` (or --print-job-script)")

    with make_cluster(gpu=args.gpu, partition=args.partition, account=args.account,
                      walltime=args.walltime, interface=args.interface) as cluster:
        if args.print_job_script:
            print(cluster.job_script())
            return 0
        cluster.scale(jobs=args.jobs)
        print(f"scheduler {cluster.scheduler_address}, dashboard {cluster.dashboard_link}", file=sys.stderr)
        env = dict(os.environ, DASK_SCHEDULER_ADDRESS=cluster.scheduler_address)
        return subprocess.call(command, env=env)


if __name__ == "__main__":
    sys.exit(main())
