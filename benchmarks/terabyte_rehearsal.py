"""A terabyte job rehearsed on a 20 GB capture: parallel ingest, a time range, a region, kills and resumes.

What (issue #36): a synthetic 1000x1000 RGGB ``.dat`` capture of ``--frames`` frames (default 160,000: 20.0 GB,
8 s of the camera), made on the fly by integrate-and-fire of a moving colour scene (a drifting smooth
background and a bright disc crossing it, so edges move; rates 0.02-0.35 spikes/pixel/frame), then:

1. ``ingest``: ``cp`` of the capture (the reference), ``cscsr ingest`` in one process, and on local clusters
   of 1 and 2 workers started before the timer (``pipeline.compute.cluster.dask_client``); the stores of one process
   and of 2 workers are compared file by file (identical bytes). Goals: 2 workers >= 1.7x one process, and
   >= 0.8x ``cp``.
2. ``ingest-resume``: ``cscsr ingest --workers 2`` SIGKILLed (its process group: client and cluster) once about a
   third of its tasks are committed, then ``--resume``: the store must be byte-identical to one process's.
3. ``tfp``: ``reconstruct --dry-run --json`` of TFP over ``--range`` (default ``4s:4.5s``), then the job on
   ``--workers`` (default 2); goal: the plan's time within 25 % of the job's.
4. ``tfp-resume``: the same job SIGKILLed once about a third of its frames are written, ``--resume``d: the
   output must be byte-identical to the uninterrupted job's.
5. ``lite``: the plan and the job of ``cscsr`` ``lite`` over ``--region`` (default ``448:576,448:576``, LR pixels)
   and a shorter range (``--lite-range``, default ``4s:4.1s``).
6. The cost of one terabyte (8,000,000 frames, 195,121 output frames at one per 41 frames) per stage, from
   the measured per-task costs: CPU-seconds per unit from the jobs above, divided over N CPU workers; the
   network on one GPU worker from the forward-pass figures of ``docs/gpu.md`` (H100, not measured here).

All timings are wall-clock of whole jobs, medians of ``--repeats`` where a step is repeated (default 1: each
20 GB ingest takes about a minute). Outputs are deleted at the end; the capture is cached under
/tmp/cscsr_bench. Needs about 2.5x the capture's size free on /tmp's disk.

Run: ``python benchmarks/terabyte_rehearsal.py [--frames N] [--steps ingest,ingest-resume,tfp,tfp-resume,lite]
[--workers W] [--repeats R]``.
"""

import argparse
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from _common import ROOT, load_average, markdown_table, median, save_results, write_integrate_and_fire

H = W = 1000
FRAME_BYTES = H * W // 8
FPS = 20_000
WINDOW = 41
TERABYTE_FRAMES = 8_000_000  # 1 TB of 125,000-byte frames
CACHE = Path("/tmp/cscsr_bench")
BLOCK = 250  # frames generated per block; the scene moves block to block
CLI = str(Path(sys.executable).parent / "cscsr")
STEPS = ("ingest", "ingest-resume", "tfp", "tfp-resume", "lite")
GPU_FORWARD_S = {"full bf16": 0.332, "lite bf16": 0.164}  # s per 1000x1000 window, H100 (docs/gpu.md)


def scene_rates(first_frame: int) -> np.ndarray:
    """(H, W) float32 firing rates of an RGGB sensor watching a moving colour scene at ``first_frame``: a smooth
    background drifting 0.01 px/frame and a bright disc of radius 120 crossing the frame at 0.02 px/frame."""
    t = float(first_frame)
    y, x = np.mgrid[0:H, 0:W].astype(np.float32)
    xs = x - 0.01 * t
    base = 0.5 + 0.3 * np.sin(xs / 97) * np.cos(y / 131) + 0.2 * np.sin((xs + 0.6 * y) / 53)  # [0, 1]
    rgb = np.stack([base, 0.6 + 0.4 * np.sin(xs / 71 + 1.0) * base, 0.3 + 0.5 * np.cos(y / 83) * base], -1)
    cx, cy = (100 + 0.02 * t) % (W + 240) - 120, 500 + 200 * np.sin(t / 40_000)
    disc = ((x - cx) ** 2 + (y - cy) ** 2 < 120**2)[..., None] * np.array([0.9, 0.7, 0.2], np.float32)
    rgb = np.clip(np.maximum(rgb * 0.7, disc), 0, 1)
    channel = np.array([[0, 1], [1, 2]])[y.astype(int) % 2, x.astype(int) % 2]  # RGGB
    level = np.take_along_axis(rgb, channel[..., None], -1)[..., 0]
    return (0.02 + 0.33 * level).astype(np.float32)


def capture(frames: int) -> Path:
    path = CACHE / f"rehearsal_{H}x{W}_{frames}.dat"
    if not (path.exists() and path.stat().st_size == frames * FRAME_BYTES):
        CACHE.mkdir(parents=True, exist_ok=True)
        began = time.perf_counter()
        write_integrate_and_fire(path, frames, scene_rates, block=BLOCK)  # subtract reset, bounded memory
        print(f"capture: {frames} frames in {time.perf_counter() - began:.0f} s", file=sys.stderr)
    return path


def files_digest(path: Path) -> dict[str, str]:
    """SHA-256 of every file of a store by its path inside it (chunks, metadata, commit records)."""
    digests = {}
    for folder, _, names in os.walk(path):
        for name in names:
            with open(os.path.join(folder, name), "rb") as handle:
                digests[os.path.relpath(os.path.join(folder, name), path)] = hashlib.file_digest(handle, "sha256").hexdigest()
    return digests


def store_bytes(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def committed(path: Path) -> int:
    """Tasks a job has committed: each writes one chunk file of its ``committed`` array."""
    return sum(name.isdigit() for _, _, files in os.walk(path / "committed" / "c") for name in files)


def remove(path: Path) -> None:
    shutil.rmtree(path, ignore_errors=True) if path.is_dir() else path.unlink(missing_ok=True)
    subprocess.run(["sync"], check=True)


INGEST_CHILD = """
import json, sys, time
from pipeline.compute.cluster import dask_client
from pipeline.jobs.ingest import IngestOptions, ingest
src, dest, workers = sys.argv[1], sys.argv[2], int(sys.argv[3])
options = IngestOptions(height=%d, width=%d, cfa="rggb", fps=%d)
if workers:
    with dask_client(workers=workers) as client:
        began = time.perf_counter()
        ingest(src, dest, options, progress=False, client=client)
        seconds = time.perf_counter() - began
else:
    began = time.perf_counter()
    ingest(src, dest, options, progress=False)
    seconds = time.perf_counter() - began
print(json.dumps({"seconds": seconds}))
""" % (H, W, FPS)


def timed_ingest(src: Path, dest: Path, workers: int) -> float:
    """Seconds of ``ingest()`` in a fresh interpreter: in its own process (0) or on a local cluster of ``workers``
    started before the timer."""
    remove(dest)
    out = subprocess.run([sys.executable, "-c", INGEST_CHILD, str(src), str(dest), str(workers)], cwd=ROOT,
                         check=True, capture_output=True, text=True)
    return json.loads(out.stdout.splitlines()[-1])["seconds"]


def timed_cp(src: Path, dest: Path) -> float:
    remove(dest)
    began = time.perf_counter()
    subprocess.run(["cp", str(src), str(dest)], check=True)
    seconds = time.perf_counter() - began
    remove(dest)
    return seconds


def cscsr(*args, check: bool = True) -> tuple[float, str]:
    """Seconds and stdout of a ``cscsr -q`` command, start-up included (what a user waits for)."""
    began = time.perf_counter()
    out = subprocess.run([CLI, "-q", *map(str, args)], capture_output=True, text=True)
    if check and out.returncode:
        raise SystemExit(f"cscsr {' '.join(map(str, args))} failed: {out.stderr.strip()[-2000:]}")
    return time.perf_counter() - began, out.stdout


def killed(args: list, out: Path, fraction_of: int, fraction: float = 1 / 3) -> int:
    """``cscsr -q ARGS`` SIGKILLed (its whole process group: client, scheduler and workers) once ``fraction`` of its
    ``fraction_of`` tasks are committed in ``out``; returns the tasks committed at the kill."""
    process = subprocess.Popen([CLI, "-q", *map(str, args)], start_new_session=True, stdout=subprocess.DEVNULL,
                               stderr=subprocess.DEVNULL)
    while committed(out) < fraction * fraction_of:
        if process.poll() is not None:
            raise SystemExit(f"cscsr {' '.join(map(str, args))} ended before it could be killed")
        time.sleep(0.05)
    os.killpg(process.pid, signal.SIGKILL)
    process.wait()
    return committed(out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=160_000, help="frames of the capture (default 160,000: 20 GB)")
    parser.add_argument("--steps", default=",".join(STEPS), help=f"which steps (default all: {','.join(STEPS)})")
    parser.add_argument("--workers", type=int, default=2, help="workers of the reconstruct jobs (default 2)")
    parser.add_argument("--repeats", type=int, default=1, help="repetitions of the timed ingests and jobs")
    parser.add_argument("--range", default="4s:4.5s", help="TFP's --start:--stop (default 4s:4.5s)")
    parser.add_argument("--lite-range", default="4s:4.1s", help="lite's --start:--stop (default 4s:4.1s)")
    parser.add_argument("--region", default="448:576,448:576", help="lite's --region (default the middle 128x128)")
    parser.add_argument("--keep", action="store_true", help="keep the stores under /tmp/cscsr_bench/rehearsal")
    args = parser.parse_args()
    steps = args.steps.split(",")
    if unknown := set(steps) - set(STEPS):
        parser.error(f"unknown steps {sorted(unknown)}: expected some of {', '.join(STEPS)}")
    needed = args.frames * FRAME_BYTES * (3.3 if "ingest" in steps else 2.3)  # the capture, cp's copy, 2 stores
    CACHE.mkdir(parents=True, exist_ok=True)
    cached = CACHE / f"rehearsal_{H}x{W}_{args.frames}.dat"
    free = shutil.disk_usage(CACHE).free + (cached.stat().st_size if cached.exists() else 0)
    if free < needed:
        raise SystemExit(f"terabyte_rehearsal: {CACHE} has {free / 1e9:.0f} GB free, the rehearsal needs about "
                         f"{needed / 1e9:.0f} GB: free some, or use fewer --frames")
    load_start = load_average()
    src = capture(args.frames)
    size = src.stat().st_size
    work = CACHE / "rehearsal"
    work.mkdir(parents=True, exist_ok=True)
    store, results = work / "spikes.zarr", {"frames": args.frames, "capture_bytes": size, "args": vars(args)}
    try:
        if "ingest" in steps or not store.exists():
            ways = {"cp": lambda: timed_cp(src, work / "copy.dat"),
                    "1 process": lambda: timed_ingest(src, work / "one.zarr", 0),
                    "1 worker": lambda: timed_ingest(src, work / "w1.zarr", 1),
                    "2 workers": lambda: timed_ingest(src, work / "w2.zarr", 2)}
            if "ingest" not in steps:  # only the store the other steps read
                ways = {"1 process": ways["1 process"]}
            runs = []
            for repeat in range(args.repeats if "ingest" in steps else 1):
                run = {"repeat": repeat}
                for name in list(ways)[:: 1 if repeat % 2 == 0 else -1]:  # alternate the order
                    run[name] = ways[name]()
                    print(f"ingest #{repeat} {name}: {run[name]:.1f} s, {size / 1e6 / run[name]:.0f} MB/s", file=sys.stderr)
                    remove(work / "w1.zarr")  # at most two stores and cp's copy beside the capture
                if "2 workers" in run:
                    run["identical"] = files_digest(work / "w2.zarr") == files_digest(work / "one.zarr")
                    remove(work / "w2.zarr")
                if repeat < args.repeats - 1:
                    remove(work / "one.zarr")
                runs.append(run)
            remove(store)
            (work / "one.zarr").rename(store)
            results["store_bytes"] = store_bytes(store)
            if "ingest" in steps:
                results["ingest"] = runs
        if "ingest-resume" in steps:
            dest = work / "killed.zarr"
            remove(dest)
            ingest_args = ["ingest", src, dest, "--height", H, "--width", W, "--cfa", "rggb", "--fps", FPS]
            tasks = int(json.loads(cscsr(*ingest_args, "--dry-run", "--json")[1])["tasks"])
            at_kill = killed([*ingest_args, "--workers", 2], dest, tasks)
            seconds, _ = cscsr(*ingest_args, "--resume", "--workers", 2)
            results["ingest_resume"] = {"tasks": tasks, "committed_at_kill": at_kill, "resume_s": seconds,
                                        "identical": files_digest(dest) == files_digest(store)}
            print(f"ingest killed at {at_kill}/{tasks} tasks, resumed in {seconds:.1f} s: identical "
                  f"{results['ingest_resume']['identical']}", file=sys.stderr)
            remove(dest)
        jobs = {"tfp": ["--method", "tfp", *ranged(args.range)],
                "lite": ["--method", "cscsr", "--weights", "lite", *ranged(args.lite_range), "--region", args.region]}
        for name in ("tfp", "lite"):
            if name not in steps:
                continue
            out, runs = work / f"{name}.zarr", []
            for repeat in range(args.repeats):
                command = ["reconstruct", store, out, *jobs[name], "--workers", args.workers, "--overwrite"]
                plan = json.loads(cscsr(*command, "--dry-run", "--json")[1])
                seconds, _ = cscsr(*command)
                runs.append({"repeat": repeat, "estimated_s": plan["job_seconds"], "job_s": seconds,
                             "time_ratio": plan["job_seconds"] / seconds, "tasks": plan["tasks"],
                             "frames": plan["frames"], "hr": [plan["hr_height"], plan["hr_width"]],
                             "estimated_bytes": plan["output_bytes"], "bytes": store_bytes(out / "video"),
                             "seconds_per_task_planned": plan["seconds_per_task"]})
                print(f"{name} #{repeat}: planned {plan['job_seconds']:.1f} s, job {seconds:.1f} s "
                      f"({plan['frames']} frames, {plan['tasks']} tasks)", file=sys.stderr)
            results[name] = runs
            if name == "tfp" and "tfp-resume" in steps:
                clean, dest = files_digest(out), work / "tfp-killed.zarr"
                remove(dest)
                command = ["reconstruct", store, dest, *jobs[name], "--workers", args.workers]
                at_kill = killed(command, dest, runs[0]["tasks"])
                seconds, _ = cscsr(*command, "--resume")
                results["tfp_resume"] = {"tasks": runs[0]["tasks"], "committed_at_kill": at_kill, "resume_s": seconds,
                                         "identical": files_digest(dest) == clean}
                print(f"tfp killed at {at_kill}/{runs[0]['tasks']} tasks, resumed in {seconds:.1f} s: identical "
                      f"{results['tfp_resume']['identical']}", file=sys.stderr)
                remove(dest)
            remove(out)
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    results["load_average"] = [load_start, load_average()]
    report(results, args)


def ranged(text: str) -> list[str]:
    start, stop = text.split(":")
    return ["--start", start, "--stop", stop]


def report(results: dict, args) -> None:
    size, tb_windows = results["capture_bytes"], TERABYTE_FRAMES / WINDOW
    print(f"## Terabyte rehearsal: {args.frames} frames of {H}x{W} RGGB ({size / 1e9:.1f} GB), "
          f"integrate-and-fire of a moving scene\n")
    cost_rows = []  # stage, what was measured, worker-seconds per terabyte
    if runs := results.get("ingest"):
        rates = {name: median(size / 1e6 / run[name] for run in runs) for name in ("cp", "1 process", "1 worker", "2 workers")}
        two = rates["2 workers"]
        print(markdown_table(["ingest", "MB/s (median)", "2 workers over it", "goal", "result"], [
            ["cp", f"{rates['cp']:.0f}", f"{two / rates['cp']:.2f}", ">= 0.8", "PASS" if two >= 0.8 * rates["cp"] else "FAIL"],
            ["1 process", f"{rates['1 process']:.0f}", f"{two / rates['1 process']:.2f}", ">= 1.7",
             "PASS" if two >= 1.7 * rates["1 process"] else "FAIL"],
            ["1 worker", f"{rates['1 worker']:.0f}", f"{two / rates['1 worker']:.2f}", "", ""],
            ["2 workers", f"{two:.0f}", "", "", ""]]))
        identical = all(run["identical"] for run in runs)
        print(f"\nStores of 2 workers and of one process byte-identical: {identical}; store "
              f"{results['store_bytes'] / 1e9:.2f} GB ({8 * results['store_bytes'] / (args.frames * H * W):.3f} bits/pixel).\n")
        cost_rows.append(["ingest", f"{two:.0f} MB/s on 2 workers", 2 * 1e12 / (two * 1e6)])
    for name in ("ingest_resume", "tfp_resume"):
        if kill := results.get(name):
            print(f"{name.replace('_', ' ')}: killed at {kill['committed_at_kill']}/{kill['tasks']} tasks committed, "
                  f"--resume took {kill['resume_s']:.1f} s; byte-identical to the uninterrupted run: {kill['identical']}\n")
    plan_rows = []
    for name, label in (("tfp", f"TFP {args.range}"), ("lite", f"lite {args.lite_range}, region {args.region}")):
        if runs := results.get(name):
            ratio = median(r["time_ratio"] for r in runs)
            first = runs[0]
            plan_rows.append([label, first["frames"], f"{first['hr'][0]}x{first['hr'][1]}", first["tasks"],
                              f"{median(r['estimated_s'] for r in runs):.1f}", f"{median(r['job_s'] for r in runs):.1f}",
                              f"{ratio:.2f}", f"{median(r['estimated_bytes'] / r['bytes'] for r in runs):.3f}",
                              "PASS" if abs(ratio - 1) <= 0.25 else "FAIL"])
            per_frame = median(r["seconds_per_task_planned"] * r["tasks"] / r["frames"] for r in runs)
            whole = (4 * H) * (4 * W) / (first["hr"][0] * first["hr"][1])  # a region's cost scaled to whole frames
            cost_rows.append([f"{'TFP' if name == 'tfp' else 'lite (CPU)'}, whole frames",
                              f"{per_frame * whole:.2f} worker-s per output frame"
                              + (f" (a {first['hr'][0]}x{first['hr'][1]} region x{whole:.0f}: its halo makes "
                                 f"this an upper bound)" if whole > 1 else ""),
                              per_frame * whole * tb_windows])
    if plan_rows:
        print(markdown_table(["job", "output frames", "HR size", "tasks", "planned s", "job s", "planned / job",
                              "size planned / actual", "goal within 25 %"], plan_rows))
        print()
    for label, seconds in GPU_FORWARD_S.items():
        cost_rows.append([f"{label} on one H100 (forward pass)", f"{seconds:.3f} s per window (docs/gpu.md)",
                          seconds * tb_windows])
    print(f"### One terabyte ({TERABYTE_FRAMES:,} frames, {tb_windows:,.0f} output frames of {4 * H}x{4 * W})\n")
    print(markdown_table(["stage", "measured", "worker-hours", "hours on 8 workers", "hours on 64 workers"],
                         [[stage, measured, f"{total / 3600:.1f}", f"{total / 8 / 3600:.2f}", f"{total / 64 / 3600:.2f}"]
                          for stage, measured, total in cost_rows]))
    results["terabyte_worker_seconds"] = {stage: total for stage, _, total in cost_rows}
    print(f"\nLoad average at start {results['load_average'][0]}, at end {results['load_average'][1]}.")
    path = save_results("terabyte_rehearsal", results)
    print(f"\n(results: {path})")


if __name__ == "__main__":
    if sys.argv[1:2] == ["--capture-only"]:
        print(capture(int(sys.argv[2])))
    else:
        main()
