"""bf16 against fp32 through the shipped network at a production-sized tile (issue #53's goal: LR 512x512,
shipped ``lite``, uint8 after exposure, >= 40 dB and mean <= 1 level). On the CPU (bf16 autocast) or CUDA.

Run: ``python benchmarks/bf16_tolerance.py [--side 512] [--config lite] [--device cpu] [--json]``.
"""

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cscsr.weights.weights_io import default_weights, load_model  # noqa: E402
from stages.reconstruction.colour import expose  # noqa: E402
from tests.test_bf16_exact import natural_clip  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--side", type=int, default=512)
    parser.add_argument("--config", default="lite")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    model, _ = load_model(default_weights(args.config), args.device)
    spikes = natural_clip(min(args.side, 300), seed=0)  # chelsea is 300 px high: tiled up to the side
    reps = -(-args.side // spikes.shape[-1])
    spikes = spikes.repeat(1, 1, reps, reps)[..., : args.side, : args.side].to(args.device)
    images, seconds = {}, {}
    with torch.inference_mode():
        for precision in ("fp32", "bf16"):
            start = time.perf_counter()
            with torch.autocast(args.device, dtype=torch.bfloat16, enabled=precision == "bf16"):
                image = model(spikes, "grbg", False, 4)["image"]
            seconds[precision] = time.perf_counter() - start
            images[precision] = expose(image[0].permute(1, 2, 0).float().cpu().numpy(), 1.5).astype(np.float64)
    difference = np.abs(images["fp32"] - images["bf16"])
    result = {"config": args.config, "lr_side": args.side, "device": args.device,
              "psnr_db": float(10 * np.log10(255**2 / (difference**2).mean())),
              "mean_abs_levels": float(difference.mean()), "max_abs_levels": float(difference.max()),
              "seconds": seconds}
    result["goal_met"] = result["psnr_db"] >= 40 and result["mean_abs_levels"] <= 1
    print(json.dumps(result) if args.json else "\n".join(f"{k}: {v}" for k, v in result.items()))


if __name__ == "__main__":
    main()
