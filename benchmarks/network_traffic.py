"""Every byte of one forward pass, counted on the CPU as GPU workers run it, scaled to 1000x1000 LR x4 (issue #53).

What: one forward pass (batch 1, x4) of ``lite`` and ``full`` (the shipped weights) prepared exactly as a GPU
worker prepares it (``cscsr.inference.reconstructor.prepare_model`` for a CUDA device, the same precision
context: ``precision_context``), counted op by op at the dispatch level (``benchmarks/_traffic.py``) at two
small LR sizes and extrapolated, op by op and linearly in pixels, to 1008x1008 (what a 1000x1000 frame is
padded to). Per output frame:

- ``tflop_per_frame``: convolutions and matrix products, 2 per multiply-add;
- ``gb_per_frame``: bytes read and written by all operations (10^9; bf16 tensors at 2 bytes);
- ``cast_gb_per_frame``: of which dtype casts (``.to()``, autocast's casts); ``fp32_gb_per_frame``: of which
  operations (not casts) with float32 outputs;
- ``nhwc_conv_flop_share``, ``aligned_conv_flop_share``: the share of convolution FLOPs whose input is stored
  NHWC, and whose channel counts (in per group, out) are multiples of 8;
- ``top_operations``: operations (by ATen name and output dtype) by their roofline time on an H100;
- ``roofline_frames_per_second`` for an H100 and an H200: each operation takes the longer of its FLOPs at
  the bf16 dense tensor-core peak and its bytes at the memory bandwidth (:data:`PEAKS`), summed.

The count starts at the network's input (spikes in the network's dtype) and ends at its image: the unpacking
of the bits and the exposure to uint8 around it are not counted. Kernels' own internals (cuDNN's workspaces,
conversions it makes inside a convolution) are not seen.

Run: ``python benchmarks/network_traffic.py [--json] [--configs lite,full] [--precision bf16] [--sizes 64,128]``.
"""

import argparse
import json
import sys
from collections import defaultdict

from _common import markdown_table, random_window, save_results
from _traffic import count, extrapolate

# bf16 dense tensor-core peak (FLOP/s) and memory bandwidth (bytes/s), from NVIDIA's data sheets (SXM)
PEAKS = {"H100": {"bf16_flops": 989.4e12, "bytes_per_s": 3.35e12},
         "H200": {"bf16_flops": 989.4e12, "bytes_per_s": 4.8e12}}
TARGET_SIDE = 1008  # 1000 padded to a multiple of 16, as the network runs it
SCALE = 4


def prepared(config: str, precision: str):
    """The shipped ``config`` network as a GPU worker runs it in ``precision`` (padded, channels-last)."""
    from cscsr.inference.reconstructor import prepare_model
    from cscsr.weights.weights_io import default_weights, load_model

    model, _ = load_model(default_weights(config))
    return prepare_model(model.eval(), "cuda", precision, channels_last=True)


def counted(model, precision: str, side: int):
    import torch

    from cscsr.inference.reconstructor import precision_context

    spikes = torch.from_numpy(random_window(side, model.config.frames))
    spikes = spikes.to(model.dtype)  # as the device path unpacks them (the network's dtype)
    if getattr(model, "channels_last", False):
        spikes = spikes.contiguous(memory_format=torch.channels_last)

    def run():
        with torch.inference_mode(), precision_context("cpu", precision, model):
            model(spikes, "mono" if model.config.mono else "rggb", False, SCALE)["image"]

    run()  # warm: lazily made constants are not counted
    return count(run)


def roofline_seconds(op, peak: dict) -> float:
    return max(op.flop / peak["bf16_flops"], op.bytes / peak["bytes_per_s"])


def summary(ops, top: int) -> dict:
    conv = [o for o in ops if o.conv_nhwc is not None]
    conv_flop = sum(o.flop for o in conv) or 1
    groups = defaultdict(lambda: {"gb": 0.0, "tflop": 0.0, "h100_ms": 0.0, "calls": 0})
    for o in ops:
        g = groups[f"{o.name} ({o.dtype})"]
        g["gb"] += o.bytes / 1e9
        g["tflop"] += o.flop / 1e12
        g["h100_ms"] += roofline_seconds(o, PEAKS["H100"]) * 1e3
        g["calls"] += 1
    ranked = sorted(groups.items(), key=lambda kv: -kv[1]["h100_ms"])[:top]
    return {
        "tflop_per_frame": sum(o.flop for o in ops) / 1e12,
        "gb_per_frame": sum(o.bytes for o in ops) / 1e9,
        "cast_gb_per_frame": sum(o.bytes for o in ops if o.cast) / 1e9,
        "fp32_gb_per_frame": sum(o.bytes for o in ops if o.dtype == "float32" and not o.cast) / 1e9,
        "convolutions": len(conv),
        "nhwc_conv_flop_share": sum(o.flop for o in conv if o.conv_nhwc) / conv_flop,
        "aligned_conv_flop_share": sum(o.flop for o in conv if o.conv_aligned) / conv_flop,
        "unaligned_convolutions": sorted({str(o.shape) for o in conv if not o.conv_aligned}),
        "nchw_convolutions": sorted({str(o.shape) for o in conv if not o.conv_nhwc}),
        "roofline_frames_per_second": {gpu: 1 / sum(roofline_seconds(o, peak) for o in ops)
                                       for gpu, peak in PEAKS.items()},
        "top_operations": [{"op": name, **{k: round(v, 3) for k, v in g.items()}} for name, g in ranked],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print the JSON only")
    parser.add_argument("--configs", default="lite,full")
    parser.add_argument("--precision", default="bf16", choices=["bf16", "fp32"])
    parser.add_argument("--sizes", default="64,128", help="the two LR sides counted (multiples of 16)")
    parser.add_argument("--top", type=int, default=10)
    args = parser.parse_args()
    small, large = (int(s) for s in args.sizes.split(","))
    results = {"precision": args.precision, "lr_side": TARGET_SIDE, "scale": SCALE, "counted_at": [small, large],
               "peaks": PEAKS, "configs": {}}
    for config in args.configs.split(","):
        model = prepared(config, args.precision)
        ops = extrapolate(counted(model, args.precision, small), counted(model, args.precision, large),
                          (small * small, large * large), TARGET_SIDE * TARGET_SIDE)
        results["configs"][config] = summary(ops, args.top)
    save_results("network_traffic", results)
    if args.json:
        print(json.dumps(results, indent=1))
        return
    rows = [[name, f"{r['tflop_per_frame']:.2f}", f"{r['gb_per_frame']:.1f}", f"{r['cast_gb_per_frame']:.1f}",
             f"{r['fp32_gb_per_frame']:.1f}", f"{r['nhwc_conv_flop_share']:.0%}", f"{r['aligned_conv_flop_share']:.0%}",
             f"{r['roofline_frames_per_second']['H100']:.1f}", f"{r['roofline_frames_per_second']['H200']:.1f}"]
            for name, r in results["configs"].items()]
    print(markdown_table(["config", "TFLOP/frame", "GB/frame", "casts GB", "fp32 GB", "NHWC conv FLOPs",
                          "aligned conv FLOPs", "roofline H100 frames/s", "roofline H200 frames/s"], rows))
    for name, r in results["configs"].items():
        print(f"\n{name}: top operations by roofline time on an H100")
        print(markdown_table(["op", "GB", "TFLOP", "ms (H100)", "calls"],
                             [[t["op"], t["gb"], t["tflop"], t["h100_ms"], t["calls"]] for t in r["top_operations"]]))


if __name__ == "__main__":
    sys.exit(main())
