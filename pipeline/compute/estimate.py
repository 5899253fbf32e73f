"""What a job will cost, from one of its tasks run for real (``cscsr reconstruct --dry-run``): its time on N
workers and the size of its output at rest. Arithmetic only: the job measures the task
(``pipeline.jobs.dry_run.plan_job``)."""

WORKERS = (1, 8, 64)  # the rows of the table of hours


def hours(seconds_per_task: float, tasks: int, workers: int) -> float:
    """Hours for ``tasks`` tasks of ``seconds_per_task`` each on ``workers`` workers, one task at a time each: whole
    rounds of tasks (a last round that is only part full takes as long as a full one)."""
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    return -(-tasks // workers) * seconds_per_task / 3600


def hours_table(seconds_per_task: float, tasks: int, workers: tuple[int, ...] = WORKERS) -> dict[str, float]:
    """``{"1": H, "8": H, "64": H}``: :func:`hours` for each count of ``workers``, keyed as JSON keys them (the
    shape ``ingest --dry-run --json`` prints too)."""
    return {str(n): hours(seconds_per_task, tasks, n) for n in workers}


def output_bytes(task_bytes: int, task_pixels: int, total_pixels: int) -> int:
    """The output's size at rest, from one task's compressed bytes over its HR pixels: the same bytes per pixel
    over all of the output's pixels."""
    return round(task_bytes / task_pixels * total_pixels) if task_pixels else 0
