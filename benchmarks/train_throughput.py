"""Training throughput of CSCSR, in clips per second, beside the cost of simulating a clip.

What: for each configuration and LR crop side, ``--repeats`` timed optimiser steps (after two
warm-up steps) of exactly what ``cscsr train`` does per step (``cscsr.training.training_losses.optimiser_step``:
forward, L1 image and flow losses, backward, gradient clipping, Adam) on a batch of ``--batch`` x4
clips from a pool, median. References in the same run: the forward pass alone on the same
batch (``torch.inference_mode``; a step costs about three of them) and the simulation of one
clip (``cscsr.training.training_data.random_clip``, on one core), which is why ``cscsr train --pool``
simulates clips once and reuses them. Threads: every CPU (``--threads``); on a GPU
(``--device cuda``) the same in fp32.

Run: ``python benchmarks/train_throughput.py [--configs lite,full] [--sides 24,48]
[--batch 8] [--repeats 5] [--device cpu|cuda]`` (about 4 minutes for lite at 24 and 48 on 2 cores).
"""

import argparse
import os
import time

import torch

from _common import load_average, markdown_table, median, save_results
from cscsr.network.config import named
from cscsr.network.model import CSCSR
from cscsr.training.train import TrainOptions
from cscsr.training.training_batches import to_tensors
from cscsr.training.training_data import batch_arrays, random_clip
from cscsr.training.training_losses import optimiser_step


def synchronised(device: str) -> None:
    if device == "cuda":
        torch.cuda.synchronize()


def one_case(config: str, side: int, batch: int, repeats: int, device: str) -> dict:
    """Median seconds of a training step, a forward pass and a clip's simulation; clips per second."""
    simulated = []
    clips = []
    for i in range(batch):
        start = time.perf_counter()
        clips.append(random_clip([0, 996, i], lr_side=side, scale=4))
        simulated.append(time.perf_counter() - start)
    tensors = to_tensors(batch_arrays(clips))
    tensors = {k: v.to(device) if isinstance(v, torch.Tensor) else v for k, v in tensors.items()}
    torch.manual_seed(0)
    model = CSCSR(named(config)).to(device).train()
    optimiser = torch.optim.Adam(model.parameters(), lr=1e-4)
    options = TrainOptions(config=config, batch=batch, lr_side=side)

    def step() -> None:
        optimiser_step(model, optimiser, tensors, options)

    def forward() -> None:
        with torch.inference_mode():
            model(tensors["spikes"], tensors["cfa"], tensors["zero_reset"], tensors["scale"])

    timings = {}
    for name, work in (("step", step), ("forward", forward)):
        for _ in range(2):
            work()
        synchronised(device)
        seconds = []
        for _ in range(repeats):
            start = time.perf_counter()
            work()
            synchronised(device)
            seconds.append(time.perf_counter() - start)
        timings[name] = seconds
    step_s, forward_s, clip_s = median(timings["step"]), median(timings["forward"]), median(simulated)
    return {"config": config, "lr_side": side, "batch": batch, "step_s": step_s, "forward_s": forward_s,
            "simulate_clip_s": clip_s, "clips_per_s": batch / step_s, "step_over_forward": step_s / forward_s,
            "simulate_over_step_per_clip": clip_s / (step_s / batch), "timings": timings, "simulated": simulated}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--configs", default="lite")
    parser.add_argument("--sides", default="24,48")
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    parser.add_argument("--threads", type=int, default=None)
    args = parser.parse_args()
    threads = args.threads or os.cpu_count()
    torch.set_num_threads(threads)
    cases = [one_case(config, int(side), args.batch, args.repeats, args.device)
             for config in args.configs.split(",") for side in args.sides.split(",")]
    print(f"device {args.device}, {threads} threads, batch {args.batch}, x4, load average {load_average()}")
    print(markdown_table(
        ["config", "LR crop", f"step s (median of {args.repeats})", "clips / s", "step ÷ forward",
         "simulating a clip, s", "simulating ÷ training, per clip"],
        [[c["config"], f"{c['lr_side']}×{c['lr_side']}", f"{c['step_s']:.2f}", f"{c['clips_per_s']:.2f}",
          f"{c['step_over_forward']:.1f}", f"{c['simulate_clip_s']:.2f}", f"{c['simulate_over_step_per_clip']:.2f}"]
         for c in cases]))
    save_results(f"train_throughput_{args.device}", {"threads": threads, "repeats": args.repeats, "cases": cases})


if __name__ == "__main__":
    main()
