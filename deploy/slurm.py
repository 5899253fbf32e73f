"""Dask workers for cscsr as SLURM jobs (dask-jobqueue), then one cscsr command on them.

Run on the cluster's login node, in the environment where cscsr is installed (the jobs run
the same Python, so that environment must be on the shared filesystem):

    pip install dask-jobqueue
    python deploy/slurm.py --jobs 16 -- cscsr reconstruct /shared/x.zarr /shared/out/x.zarr
    python deploy/slurm.py --jobs 4 --gpu --partition gpu -- cscsr reconstruct ...
    python deploy/slurm.py --jobs 2 --gpu --gpus-per-job 4 --partition gpu -- cscsr reconstruct ...
    python deploy/slurm.py --jobs 16 --print-job-script     # what would be submitted

The scheduler runs in this process; every CPU job is one `dask worker` with the options of the
compose `worker` service (1 process, 1 thread, 4 GiB). A --gpu job asks for --gpus-per-job GPUs
(default 1) and runs `cscsr worker` (`python -m pipeline.cli worker`, the compose `gpu-worker`
command, as `dask cuda worker` would run): one worker per GPU of the job, pinned to it (SLURM's
CUDA_VISIBLE_DEVICES), advertising GPU=1, with GPU_TASKS_IN_FLIGHT threads and 4 GiB each.
The command after `--` runs with DASK_SCHEDULER_ADDRESS set, so any cscsr command uses these
workers; the jobs end with this script. PBS: the same with dask_jobqueue.PBSCluster
(`resource_spec` instead of `job_extra_directives`).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys

# The compose `worker` service: `dask worker ... --nworkers 1 --nthreads 1 --memory-limit 4GiB`.
CORES = 1
MEMORY_GIB = 4
MEMORY = f"{MEMORY_GIB}GiB"
# The compose `gpu-worker` service: `cscsr worker ADDRESS --memory-limit 4GiB`, run as dask-jobqueue
# runs a worker command (`python -m ...`), with the options it gives every worker command.
GPU_WORKER_COMMAND = "pipeline.cli worker"


def make_cluster(*, gpu: bool = False, gpus_per_job: int = 1, partition: str | None = None,
                 account: str | None = None, walltime: str = "04:00:00", interface: str | None = None,
                 python: str | None = None, **kwargs):
    """A dask_jobqueue.SLURMCluster whose jobs are cscsr workers (no job is submitted yet).

    With ``gpu``, a job of ``gpus_per_job`` GPUs runs that many pinned workers (``cscsr worker``), each
    with GPU_TASKS_IN_FLIGHT cores and 4 GiB: dask-jobqueue counts them as the job's processes, named
    NAME-0, NAME-1, ... as it expects."""
    from dask_jobqueue import SLURMCluster

    if not gpu:
        return SLURMCluster(
            job_name="cscsr", cores=CORES, processes=1, memory=MEMORY, walltime=walltime,
            queue=partition, account=account, interface=interface,
            python=python or sys.executable,  # the jobs run this very environment
            job_script_prologue=["export OMP_NUM_THREADS=1"],
            **kwargs,
        )
    from pipeline.compute.cluster import GPU_TASKS_IN_FLIGHT

    if not isinstance(gpus_per_job, int) or gpus_per_job < 1:
        raise ValueError(f"gpus_per_job must be an integer >= 1, got {gpus_per_job!r}")
    return SLURMCluster(
        job_name="cscsr-gpu", cores=GPU_TASKS_IN_FLIGHT * gpus_per_job, processes=gpus_per_job,
        memory=f"{MEMORY_GIB * gpus_per_job}GiB", walltime=walltime,
        queue=partition, account=account, interface=interface,
        python=python or sys.executable,
        worker_command=GPU_WORKER_COMMAND,
        worker_extra_args=["--gpus", str(gpus_per_job)],  # SLURM's CUDA_VISIBLE_DEVICES must show them all
        job_extra_directives=[f"--gres=gpu:{gpus_per_job}"],
        job_script_prologue=["export OMP_NUM_THREADS=1"],
        **kwargs,
    )


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    command = argv[argv.index("--") + 1:] if "--" in argv else []
    own = argv[:argv.index("--")] if "--" in argv else argv
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--jobs", type=int, default=4, help="worker jobs to submit (default 4)")
    parser.add_argument("--gpu", action="store_true", help="GPU jobs: `cscsr worker`, one pinned GPU=1 worker "
                        "per GPU of a job")
    parser.add_argument("--gpus-per-job", type=int, default=1, help="GPUs of a --gpu job (default 1)")
    parser.add_argument("--partition")
    parser.add_argument("--account")
    parser.add_argument("--walltime", default="04:00:00")
    parser.add_argument("--interface", help="network interface the jobs reach the scheduler on (e.g. ib0)")
    parser.add_argument("--print-job-script", action="store_true", help="print the job script and exit")
    args = parser.parse_args(own)
    if not command and not args.print_job_script:
        parser.error("give the command to run after `--` (or --print-job-script)")
    if args.gpus_per_job < 1:
        parser.error(f"--gpus-per-job must be >= 1, got {args.gpus_per_job}")
    if args.jobs < 1:
        parser.error(f"--jobs must be >= 1, got {args.jobs}")

    with make_cluster(gpu=args.gpu, gpus_per_job=args.gpus_per_job, partition=args.partition, account=args.account,
                      walltime=args.walltime, interface=args.interface) as cluster:
        if args.print_job_script:
            print(cluster.job_script())
            return 0
        if refused := refused_submission(cluster.job_script()):
            print(f"error: sbatch refuses the worker job ({refused}): the command was not run", file=sys.stderr)
            return 1
        cluster.scale(jobs=args.jobs)
        if unsubmitted := wait_for_submission(cluster, args.jobs):
            print(f"error: {unsubmitted} of {args.jobs} worker jobs not submitted within {SUBMIT_SECONDS} s (sbatch "
                  f"failed: the lines above say why): the command was not run", file=sys.stderr)
            return 1
        print(f"scheduler {cluster.scheduler_address}, dashboard {cluster.dashboard_link}", file=sys.stderr)
        env = dict(os.environ, DASK_SCHEDULER_ADDRESS=cluster.scheduler_address)
        return subprocess.call(command, env=env)


SUBMIT_SECONDS = 120  # for every worker job to be given a SLURM job id (sbatch answers in seconds)


def refused_submission(script: str) -> str | None:
    """What ``sbatch --test-only`` says against the job script (a partition, account or --gres SLURM does not
    have), or None if it would take it: a submission that fails later is only logged by dask-jobqueue, and the
    command then waited for workers that were never asked for."""
    try:
        done = subprocess.run(["sbatch", "--test-only"], input=script, capture_output=True, text=True)
    except FileNotFoundError:
        return "no sbatch command here: run this on a SLURM login node"
    said = (done.stderr or done.stdout).strip().splitlines()
    return None if done.returncode == 0 else (said[-1] if said else f"exit status {done.returncode}")


def wait_for_submission(cluster, jobs: int) -> int:
    """How many of the ``jobs`` worker jobs have no SLURM job id after :data:`SUBMIT_SECONDS` (0: all submitted)."""
    import time

    deadline = time.monotonic() + SUBMIT_SECONDS
    while True:
        submitted = sum(1 for job in list(cluster.workers.values()) if getattr(job, "job_id", None))
        if submitted >= jobs or time.monotonic() > deadline:
            return max(jobs - submitted, 0)
        time.sleep(0.5)


if __name__ == "__main__":
    sys.exit(main())
