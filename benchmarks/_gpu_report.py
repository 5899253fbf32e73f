"""What ``gpu_pipeline.py`` prints and writes: its markdown tables and ``gpu_pipeline.json``.

:func:`print_stand_in` (the CPU proxy's figures against its goals), :func:`print_network` (the real
network's frames/s, FLOP/s and GPU-hours per terabyte) and :func:`save` (the JSON, with the machine's
description; ``--merge`` keeps other configurations' runs).
"""

import contextlib
import json
import os
import platform
from pathlib import Path

from _common import markdown_table, median
from _gpu_proxy_mode import GOAL_CPU_PER_FRAME, GOAL_JOB_OVER_STAND_IN
from _gpu_recording import OUTPUT_FRAMES_PER_TB, SCALE, WINDOW


def save(folder: Path, data: dict, merge: bool = False) -> Path:
    """``folder/gpu_pipeline.json`` with the machine's description beside the data; with ``merge``, the runs
    already there of configurations not measured now are kept."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "gpu_pipeline.json"
    if merge and path.exists() and "runs" in data:
        key = lambda run: (run["config"], run["precision"], run.get("fast_gpu", False))  # noqa: E731
        now = {key(run) for run in data["runs"]}
        data["runs"] = [r for r in json.loads(path.read_text()).get("runs", []) if key(r) not in now] + data["runs"]
    machine = {"cpus": os.cpu_count(), "cpu": cpu_model(), "python": platform.python_version(),
               "platform": platform.platform(), "load_average_at_end": os.getloadavg()}
    path.write_text(json.dumps({"benchmark": "gpu_pipeline", "machine": machine, **data}, indent=2) + "\n")
    return path


def cpu_model() -> str:
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor()


def verdict(value: float, goal: float) -> str:
    return "PASS" if value <= goal else "FAIL"


def print_stand_in(result: dict, args) -> None:
    s = args.stand_in
    job, cpu = result["job_seconds_per_frame_runs"], result["non_network_cpu_seconds_per_frame_runs"]
    rows = [["job seconds per output frame", f"{result['job_seconds_per_frame']:.3f}",
             f"{min(job):.3f} - {max(job):.3f}", f"<= {GOAL_JOB_OVER_STAND_IN * s:.3f} (1.15 x {s})",
             verdict(result["job_seconds_per_frame"], GOAL_JOB_OVER_STAND_IN * s)],
            ["worker CPU seconds per output frame", f"{result['non_network_cpu_seconds_per_frame']:.3f}",
             f"{min(cpu):.3f} - {max(cpu):.3f}", f"<= {GOAL_CPU_PER_FRAME}",
             verdict(result["non_network_cpu_seconds_per_frame"], GOAL_CPU_PER_FRAME)],
            ["of which system (kernel) CPU", f"{median(result['of_which_system_cpu_seconds_per_frame_runs']):.3f}",
             "", "", ""],
            ["device busy share", f"{result['device_busy_share']:.2f}", "", "", ""]]
    first = result["device_busy"][len(result["device_busy"]) // 2]
    middle = len(result["device_busy"]) // 2
    idle = (f"the device idle {first['before_first_pass_seconds']:.2f} s before the first pass, "
            f"{first['idle_between_passes_seconds']:.2f} s between passes and {first['after_last_pass_seconds']:.2f} s "
            f"after the last ({first['passes']} passes of {first['windows_per_pass']} windows); the job's first task "
            f"began {result['job_before_first_task_seconds_runs'][middle]:.2f} s after the job, which ended "
            f"{result['job_after_last_task_seconds_runs'][middle]:.2f} s after its last task")
    print(f"## GPU pipeline, CPU proxy: stand-in of {s} s per window, {result['path']} path\n")
    print(f"{args.frames} output frames of {args.side}x{args.side} RGGB -> x{SCALE}, tile {result['tile']}, "
          f"{result['chunks_written']} chunks written, {result['worker_threads']} worker thread(s) "
          f"({result['cluster']}), "
          f"{result['output_bytes_per_frame'] / 1e6:.1f} MB per output frame at rest; medians of {args.repeats}; "
          f"in the middle run {idle}.\n")
    print(markdown_table(["figure", "median", "range", "goal", ""], rows))
    if "profile_cpu_seconds_per_frame" in result:
        profile = result["profile_cpu_seconds_per_frame"]
        steps = [[name, f"{v['cpu']:.3f}", f"{v['wall']:.3f}"] for name, v in profile.items() if isinstance(v, dict)]
        print(f"\nOne task's steps, here, one after the other ({profile['frames_per_task']} frames), "
              f"per output frame:\n")
        print(markdown_table(["step", "CPU s", "wall s"], steps))
    if "picture_against_network" in result:
        against = result["picture_against_network"]
        rows = [[name, f"{v['bytes_per_hr_pixel']:.2f}", f"{1000 * v['seconds_per_hr_megapixel']:.1f}"]
                for name, v in against.items() if isinstance(v, dict)]
        print(f"\nThe stand-in's picture against the network's output ({against['lr_side']}x{against['lr_side']} LR, "
              f"zstd level 1, one thread):\n")
        print(markdown_table(["image", "bytes per HR pixel", "ms per HR megapixel"], rows))


def print_network(result: dict, args) -> None:
    rows = [[r["config"], r["precision"], r["tile"], f"{r['forward_frames_per_second']:.2f}",
             f"{r['reconstructor_frames_per_second']:.2f}", f"{r['pipeline_frames_per_second']:.2f}",
             f"{100 * r['pipeline_share_of_forward']:.0f} %", f"{r['forward_tflops_per_second']:.1f}",
             f"{100 * r['forward_share_of_bf16_peak']:.1f} %" if r["forward_share_of_bf16_peak"] else "-",
             f"{r['gpu_hours_per_terabyte']:.1f}"] for r in result["runs"]]
    print(f"## GPU pipeline: {args.frames} output frames of {args.side}x{args.side} RGGB -> x{SCALE} on "
          f"{result['device']}{' (' + result['gpu'] + ')' if result['gpu'] else ''}\n")
    print(markdown_table(["config", "precision", "tile", "forward frames/s", "reconstructor frames/s",
                          "pipeline frames/s", "pipeline / forward", "forward TFLOP/s", "of bf16 peak",
                          "GPU-hours per TB"], rows))
    print(f"\nGPU-hours per terabyte: {OUTPUT_FRAMES_PER_TB:,} output frames (8 M spike frames, one per {WINDOW}) "
          f"at the pipeline's frames/s. Medians of {args.repeats}. Goals (H100): pipeline >= 85 % of the forward "
          f"pass; full bf16 >= 6 frames/s; lite >= 15.")
    if result.get("cli_seconds") is not None:
        print(f"The command line, cold ({result['runs'][0]['config']}): {result['cli_seconds']:.1f} s.")
