"""Training clips per second: the torch synthesis (cscsr.training.synthesis) against the numpy simulator.

What: the same batch of ``--batch`` x4 clip plans (``cscsr.training.training_data.random_plan``, LR side
``--side``) made three ways, median of ``--repeats``:

* numpy: ``run_plan`` per clip, the simulator of record (``stages``), as ``cscsr train`` on the CPU;
* torch on the CPU: ``synthesise(prepare(plans), "cpu")`` (sensor draws and flows included, as in numpy);
* torch on the GPU, when there is one (``--device cuda``): ``synthesise`` alone, the device's part of
  what ``cscsr train --device cuda`` does (``prepare`` runs in worker processes there).

The CPU's share of on-device synthesis (``random_plan`` + ``prepare``: scene crops, dead leaves,
sensor draws, flows) is timed apart: on a GPU it runs in worker processes beside training.
Reference in the same run: one training step of ``--config`` on that batch (forward, losses,
backward, Adam), so the table also gives the share of a step that data would cost if made in line.

Run: ``python benchmarks/synthesis_throughput.py [--batch 8] [--side 32] [--repeats 3] [--device cpu|cuda]``
(about a minute on 2 cores).
"""

import argparse
import time

import torch

from _common import load_average, markdown_table, median, save_results
from cscsr.network.config import named
from cscsr.network.model import CSCSR
from cscsr.training.synthesis import prepare, synthesise
from cscsr.training.train import TrainOptions
from cscsr.training.training_data import random_plan, run_plan
from cscsr.training.training_losses import optimiser_step


def timed(work, repeats: int, device: str = "cpu") -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        work()
        if device == "cuda":
            torch.cuda.synchronize()
        times.append(time.perf_counter() - start)
    return median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--side", type=int, default=32)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--config", default="lite")
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    args = parser.parse_args()
    batch, side = args.batch, args.side

    def plans():
        return [random_plan([0, 994, i], lr_side=side, scale=4) for i in range(batch)]

    planned = plans()
    prepared = prepare(planned)
    rows, results = [], {}
    results["numpy_s"] = timed(lambda: [run_plan(p) for p in planned], args.repeats)
    results["cpu_share_s"] = timed(lambda: prepare(plans()), args.repeats)
    synthesise(prepared, "cpu")
    results["torch_cpu_s"] = timed(lambda: synthesise(prepare(planned), "cpu"), args.repeats)
    if args.device == "cuda":
        synthesise(prepared, "cuda")
        results["torch_cuda_s"] = timed(lambda: synthesise(prepared, "cuda"), args.repeats, "cuda")

    options = TrainOptions(config=args.config, batch=batch, lr_side=side, device=args.device)
    model = CSCSR(named(args.config)).to(args.device).train()
    optimiser = torch.optim.Adam(model.parameters(), lr=1e-4)
    tensors = synthesise(prepared, args.device)
    optimiser_step(model, optimiser, tensors, options)
    results["step_s"] = timed(lambda: optimiser_step(model, optimiser, tensors, options), args.repeats, args.device)

    step = results["step_s"]
    for label, key in (("numpy simulator (stages), in line", "numpy_s"),
                       ("torch synthesis on the CPU, in line", "torch_cpu_s"),
                       ("torch synthesis on the GPU (+ CPU share in worker processes)", "torch_cuda_s"),
                       ("CPU share of on-device synthesis alone (plans, draws, flows)", "cpu_share_s")):
        if key in results:
            seconds = results[key]
            rows.append([label, f"{seconds:.3f}", f"{batch / seconds:.1f}", f"{seconds / (seconds + step):.0%}"])
    print(f"{batch} clips of LR {side}x{side} at x4, {args.repeats} repeats (median); training step of "
          f"{args.config} on {args.device}: {step:.3f} s; load average {load_average()}\n")
    print(markdown_table(["clips made by", "s per batch", "clips / s", "share of step + data"], rows))
    save_results(f"synthesis_throughput_{args.device}", {"batch": batch, "side": side, "config": args.config,
                                                         "repeats": args.repeats, **results})


if __name__ == "__main__":
    main()
