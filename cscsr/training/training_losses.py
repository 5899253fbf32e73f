"""What a training step optimises and how a run is scored while it trains.

The loss: L1 on the HR rate image plus ``flow_weight`` times L1 of the two key flows against the
simulator's exact flows; one optimiser step (gradients norm-clipped, Adam), with bf16 autocast on
request; and the validation PSNR of the network and of its TFP base image on held-out clips.
"""

import math

import numpy as np
import torch

from cscsr.network.model import CSCSR
from cscsr.training.training_batches import to_tensors
from cscsr.training.training_options import TrainOptions


def autocast(options: TrainOptions):
    """bf16 autocast on the run's device when ``--precision bf16``, else nothing."""
    device = torch.device(options.device).type
    return torch.autocast(device, torch.bfloat16, enabled=options.precision == "bf16")


def losses(model: CSCSR, batch: dict, flow_weight: float,
           options: TrainOptions | None = None) -> tuple[torch.Tensor, dict]:
    with autocast(options or TrainOptions()):
        out = model(batch["spikes"], batch["cfa"], batch["zero_reset"], batch["scale"])
    image = (out["image"].float() - batch["truth"]).abs().mean()
    total, parts = image, {"l1": image.item()}
    if out["flows"] is not None and flow_weight > 0:
        flow = sum((f.float() - batch["flows"][:, k]).abs().mean() for k, f in enumerate(out["flows"])) / 2
        total = total + flow_weight * flow
        parts["flow"] = flow.item()
    return total, parts


def optimiser_step(model: CSCSR, optimiser: torch.optim.Optimizer, batch: dict,
                   options: TrainOptions) -> tuple[torch.Tensor, dict]:
    """One step on ``batch``: the losses, their gradients (norm clipped to ``options.clip``), Adam."""
    optimiser.zero_grad(set_to_none=True)
    loss, parts = losses(model, batch, options.flow_weight, options)
    loss.backward()
    torch.nn.utils.clip_grad_norm_(model.parameters(), options.clip)
    optimiser.step()
    return loss, parts


def psnr_intensity(rate: torch.Tensor, truth: torch.Tensor, alpha: torch.Tensor) -> float:
    """PSNR of intensities I = rate / alpha clipped to [0, 1], as the images would be written."""
    a = (rate / alpha[:, None, None, None]).clamp(0, 1)
    b = (truth / alpha[:, None, None, None]).clamp(0, 1)
    mse = ((a - b) ** 2).mean().item()
    return 10 * math.log10(1 / max(mse, 1e-12))


def validate(model: CSCSR, batches: list[dict], device: str = "cpu") -> tuple[float, float]:
    """Mean PSNR of the network and of its TFP base image on the validation clips (fp32 on any device)."""
    model.eval()
    scores, bases = [], []
    with torch.inference_mode():
        for batch in batches:
            t = to_tensors(batch, device)
            out = model(t["spikes"], t["cfa"], t["zero_reset"], t["scale"])
            scores.append(psnr_intensity(out["image"], t["truth"], t["alpha"]))
            bases.append(psnr_intensity(out["base"], t["truth"], t["alpha"]))
    model.train()
    return float(np.mean(scores)), float(np.mean(bases))
