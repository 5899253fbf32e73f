"""Prove the GPU path in one command on a lent GPU (issue #46): ``gpu_lease.py prove`` runs this.

A lease is 15 minutes of device time in all, so this is one prepared command of at most ``--budget``
seconds (default 510) that writes everything to ``--out`` (``$OUT``), ``prove.json`` after every step,
so that a step that hangs or fails costs only itself (each runs in its own process under its own time
limit, cut to what is left of the budget; a step that would not fit is recorded as skipped):

0. ``compile-full``, ``bf16-1000``, ``micro`` (#53; ``benchmarks/_gpu_measure.py``): ``full``'s compile with
   ``--fast-gpu`` first (per block, ``dynamic=False``), so that its cost is known, with the compiled pass against
   the eager one and ``torch.profiler``'s top 25 kernels of each at 1000x1000; bf16 against fp32 at 1000x1000 on
   the device; convolution micro-benchmarks (96->96 NCHW against NHWC, Conv3d 50 against 56 channels, 101->50
   against 104->56). ``pipeline-full-bf16-fast`` (after step 2's eager jobs) is the job with ``--fast-gpu``
   (job frames/s per mode);
1. ``smoke``: ``lite`` and ``full`` through the device-side path (``NetworkReconstructor.many``:
   packed bits in, uint8 out), fp32 and bf16, on two 41-frame windows of a clip simulated by the
   simulator of record (LR ``--smoke-side``, x4), each compared with
   - the same network's host path on the same device (numpy unpacking, float spikes to the device,
     numpy exposure: :func:`host_path`): **the same bytes** (the device steps are exact twins);
   - the CPU path's bytes (fp32 on the CPU, one thread, as a CPU worker runs it): within
     :data:`TOLERANCE` for the precision (fp32 on CUDA differs by TF32 and kernel choice; bf16 as the
     bf16-against-fp32 test on the CPU allows);
2. ``pipeline-full-bf16``, ``pipeline-lite-bf16``: ``benchmarks/gpu_pipeline.py`` (the Dask job on one
   GPU worker, 1000x1000 LR x4, ``--frames`` output frames, the forward pass alone beside it, FLOP/s and
   the share of the chip's bf16 peak, the worker's and the forward pass's peak GPU memory), one
   configuration per step, merged into ``gpu_pipeline.json``;
3. ``smoke-fast-gpu``: step 1 with ``--fast-gpu`` (channels-last, cuDNN autotuning, ``torch.compile``),
   ``full`` first, each also compared with the eager device path's bytes;
4. ``pipeline-full-fp32``, ``pipeline-lite-fp32``: if time is left.

Every step records the device's memory high-water mark (``nvidia-smi``'s ``memory.used``, sampled every
0.2 s, all processes) beside torch's own peaks. The recording for the pipeline steps is simulated in
the background (CPU only) while the first smoke step runs.

On the CPU (``--device cpu --tiny``: tests/test_gpu_lease.py) the same steps run on tiny sizes, so the
command cannot rot; there the device path and the CPU path are one and the bytes must be equal.

Run: ``python benchmarks/gpu_lease.py prove --out $OUT [--budget 510] [--only STEP,...] [--configs lite,full]
[--precisions fp32,bf16]``.
"""

import argparse
import contextlib
import dataclasses
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
WINDOW, SCALE = 41, 4
# What the device's bytes may differ from the CPU path's (uint8 HR images, levels of 255): fp32 on a GPU
# runs its convolutions in TF32 and other kernels; bf16 is held to what bf16 against fp32 is held to on the
# CPU at production tile sizes (#53: float32 sampling positions; tests/test_bf16_exact.py, docs/gpu.md).
TOLERANCE = {"fp32": {"psnr_db": 40.0, "mean_abs_levels": 1.0}, "bf16": {"psnr_db": 40.0, "mean_abs_levels": 1.0}}
# --fast-gpu against the eager device path of the same precision: float rounding only.
FAST_TOLERANCE = {"psnr_db": 45.0, "mean_abs_levels": 0.5}
GOALS = {"pipeline_share_of_forward": 0.85, "full_bf16_frames_per_second": 11.0, "lite_bf16_frames_per_second": 30.0,
         "forward_share_of_bf16_peak": 0.20}  # #53: full bf16 >= 11 output frames/s through the job, lite >= 30


@dataclass(frozen=True)
class Step:
    name: str
    limit_s: float  # its own time limit
    least_s: float  # not started with less left than this
    kind: str  # "smoke", "pipeline" or "measure" (benchmarks/_gpu_measure.py ``what``)
    configs: tuple = ("lite", "full")
    precisions: tuple = ("fp32", "bf16")
    fast_gpu: bool = False
    what: str = ""


STEPS = (  # in this order; limits from the first lease (H200, 2026-11-27: docs/measurements/h200-2026-11-27)
    # #53: full's compile first (per block, dynamic=False), so its cost is known; then the network's own figures
    Step("compile-full", 240, 90, "measure", ("full",), ("bf16",), what="compile"),  # 55 s (H200, lease 3)
    Step("smoke", 120, 40, "smoke"),  # took 10-23 s
    Step("bf16-1000", 90, 30, "measure", ("lite", "full"), ("bf16",), what="bf16"),  # 4 passes at 1000x1000
    Step("micro", 60, 20, "measure", ("full",), ("bf16",), what="micro"),
    Step("pipeline-full-bf16", 170, 90, "pipeline", ("full",), ("bf16",)),  # 126 s
    Step("pipeline-lite-bf16", 120, 60, "pipeline", ("lite",), ("bf16",)),  # 70 s
    # after the eager job (lease 3: a slow compile must not cost the eager figures); compile cached by then
    Step("pipeline-full-bf16-fast", 200, 100, "pipeline", ("full",), ("bf16",), fast_gpu=True),  # compile cached
    # torch.compile: about 65 s a configuration and precision (lite); full first, lite was proved then
    Step("smoke-fast-gpu", 240, 90, "smoke", ("full", "lite"), ("bf16", "fp32"), fast_gpu=True),
    Step("pipeline-full-fp32", 240, 150, "pipeline", ("full",), ("fp32",)),  # not done in 150 s
    Step("pipeline-lite-fp32", 130, 80, "pipeline", ("lite",), ("fp32",)),  # not done in 60 s
)


# --- the smoke step (in its own process) ---

def smoke_windows(side: int):
    """Two 41-frame windows of side x side LR at x4: a clip of a natural picture simulated by the simulator of
    record (``cscsr.training.training_data.random_clip``), as recorded and reversed in time; same CFA, reset, gain."""
    import numpy as np

    from cscsr.training.training_data import random_clip
    from stages.capture.bits import pack_rows
    from stages.reconstruction.methods import Window

    clip = random_clip([46, 0], lr_side=side, scale=SCALE)
    spikes = clip.spikes.astype(np.uint8)  # (41, side, side) 0/1
    reset = "zero" if clip.zero_reset else "subtract"
    return [Window(pack_rows(np.ascontiguousarray(s)), side, clip.cfa, reset, 1.0 / clip.alpha, SCALE)
            for s in (spikes, spikes[::-1])]


def host_path(network, windows) -> list:
    """The same network on the same device by the host path: numpy unpacking, float32 spikes to the device,
    the float32 image back, numpy exposure (what ``many`` did before the device-side steps)."""
    import numpy as np
    import torch

    from cscsr.inference.reconstructor import one_thread_on_cpu
    from stages.capture.bits import unpack_rows
    from stages.reconstruction.colour import expose

    first = windows[0]
    spikes = np.stack([unpack_rows(w.packed, w.width) for w in windows])
    with one_thread_on_cpu(network.device), torch.inference_mode(), network._autocast():
        x = torch.from_numpy(spikes).to(network.device, torch.float32)
        rate = network._seen_under(0, x, first).permute(0, 2, 3, 1).float().cpu().numpy()
    return [expose(r, first.gain) for r in rate]


def compare(images, reference) -> dict:
    """uint8 images against reference images: equal bytes, PSNR (dB), mean and largest difference (levels)."""
    import numpy as np

    a = np.stack(images).astype(np.float64)
    b = np.stack(reference).astype(np.float64)
    difference = np.abs(a - b)
    mse = float((difference**2).mean())
    return {"equal_bytes": bool(mse == 0), "psnr_db": float(10 * np.log10(255**2 / mse)) if mse else None,  # None: equal
            "mean_abs_levels": float(difference.mean()), "max_abs_levels": float(difference.max()),
            "share_within_one_level": float((difference <= 1).mean())}


def within(figures: dict, tolerance: dict) -> bool:
    return (figures["psnr_db"] is None or figures["psnr_db"] >= tolerance["psnr_db"]) and figures["mean_abs_levels"] <= tolerance["mean_abs_levels"]


def smoke(args) -> None:
    """Each configuration x precision through the device path on ``args.device``, against the CPU path's bytes
    (and, with ``--fast-gpu``, the eager device path's); the result file rewritten after each."""
    import torch

    from cscsr.inference.reconstructor import load_reconstructor

    result_file = Path(args.result)
    windows = smoke_windows(args.smoke_side)
    results = {"windows": len(windows), "lr_side": args.smoke_side, "cfa": windows[0].cfa, "reset": windows[0].reset,
               "tolerance": TOLERANCE, "runs": []}
    cuda = args.device == "cuda"
    for config in args.configs.split(","):
        cpu = load_reconstructor(config, "cpu", precision="fp32").many(windows)  # the CPU path, one thread
        for precision in args.precisions.split(","):
            run = {"config": config, "precision": precision, "fast_gpu": args.fast_gpu, "device": args.device}
            try:
                if cuda:
                    torch.cuda.reset_peak_memory_stats()
                start = time.perf_counter()
                network = load_reconstructor(config, args.device, precision=precision, fast_gpu=args.fast_gpu)
                run["load_seconds"] = time.perf_counter() - start
                start = time.perf_counter()
                images = network.many(windows)  # the first pass: cuDNN autotuning, torch.compile
                run["first_pass_seconds"] = time.perf_counter() - start
                start = time.perf_counter()
                again = network.many(windows)
                run["second_pass_seconds"] = time.perf_counter() - start
                run["repeatable"] = compare(again, images)["equal_bytes"]
                run["against_cpu_path"] = compare(images, cpu)
                run["within_tolerance_of_cpu"] = within(run["against_cpu_path"], TOLERANCE[precision])
                if args.fast_gpu:
                    eager = load_reconstructor(config, args.device, precision=precision).many(windows)
                    run["against_eager_device_path"] = compare(images, eager)
                    run["within_tolerance_of_eager"] = within(run["against_eager_device_path"], FAST_TOLERANCE)
                else:
                    run["against_host_path"] = compare(images, host_path(network, windows))
                run["gpu_peak_mib"] = torch.cuda.max_memory_allocated() / 2**20 if cuda else None
                run["ok"] = bool(run["within_tolerance_of_cpu"] and run["repeatable"] and (
                    run["within_tolerance_of_eager"] if args.fast_gpu else run["against_host_path"]["equal_bytes"]))
                del network
            except Exception as error:  # reported, and the next configuration goes on
                run["ok"], run["error"] = False, f"{type(error).__name__}: {error}"[:2000]
            if cuda:
                torch.cuda.empty_cache()
            results["runs"].append(run)
            print(json.dumps(run), flush=True)
            result_file.write_text(json.dumps(results, indent=1))
    if not all(run["ok"] for run in results["runs"]):
        sys.exit(1)


# --- the orchestrator ---

class MemoryWatch:
    """The device's memory in use (``nvidia-smi``, all processes, MiB), its largest value while running."""

    def __init__(self, period: float = 0.2):
        self.period, self.most, self._stop = period, None, threading.Event()
        self._thread = threading.Thread(target=self._poll, daemon=True)

    def _poll(self):
        while not self._stop.is_set():
            with contextlib.suppress(OSError, ValueError, subprocess.SubprocessError):
                used = subprocess.run(["nvidia-smi", "--query-gpu=memory.used", "--format=csv,noheader,nounits"],
                                      capture_output=True, text=True, timeout=5).stdout.split()
                if used:
                    self.most = max(self.most or 0, max(int(u) for u in used))
            self._stop.wait(self.period)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join(timeout=10)


def device_description(device: str) -> dict:
    import torch

    described = {"device": device, "torch": torch.__version__, "python": platform.python_version(),
                 "cpus": os.cpu_count(), "platform": platform.platform()}
    if device == "cuda":
        props = torch.cuda.get_device_properties(0)
        described |= {"gpu": props.name, "gpu_memory_gib": round(props.total_memory / 2**30, 1),
                      "multiprocessors": props.multi_processor_count, "cuda": torch.version.cuda}
        with contextlib.suppress(OSError, subprocess.SubprocessError):
            described["driver"] = subprocess.run(
                ["nvidia-smi", "--query-gpu=driver_version", "--format=csv,noheader"], capture_output=True,
                text=True, timeout=10).stdout.strip()
    return described


def sizes(args) -> dict:
    if args.tiny:
        return {"side": 32, "frames": 1, "repeats": 1, "smoke_side": 16}  # measure steps: smoke_side
    return {"side": args.side, "frames": args.frames, "repeats": args.repeats, "smoke_side": args.smoke_side}


def step_command(step: Step, args, size: dict, result: Path) -> list[str]:
    python = sys.executable
    if step.kind == "measure":
        return [python, str(HERE / "_gpu_measure.py"), step.what, "--device", args.device, "--side",
                str(size["smoke_side"] if args.tiny else size["side"]), "--result", str(result)] + (
            ["--tiny"] if args.tiny else [])
    if step.kind == "smoke":
        return [python, str(HERE / "gpu_prove.py"), "_smoke", "--device", args.device, "--result", str(result),
                "--configs", ",".join(step.configs), "--precisions", ",".join(step.precisions),
                "--smoke-side", str(size["smoke_side"])] + (["--fast-gpu"] if step.fast_gpu else [])
    return [python, str(HERE / "gpu_pipeline.py"), "--device", args.device, "--side", str(size["side"]),
            "--frames", str(size["frames"]), "--repeats", str(size["repeats"]), "--configs", ",".join(step.configs),
            "--precisions", ",".join(step.precisions), "--merge", "--out", str(args.out)] + (
        ["--fast-gpu"] if step.fast_gpu else [])


def recording_command(size: dict) -> list[str]:
    """Simulate (and cache) the pipeline steps' recording, as gpu_pipeline.py would, on the CPU alone."""
    code = (f"import sys; sys.path.insert(0, {str(HERE)!r}); from _gpu_recording import cached_recording; "
            f"print(cached_recording({size['side']}, {WINDOW * size['frames']}))")
    return [sys.executable, "-c", code]


def step_result(step: Step, args, result: Path):
    """What a finished (or stopped) step measured: the smoke step's file, or its runs in gpu_pipeline.json."""
    if step.kind in ("smoke", "measure"):
        return json.loads(result.read_text()) if result.exists() else None
    path = Path(args.out) / "gpu_pipeline.json"
    if not path.exists():
        return None
    runs = [r for r in json.loads(path.read_text()).get("runs", [])
            if r["config"] in step.configs and r["precision"] in step.precisions
            and bool(r.get("fast_gpu")) == step.fast_gpu]
    keep = ("config", "precision", "fast_gpu", "tile", "forward_batch", "pipeline_frames_per_second", "forward_frames_per_second",
            "reconstructor_frames_per_second", "pipeline_share_of_forward", "forward_tflops_per_second",
            "forward_share_of_bf16_peak", "gpu_hours_per_terabyte", "worker_gpu_peak_mib", "forward_gpu_peak_mib")
    return [{k: r.get(k) for k in keep} for r in runs] or None


def goals(report: dict) -> dict:
    """The issue's goals against what the pipeline steps measured (absent where not measured)."""
    runs = {(r["config"], r["precision"], bool(r.get("fast_gpu"))): r for s in report["steps"].values()
            if s.get("kind") == "pipeline" for r in (s.get("result") or [])}
    out = {}
    for (config, precision, fast), run in sorted(runs.items()):
        name = f"{config}-{precision}" + ("-fast-gpu" if fast else "")
        out[f"{name}: pipeline / forward >= {GOALS['pipeline_share_of_forward']}"] = \
            run["pipeline_share_of_forward"] >= GOALS["pipeline_share_of_forward"]
        if run.get("forward_share_of_bf16_peak") is not None and precision == "bf16":
            out[f"{name}: forward >= {GOALS['forward_share_of_bf16_peak']:.0%} of the bf16 peak"] = \
                run["forward_share_of_bf16_peak"] >= GOALS["forward_share_of_bf16_peak"]
        goal = GOALS.get(f"{config}_{precision}_frames_per_second")
        if goal:
            out[f"{name}: pipeline >= {goal} frames/s"] = run["pipeline_frames_per_second"] >= goal
    return out


def chosen_steps(args) -> list[Step]:
    """The steps named by ``--only`` (default all), each cut to ``--configs`` and ``--precisions`` where given;
    a step left with no configuration or precision is dropped."""
    steps = [s for s in STEPS if not args.only or s.name in args.only.split(",")]
    if args.configs:
        steps = [dataclasses.replace(s, configs=tuple(c for c in s.configs if c in args.configs.split(",")))
                 for s in steps]
    if args.precisions:
        steps = [dataclasses.replace(s, precisions=tuple(p for p in s.precisions if p in args.precisions.split(",")))
                 for s in steps]
    return [s for s in steps if s.configs and s.precisions]


def prove(args) -> dict:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    started = time.monotonic()
    deadline = started + args.budget
    size = sizes(args)
    chosen = chosen_steps(args)
    report = {"issue": 46, "started": time.strftime("%Y-%m-%d %H:%M:%S %Z"), "budget_seconds": args.budget,
              "sizes": size, "machine": device_description(args.device), "steps": {}}
    report_path, log_path = out / "prove.json", out / "prove.log"
    work = Path(tempfile.mkdtemp(prefix="cscsr-prove-"))  # the smoke steps' result files, read back into the report

    def save():
        report["seconds_so_far"] = round(time.monotonic() - started, 1)
        report["goals"] = goals(report)
        report_path.write_text(json.dumps(report, indent=1) + "\n")

    save()
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH")) if p)
    recording = None
    with open(log_path, "a") as log:
        # simulated on the CPU while the smoke step uses the GPU; not where no pipeline step could fit the budget
        if any(s.kind == "pipeline" and s.least_s <= args.budget for s in chosen):
            log.write(f"\n=== recording: {' '.join(recording_command(size))}\n")
            log.flush()
            recording = subprocess.Popen(recording_command(size), stdout=log, stderr=subprocess.STDOUT, cwd=ROOT,
                                         env=dict(env, CUDA_VISIBLE_DEVICES=""))
        for step in chosen:
            left = deadline - time.monotonic()
            entry = report["steps"][step.name] = {"kind": step.kind, "configs": step.configs,
                                                  "precisions": step.precisions, "fast_gpu": step.fast_gpu}
            if left < step.least_s:
                entry |= {"status": "skipped", "why": f"{left:.0f} s of the budget left, the step needs "
                                                      f"{step.least_s:.0f} s or more"}
                save()
                continue
            limit = min(step.limit_s, left)
            begun = time.monotonic()
            if step.kind == "pipeline" and recording is not None:
                try:
                    recording.wait(timeout=limit)
                except subprocess.TimeoutExpired:
                    recording.kill()
                    entry |= {"status": "timeout", "why": "the recording was not simulated within the step's limit"}
                    save()
                    continue
                if recording.returncode:
                    entry |= {"status": "failed", "why": f"simulating the recording failed ({recording.returncode})"}
                    save()
                    continue
            result = work / f"{step.name}.json"
            command = step_command(step, args, size, result)
            log.write(f"\n=== {step.name} (limit {limit - (time.monotonic() - begun):.0f} s): {' '.join(command)}\n")
            log.flush()
            with MemoryWatch() as memory:
                child = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT, env=env,
                                         start_new_session=True)
                try:
                    code = child.wait(timeout=max(1.0, limit - (time.monotonic() - begun)))
                    entry["status"] = "ok" if code == 0 else "failed"
                    entry["exit_code"] = code
                except subprocess.TimeoutExpired:
                    with contextlib.suppress(ProcessLookupError):
                        os.killpg(child.pid, 9)  # the step and the Dask workers it started
                    child.wait()
                    entry["status"] = "timeout"
            entry["seconds"] = round(time.monotonic() - begun, 1)
            entry["device_memory_used_peak_mib"] = memory.most
            entry["result"] = step_result(step, args, result)
            print(f"{step.name}: {entry['status']} in {entry['seconds']} s", flush=True)
            save()
        if recording is not None and recording.poll() is None:
            recording.kill()
    shutil.rmtree(work, ignore_errors=True)
    return report


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("mode", nargs="?", default="prove", choices=["prove", "_smoke"])
    parser.add_argument("--out", default=os.environ.get("OUT", str(ROOT / "benchmarks" / "results" / "prove")))
    parser.add_argument("--device", choices=["cuda", "cpu"], default=None,
                        help="default: cuda where torch sees a GPU, else cpu")
    parser.add_argument("--budget", type=float, default=510, help="seconds for all steps (default 510: with the "
                        "processes' start, within 9 minutes)")
    parser.add_argument("--only", default="", help=f"steps to run, comma-separated: {','.join(s.name for s in STEPS)}")
    parser.add_argument("--side", type=int, default=1000, help="the pipeline's LR side (default 1000)")
    parser.add_argument("--frames", type=int, default=40, help="the pipeline's output frames (default 40)")
    parser.add_argument("--repeats", type=int, default=2, help="the pipeline's timed runs (default 2)")
    parser.add_argument("--smoke-side", type=int, default=64, help="the smoke windows' LR side (default 64)")
    parser.add_argument("--tiny", action="store_true", help="tiny sizes (a CPU dry run)")
    parser.add_argument("--configs", default="", help="only these configurations (lite,full; default both)")
    parser.add_argument("--precisions", default="", help="only these precisions (fp32,bf16; default both)")
    # the smoke step's own options (run by the orchestrator in a process of its own)
    parser.add_argument("--result", default="")
    parser.add_argument("--fast-gpu", action="store_true")
    args = parser.parse_args(argv)
    import torch

    args.device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
    if args.device == "cuda" and not torch.cuda.is_available():
        parser.error("--device cuda: torch sees no GPU")
    unknown = set(filter(None, args.only.split(","))) - {s.name for s in STEPS}
    if unknown:
        parser.error(f"--only: no step named {', '.join(sorted(unknown))}")
    for option, allowed in (("configs", {"lite", "full"}), ("precisions", {"fp32", "bf16"})):
        if set(filter(None, getattr(args, option).split(","))) - allowed:
            parser.error(f"--{option}: one or more of {', '.join(sorted(allowed))}")
    if args.mode == "_smoke":
        args.configs, args.precisions = args.configs or "lite,full", args.precisions or "fp32,bf16"
        smoke(args)
        return
    report = prove(args)
    failed = [name for name, step in report["steps"].items() if step["status"] not in ("ok", "skipped")]
    print(json.dumps({"goals": report["goals"], "failed": failed}, indent=1))
    print(f"(results: {Path(args.out) / 'prove.json'})")


if __name__ == "__main__":
    main()
