"""The GPU lease's measurements of the network itself (#53, item 5), each run by ``gpu_prove.py`` in a process of its
own: ``python benchmarks/_gpu_measure.py {compile,bf16,micro} --device cuda --side 1000 --result FILE``.

- ``compile``: ``full`` bf16 with ``--fast-gpu`` (each repeated block compiled, ``dynamic=False``) on one window of
  ``--side``: the first pass (the compile, and cuDNN's autotuning), the compiled pass against the eager pass, and
  ``torch.profiler``'s top 25 kernels of each (by device time; CPU time on a CPU). First in the lease, so the
  compile's cost is known even if nothing else runs.
- ``bf16``: bf16 against fp32 on the device at ``--side`` (``lite`` and ``full``, the shipped weights, a still
  natural picture): PSNR, mean and largest difference in levels of the uint8 images.
- ``micro``: convolutions alone, the issue's questions: 96 -> 96 (3x3) NCHW against NHWC at ``--side``; the 3D
  convolution with 50 against 56 channels; 101 -> 50 against 104 -> 56, in the lease's precision (bf16).

Not a benchmark by itself (``run_all.py`` skips files whose name starts with ``_``). With ``--tiny`` (the CPU dry
run, tests/test_gpu_lease.py) the sizes are tiny and the compile uses torch.compile's ``eager`` backend (the same
tracing per block, no code generation), recorded as such.
"""

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cscsr.inference.reconstructor import compiled, load_reconstructor  # noqa: E402
from stages.reconstruction.colour import expose  # noqa: E402


def synchronise(device: str) -> None:
    if device == "cuda":
        torch.cuda.synchronize()


def timed(fn, device: str, repeats: int = 3) -> float:
    """Median seconds of ``repeats`` calls (after the device is idle)."""
    times = []
    for _ in range(repeats):
        synchronise(device)
        start = time.perf_counter()
        fn()
        synchronise(device)
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def natural_clip(side: int, cfa: str = "grbg", frames: int = 41, seed: int = 0) -> torch.Tensor:
    """(1, 41, side, side) spikes of a still natural picture (chelsea) through a Bayer CFA: tests/test_bf16_exact.py's
    clip, here too so that the GPU machine needs no pytest."""
    import skimage.data

    picture = skimage.data.chelsea()[:side, :side].astype(np.float32) / 255
    mosaic = np.empty((side, side), np.float32)
    for (dy, dx), c in zip([(0, 0), (0, 1), (1, 0), (1, 1)], cfa):
        mosaic[dy::2, dx::2] = picture[dy::2, dx::2, "rgb".index(c)]
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(1, frames, side, side, generator=g) < 0.05 + 0.6 * torch.from_numpy(mosaic)).float()


def window(side: int, device: str, dtype) -> torch.Tensor:
    """(1, 41, side, side) spikes of a still natural picture (:func:`natural_clip`, tiled)."""
    clip = natural_clip(min(side, 288))
    reps = -(-side // clip.shape[-1])
    return clip.repeat(1, 1, reps, reps)[..., :side, :side].to(device, dtype)


def top_kernels(run, device: str, count: int = 25) -> list[dict]:
    """``torch.profiler``'s top kernels of one call of ``run``, by device time (CPU time on a CPU)."""
    from torch.profiler import ProfilerActivity, profile

    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device == "cuda" else [])
    with profile(activities=activities) as prof:
        run()
        synchronise(device)
    key = "device_time_total" if device == "cuda" else "cpu_time_total"
    events = [e for e in prof.key_averages() if getattr(e, key, 0) > 0]
    events.sort(key=lambda e: -getattr(e, key))
    total = sum(getattr(e, "self_" + key, 0) for e in events) or 1
    return [{"name": e.key[:120], "calls": e.count, "ms": getattr(e, key) / 1e3,
             "self_share": getattr(e, "self_" + key, 0) / total} for e in events[:count]]


def measure_compile(args) -> dict:
    tiny = args.tiny
    config = "lite" if tiny else "full"  # the CPU dry run: the smaller network, so that it takes seconds
    network = load_reconstructor(config, args.device, precision="bf16")  # prepared as a GPU worker prepares it
    model = network.model
    x = window(args.side, args.device, model.dtype)

    def run():
        with torch.inference_mode(), network._autocast():
            return model(x, "grbg", False, 4)["image"]

    repeats = 1 if tiny else 3
    eager_s = timed(run, args.device, repeats)
    eager_top = top_kernels(run, args.device)
    start = time.perf_counter()
    compiled(model, backend="eager" if tiny else "inductor")
    synchronise(args.device)
    eager_image = run()
    first = time.perf_counter() - start  # the compile of every block at this shape, and the first pass
    fused_s = timed(run, args.device, repeats)
    fused_image = run()
    difference = (fused_image.float() - eager_image.float()).abs()
    backend = "eager (tiny dry run)" if tiny else "inductor"
    return {"config": config, "precision": "bf16", "lr_side": args.side, "compile_backend": backend,
            "compile_and_first_pass_s": first, "eager_pass_s": eager_s, "compiled_pass_s": fused_s,
            "compiled_over_eager": eager_s / fused_s, "largest_difference": float(difference.max()),
            "top25_eager": eager_top, "top25_compiled": top_kernels(run, args.device)}


def measure_bf16(args) -> dict:
    runs = []
    for config in ("lite",) if args.tiny else ("lite", "full"):
        images = {}
        for precision in ("fp32", "bf16"):
            network = load_reconstructor(config, args.device, precision=precision)
            x = window(args.side, args.device, network.model.dtype)
            with torch.inference_mode(), network._autocast():
                image = network.model(x, "grbg", False, 4)["image"]
            images[precision] = expose(image[0].permute(1, 2, 0).float().cpu().numpy(), 1.5).astype(np.float64)
            del network
        difference = np.abs(images["fp32"] - images["bf16"])
        mse = float((difference**2).mean())
        runs.append({"config": config, "lr_side": args.side, "psnr_db": 10 * np.log10(255**2 / mse) if mse else None,
                     "mean_abs_levels": float(difference.mean()), "max_abs_levels": float(difference.max()),
                     "goal_met": bool((not mse or 10 * np.log10(255**2 / mse) >= 40) and difference.mean() <= 1)})
    return {"runs": runs}


def measure_micro(args) -> dict:
    dtype = torch.float32 if args.tiny else torch.bfloat16
    side, device = args.side, args.device
    cases = {}

    def conv_case(name, cin, cout, layout, dims=2, size=side):
        conv = (torch.nn.Conv2d if dims == 2 else torch.nn.Conv3d)(cin, cout, 3, 1, 1).to(device, dtype)
        shape = (1, cin, size, size) if dims == 2 else (1, cin, 11, size, size)
        x = torch.randn(shape, device=device, dtype=dtype)
        if layout == "nhwc":
            memory = torch.channels_last if dims == 2 else torch.channels_last_3d
            conv, x = conv.to(memory_format=memory), x.contiguous(memory_format=memory)
        with torch.inference_mode():
            conv(x)  # autotuning, if on
            seconds = timed(lambda: conv(x), device, 5)
        flops = 2 * cin * cout * 9 * (3 if dims == 3 else 1) * x[0, 0].numel()
        cases[name] = {"ms": seconds * 1e3, "tflops": flops / seconds / 1e12}

    torch.backends.cudnn.benchmark = device == "cuda"
    conv_case("conv 96->96 NCHW", 96, 96, "nchw")
    conv_case("conv 96->96 NHWC", 96, 96, "nhwc")
    small = max(8, side // 2)  # the 3D convolution over 11 time points at half the side: its memory in bounds
    conv_case("conv3d 50->50 NDHWC", 50, 50, "nhwc", 3, small)
    conv_case("conv3d 56->56 NDHWC", 56, 56, "nhwc", 3, small)
    conv_case("conv 101->50 NHWC", 101, 50, "nhwc")
    conv_case("conv 104->56 NHWC", 104, 56, "nhwc")
    return {"dtype": str(dtype).replace("torch.", ""), "lr_side": side, "cases": cases}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("what", choices=["compile", "bf16", "micro"])
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--side", type=int, default=1000)
    parser.add_argument("--result", required=True)
    parser.add_argument("--tiny", action="store_true")
    args = parser.parse_args()
    started = time.perf_counter()
    result = {"compile": measure_compile, "bf16": measure_bf16, "micro": measure_micro}[args.what](args)
    result["seconds"] = time.perf_counter() - started
    Path(args.result).write_text(json.dumps(result, indent=1))
    print(json.dumps({k: v for k, v in result.items() if not k.startswith("top25")})[:2000], flush=True)


if __name__ == "__main__":
    main()
