"""Training clips synthesised in torch, batched, on the training device: no CPU pool on a GPU.

The CPU draws each clip's plan (``cscsr.training.training_data.random_plan``: the scene crop, the camera
path, the sensor) and the cheap per-pixel randomness of the numpy simulator of record
(initial integrator state, dark current, the shot-noise normals, all from the same
``default_rng`` streams as ``stages.simulation.sensor``) and the exact flows (closed form, at LR). The
device does the heavy part for the whole batch:

    scene (B, 3, S, S)                                       S = scale * (lr + 2 * margin)
      -> warp along the path, frames 0..40  (B, 3, s*lr, s*lr) per frame, clip's area only
         (M_t(p) = c + A(t)(p - c) + T(t) + U(t, p), bicubic, reflect-101, clipped to [0, 1])
      -> area downsample x s                (B, 3, lr, lr)
      -> CFA mosaic                         (B, lr, lr)     -> (B, 41, lr, lr)
      -> increments round(clip(a*I/theta)*2^24) (+ dark current and shot noise)
      -> integrate and fire, zero or subtract reset per clip  (B, 41, lr, lr) 0/1
    truth = alpha * frame 20 at HR          (B, 3, s*lr, s*lr)

Given the same mosaics, increments and spikes are bit-identical to ``stages.simulation.sensor`` (tested on
the CPU, both resets, with noise). Rendering uses ``grid_sample`` where the simulator uses
``cv2.remap``: frames agree to about 2e-5 (measured), so a clip's spikes are the simulator's
except where that difference crosses a threshold; the tests allow one pixel in a thousand, and
none differed in the clips measured (both resets, noise, deformed paths, all CFA phases).
"""

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from cscsr.training.frame_motion import FrameMotion
from cscsr.training.training_data import FRAMES, MIDDLE, ClipPlan
from stages.reconstruction.cfa import colour_index
from stages.simulation.sensor import UNITS, dark_increments, initial_state, shot_normals


@dataclass(frozen=True)
class SensorDraws:
    """A clip's per-pixel random numbers, drawn on the CPU exactly as ``stages.simulation.sensor`` draws them."""

    state: np.ndarray  # (lr, lr) int64 initial accumulator
    dark: np.ndarray | None  # (lr, lr) float32 dark increment per frame in theta; None without noise
    shot: np.ndarray | None  # (41, lr, lr) float32 standard normals of the shot noise; None without noise


def sensor_draws(plan: ClipPlan) -> SensorDraws:
    sensor, side = plan.sensor, plan.lr_side
    if sensor.noise == "none":
        return SensorDraws(initial_state(sensor, side, side), None, None)
    shot = np.empty((FRAMES, side, side), np.float32)
    for t in range(FRAMES):
        shot_normals(sensor, t, out=shot[t])
    return SensorDraws(initial_state(sensor, side, side), dark_increments(sensor, side, side), shot)


@dataclass(frozen=True)
class PreparedBatch:
    """What the CPU hands the device for one batch: plans, their draws and their flows."""

    plans: list
    draws: list
    flows: np.ndarray  # (B, 2, 2, lr, lr) float32


def prepare(plans: list[ClipPlan]) -> PreparedBatch:
    """The CPU's share of a batch (a background thread runs it while the device trains)."""
    scales, sides = {p.scale for p in plans}, {(p.lr_side, p.picture.shape[0]) for p in plans}
    if len(scales) != 1 or len(sides) != 1:
        raise ValueError(f"a batch needs one scale and one size, got scales {scales}, sizes {sides}")
    return PreparedBatch(plans, [sensor_draws(p) for p in plans], np.stack([p.flows() for p in plans]))


def synthesise(batch: PreparedBatch, device: torch.device | str) -> dict:
    """The batch's clips as tensors on ``device``, keyed as the trainer's batches (``cscsr.training.training_batches.to_tensors``)."""
    plans = batch.plans
    device = torch.device(device)
    scale, side = plans[0].scale, plans[0].lr_side
    scenes = torch.from_numpy(np.stack([p.picture for p in plans])).to(device).permute(0, 3, 1, 2)  # (B, 3, S, S)
    alpha = torch.tensor([p.sensor.brightness for p in plans], dtype=torch.float64, device=device)  # (B,)
    channel = torch.from_numpy(np.stack([colour_index(p.cfa, side, side) for p in plans]).astype(np.int64))
    channel = channel.clamp(min=0).to(device)[:, None]  # (B, 1, lr, lr): 0 R, 1 G, 2 B; mono (-1) reads R of its
    # grey scene (``random_plan(mono=True)`` turns the scene to luma: R = G = B = what the mono sensor sees)

    footage = footage_tensors(plans, device)
    mosaics, truth = [], None
    for t in range(FRAMES):
        frame = render(scenes, plans, t, footage)  # (B, 3, s*lr, s*lr)
        if t == MIDDLE:
            truth = (alpha[:, None, None, None].float() * frame).contiguous()
        mosaics.append(F.avg_pool2d(frame, scale).gather(1, channel)[:, 0])  # (B, lr, lr)
    mosaics = torch.stack(mosaics, 1)  # (B, 41, lr, lr)

    q = increments(mosaics, plans, batch.draws, device)  # (B, 41, lr, lr) int64
    state = torch.from_numpy(np.stack([d.state for d in batch.draws])).to(device)
    zero = torch.tensor([p.zero_reset for p in plans], device=device)
    spikes = fire(q, state, zero)
    return {"spikes": spikes.float(), "truth": truth, "flows": torch.from_numpy(batch.flows).to(device),
            "zero_reset": zero, "alpha": alpha.float(), "cfa": [p.cfa for p in plans], "scale": scale}


def sample_grid(plans: list[ClipPlan], t: float, device: torch.device) -> torch.Tensor:
    """(B, s*lr, s*lr, 2) grid_sample coordinates of frame t over each clip's area of its scene.

    ``stages.simulation.camera_path.CameraPath.sample_map`` in float64, for the clip's pixels alone.
    """
    plan = plans[0]
    size, first = plan.picture.shape[0], plan.margin * plan.scale
    centre = (size - 1) / 2
    pixels = torch.arange(first, first + plan.lr_side * plan.scale, dtype=torch.float64, device=device) - centre
    y, x = torch.meshgrid(pixels, pixels, indexing="ij")  # (h, w) centred coordinates
    affine = []
    for p in plans:
        matrix, shift = p.path._affine(t)
        affine.append([*matrix.ravel(), *shift])
    a, b, c, d, tx, ty = torch.tensor(affine, dtype=torch.float64, device=device).T[..., None, None]  # (B, 1, 1) each
    qx, qy = a * x + b * y + tx, c * x + d * y + ty  # (B, h, w)
    waves = max(len(p.path.deformation) for p in plans)
    if waves:
        table = np.zeros((len(plans), waves, 6))
        for i, p in enumerate(plans):
            if p.path.deformation:
                table[i, : len(p.path.deformation)] = p.path.deformation
        ax, ay, kx, ky, omega, phase = torch.tensor(table, device=device).permute(2, 0, 1)[..., None, None]
        argument = kx * x + ky * y + (omega * t + phase)  # (B, waves, h, w)
        qx = qx + (ax * torch.sin(argument)).sum(1)
        qy = qy + (ay * torch.sin(argument)).sum(1)
    # source pixel q + centre, normalised for align_corners=True: -1 at pixel 0, +1 at pixel size - 1
    return (torch.stack([qx, qy], -1) / centre).float()


def render(scenes: torch.Tensor, plans: list[ClipPlan], t: float, footage: dict | None = None) -> torch.Tensor:
    """(B, 3, S, S) scenes -> (B, 3, s*lr, s*lr) latent frame t over each clip's area, in [0, 1]: clips on a camera
    path warped along it, clips of footage (``footage_tensors``) interpolated between their frames."""
    moving = [i for i, p in enumerate(plans) if not isinstance(p.path, FrameMotion)]
    if len(moving) == len(plans):
        return _sample(scenes, sample_grid(plans, t, scenes.device))
    frame = torch.empty((len(plans), 3, *[plans[0].lr_side * plans[0].scale] * 2), device=scenes.device)
    if moving:
        index = torch.tensor(moving, device=scenes.device)
        frame[index] = _sample(scenes[index], sample_grid([plans[i] for i in moving], t, scenes.device))
    frame[footage["index"]] = interpolate(scenes[footage["index"]], footage, plans[0], t)
    return frame


def _sample(images: torch.Tensor, grid: torch.Tensor, clip: bool = True) -> torch.Tensor:
    """grid_sample as ``cv2.remap`` with bicubic, BORDER_REFLECT_101, clipped to [0, 1] unless ``clip`` is False."""
    frame = F.grid_sample(images, grid, mode="bicubic", padding_mode="reflection", align_corners=True)
    return frame.clamp(0, 1) if clip else frame


def footage_tensors(plans: list[ClipPlan], device: torch.device) -> dict | None:
    """The neighbouring frames and flows of the batch's clips of footage on ``device`` (None if there are none):
    index (F,), before and after (F, 3, S, S), flow_before and flow_after (F, S, S, 2) over the whole scene."""
    index = [i for i, p in enumerate(plans) if isinstance(p.path, FrameMotion)]
    if not index:
        return None
    moves = [plans[i].path for i in index]
    tensors = {"index": torch.tensor(index, device=device)}
    for side in ("before", "after"):
        tensors[side] = torch.from_numpy(np.stack([getattr(m, side) for m in moves])).to(device).permute(0, 3, 1, 2)
        tensors[f"flow_{side}"] = torch.from_numpy(np.stack([getattr(m, f"flow_{side}") for m in moves])).to(device)
    return tensors


def interpolate(centres: torch.Tensor, footage: dict, plan: ClipPlan, t: float) -> torch.Tensor:
    """(F, 3, S, S) centre frames -> (F, 3, s*lr, s*lr) frame t over the clip's area, interpolated along the flow
    between the centre and a neighbour: (1 - a) A(p - a f(p)) + a B(p + (1 - a) f(p)) (``FrameMotion.render``)."""
    a, side = FrameMotion.towards(t, FRAMES)
    size, first, count = plan.picture.shape[0], plan.margin * plan.scale, plan.lr_side * plan.scale
    area = slice(first, first + count)
    if a == 0:
        return centres[..., area, area]
    flow = footage[f"flow_{side}"][:, area, area].double()  # (F, n, n, 2)
    pixels = torch.arange(first, first + count, dtype=torch.float64, device=centres.device)
    y, x = torch.meshgrid(pixels, pixels, indexing="ij")
    p = torch.stack([x, y], -1)  # (n, n, 2) pixel (x, y)

    def grid(offset):  # pixel p + offset -> align_corners=True coordinates
        return ((p + offset) / (size - 1) * 2 - 1).float()

    blend = (1 - a) * _sample(centres, grid(-a * flow), False) + a * _sample(footage[side], grid((1 - a) * flow), False)
    return blend.clamp(0, 1)


def increments(mosaics: torch.Tensor, plans: list[ClipPlan], draws: list[SensorDraws],
               device: torch.device) -> torch.Tensor:
    """(B, 41, lr, lr) intensities -> int64 increments in units, as ``stages.simulation.sensor.increments``."""
    gain = torch.tensor([p.sensor.brightness / p.sensor.threshold * UNITS for p in plans], dtype=torch.float64,
                        device=device)[:, None, None, None]
    signal = (mosaics.double() * gain).nan_to_num(0.0).clamp(0, UNITS)  # clip(a*I/theta, 0, 1) * UNITS
    noisy = [i for i, d in enumerate(draws) if d.shot is not None]
    if noisy:
        dark = torch.from_numpy(np.stack([draws[i].dark for i in noisy])).to(device).double()[:, None] * UNITS
        shot = torch.from_numpy(np.stack([draws[i].shot for i in noisy])).to(device).double()
        per_electron = torch.tensor([UNITS / plans[i].sensor.electrons_per_threshold for i in noisy],
                                    dtype=torch.float64, device=device)[:, None, None, None]
        mean = signal[noisy] + dark
        signal = signal.index_copy(0, torch.tensor(noisy, device=device),
                                   (mean + torch.sqrt(mean * per_electron) * shot).round())
    return signal.round().clamp(0, UNITS).long()


def fire(q: torch.Tensor, state: torch.Tensor, zero_reset: torch.Tensor) -> torch.Tensor:
    """Integrate and fire (B, N, H, W) increments from (B, H, W) states, threshold 2^24 units:
    ``acc += q``, a spike at ``acc >= thr``, then 0 (zero reset) or ``acc - thr`` (subtract)."""
    acc, zero = state.clone(), zero_reset[:, None, None]
    spikes = torch.empty(q.shape, dtype=torch.bool, device=q.device)
    for t in range(q.shape[1]):
        acc = acc + q[:, t]
        fired = acc >= UNITS
        spikes[:, t] = fired
        acc = torch.where(fired, torch.where(zero, torch.zeros_like(acc), acc - UNITS), acc)
    return spikes

