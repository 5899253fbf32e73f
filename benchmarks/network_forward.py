"""Forward time, peak memory and FLOPs of the CSCSR network, beside the classic TFP.

What: one forward pass (batch 1, x4, ``torch.inference_mode``) of ``lite`` and ``full``
(randomly initialised: time and memory do not depend on the weights) on a 41-frame RGGB
clip of LR 64x64, 180x320 (the paper's REDS size: 720x1280 output) and a 256x256 tile
(the pipeline's default tile; 320x320 with its 32-px halo is what a task really runs).
Reference in the same run: the classic TFP reconstructor (``stages.reconstruction.methods``: rate,
VNG demosaicking, bicubic x4, uint8) on the same packed window.

Each case runs in a fresh subprocess with ``torch.set_num_threads(--threads)`` (default:
every CPU), one warm-up pass, then ``--repeats`` timed passes (median). Peak memory is
the subprocess's peak resident set size, everything included (Python, torch, model,
input; the resident size before the first pass is recorded beside it as ``rss_before_mib``);
on a GPU, the peak of allocated device memory. FLOPs come from
``torch.utils.flop_counter`` (convolutions and matrix products, 2 per multiply-add;
``grid_sample`` and elementwise work are not counted) divided by output pixels.

The paper reports 1.032 s per 180x320 -> 720x1280 image for CSCSR on a GPU of its time.
On a GPU (``--device cuda``) the same cases run in fp32 and bf16 (autocast).

``--compile`` runs the network through ``torch.compile`` (the warm-up pass compiles; not timed).

``--channels-last`` runs the network on NHWC tensors (``cscsr.network.model.use_channels_last``).

Run: ``python benchmarks/network_forward.py [--repeats 3] [--device cpu|cuda] [--compile] [--channels-last]
[--sizes 180x320,...] [--configs lite,full] [--quick]``.
"""

import argparse
import json
import subprocess
import sys

from _common import ROOT, load_average, markdown_table, save_results

SIZES = {"64x64": (64, 64), "180x320": (180, 320), "256x256 tile": (256, 256)}
GPU_SIZES = {"180x320": (180, 320), "1000x1000": (1000, 1000)}  # the camera's own size
PAPER_SECONDS = 1.032


def one_case(config: str, height: int, width: int, repeats: int, device: str, dtype: str, threads: int,
             compile: bool = False, channels_last: bool = False) -> dict:
    """Runs inside the subprocess: time, peak memory and FLOPs of one configuration and size."""
    import resource
    import time

    import numpy as np
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    from cscsr.network.config import named
    from cscsr.network.model import CSCSR, use_channels_last
    from stages.capture.bits import pack_rows
    from stages.reconstruction.methods import Window, classic

    torch.set_num_threads(threads)
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    spikes = (rng.random((41, height, width)) < 0.2).astype(np.uint8)
    x = torch.from_numpy(spikes).float()[None].to(device)
    model = use_channels_last(CSCSR(named(config)).eval().to(device), channels_last)
    cfa = "mono" if model.config.mono else "rggb"  # a mono configuration (lite-mono) takes mono clips
    network = torch.compile(model) if compile else model

    def forward():
        with torch.inference_mode(), torch.autocast(device, torch.bfloat16, enabled=dtype == "bf16"):
            out = network(x, cfa, scale=4)["image"]
        if device == "cuda":
            torch.cuda.synchronize()
        return out

    def rss_mib() -> float:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * 4096 / 2**20

    before = rss_mib()
    if device == "cuda":
        torch.backends.cudnn.benchmark = True
        torch.cuda.reset_peak_memory_stats()
    forward()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        forward()
        times.append(time.perf_counter() - start)
    peak = (torch.cuda.max_memory_allocated() / 2**20 if device == "cuda"
            else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
    with FlopCounterMode(display=False) as counter:
        forward()
    flops = counter.get_total_flops()
    tfp = classic("tfp")
    window = Window(pack_rows(spikes), width, cfa, "subtract", 2.0, 4)
    tfp(window)
    tfp_times = []
    for _ in range(repeats):
        start = time.perf_counter()
        tfp(window)
        tfp_times.append(time.perf_counter() - start)
    counts = model.parameter_counts()
    return {"config": config, "size": f"{height}x{width}", "device": device, "dtype": dtype, "compile": compile,
            "channels_last": channels_last,
            "seconds": float(np.median(times)), "tfp_seconds": float(np.median(tfp_times)),
            "peak_mib": peak, "rss_before_mib": before, "gflops": flops / 1e9, "flops_per_output_pixel": flops / (16 * height * width),
            "parameters": counts["network"], "flow_parameters": counts["flow"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--quick", action="store_true", help="64x64 only, one repeat (a smoke run)")
    parser.add_argument("--compile", action="store_true", help="torch.compile the network (the warm-up compiles)")
    parser.add_argument("--channels-last", action="store_true", help="the network on NHWC tensors")
    parser.add_argument("--sizes", help="only these sizes, comma-separated labels (e.g. 180x320)")
    parser.add_argument("--configs", default="lite,full", help="configurations, comma-separated")
    parser.add_argument("--out", default=None, help="folder for the JSON results (default benchmarks/results)")
    parser.add_argument("--case", help=argparse.SUPPRESS)
    args = parser.parse_args()
    import os

    threads = args.threads or os.cpu_count()
    if args.case:
        print(json.dumps(one_case(**json.loads(args.case))))
        return
    sizes = {"64x64": SIZES["64x64"]} if args.quick else GPU_SIZES if args.device == "cuda" else SIZES
    if args.sizes:
        sizes = {label: {**SIZES, **GPU_SIZES}[label] for label in args.sizes.split(",")}
    repeats = 1 if args.quick else args.repeats
    dtypes = ["fp32", "bf16"] if args.device == "cuda" else ["fp32"]
    results = []
    for config in args.configs.split(","):
        for label, (h, w) in sizes.items():
            for dtype in dtypes:
                case = {"config": config, "height": h, "width": w, "repeats": repeats, "device": args.device,
                        "dtype": dtype, "threads": threads, "compile": args.compile,
                        "channels_last": args.channels_last}
                run = subprocess.run([sys.executable, __file__, "--case", json.dumps(case)], cwd=ROOT,
                                     capture_output=True, text=True)
                if run.returncode:
                    print(f"{config} {label} {dtype}: failed: {run.stderr.strip().splitlines()[-1:]}", flush=True)
                    continue
                results.append(json.loads(run.stdout.strip().splitlines()[-1]))
                r = results[-1]
                print(f"{config} {label} {dtype}: {r['seconds']:.3f} s", flush=True)
    rows = [[r["config"], r["size"], r["dtype"], f"{r['seconds']:.3f}", f"{r['seconds'] / r['tfp_seconds']:.0f}x",
             f"{r['peak_mib']:.0f}", f"{r['flops_per_output_pixel'] / 1e3:.1f} k", f"{r['gflops']:.1f}",
             f"{r['parameters'] / 1e6:.2f} M + {r['flow_parameters'] / 1e6:.2f} M"] for r in results]
    print()
    print(f"device {args.device}, {threads} threads, batch 1, x4, load average {load_average()}")
    print("paper: CSCSR 1.032 s per 180x320 image on a GPU of its time\n")
    print(markdown_table(["config", "LR size", "dtype", "forward s (median)", "vs TFP", "peak RSS MiB",
                          "FLOPs / output px", "GFLOPs", "params (net + flow)"], rows))
    save_results(f"network_forward_{args.device}{'_channels_last' if args.channels_last else ''}", {"threads": threads, "repeats": repeats, "cases": results,
                                                    "paper_seconds_180x320": PAPER_SECONDS},
                 **({"folder": args.out} if args.out else {}))


if __name__ == "__main__":
    main()
