"""Training CSCSR on clips simulated on the fly, with resumable checkpoints.

Each step draws a batch from its own seed (``[seed, step, i]``), so a resumed run sees
exactly the clips an uninterrupted one would. Loss: L1 on the HR rate image plus
``flow_weight`` times L1 of the two key flows against the simulator's exact flows (the
motion is synthetic, so its truth is known). Adam with the sibling paper's step decay, gradients clipped.
Batches are prepared by background threads while the network trains on the previous one; on a
GPU the clips themselves are synthesised there (``cscsr.training.synthesis``), with bf16 autocast on
request, and ``time_budget`` ends a run cleanly before a command limit.
A checkpoint (weights and optimiser state, safetensors: no pickle) is written atomically
every ``checkpoint_every`` steps; the validation PSNR (fixed held-out clips) is logged to
``log.jsonl`` and printed on the progress line.

The parts, by purpose: ``cscsr.training.training_options`` (``TrainOptions`` and its checks, importable from here too),
``cscsr.training.training_batches`` (the clips of each step, made ahead), ``cscsr.training.training_losses`` (losses, one
optimiser step, validation), ``cscsr.training.training_state`` (checkpoints and resuming); here the loop itself
(``train``) and the exports of a run's checkpoint (``export_weights``, ``export_portable``).
"""

import json
import math
import os
import time
import uuid
import warnings
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch

from cscsr.network.config import CSCSRConfig
from cscsr.network.model import CSCSR, use_channels_last
from cscsr.training.training_batches import _prefetch, clip_pool, to_tensors, training_pictures, validation_batches
from cscsr.training.training_data import TRAIN_PICTURES
from cscsr.training.training_losses import optimiser_step, validate
from cscsr.training.training_options import TrainOptions
from cscsr.training.training_state import (initial_weights, load_checkpoint, model_weights, read_checkpoint, resumable,
                                  save_checkpoint)
from cscsr.weights.weights_io import save_weights
from stages.errors import InputError, exists_error, not_ours_error


def learning_rate_factor(step: int, options: TrainOptions) -> float:
    """Linear warm-up, then x0.9 every ``decay_every`` steps."""
    return min(1.0, (step + 1) / options.warmup) * 0.9 ** (step // options.decay_every)


def train(options: TrainOptions, out: str | os.PathLike, *, resume: bool = False, log=print,
          command: str = "") -> Path:
    """Train into folder ``out``; returns the path of the final weights file.

    With ``options.time_budget`` the run stops early, cleanly, when the next steps and the final
    checkpoint, validation and weights would not fit before the budget: a command limit (a GPU
    lease's 10 minutes) then ends a run that ``--resume`` continues exactly.
    """
    began = time.perf_counter()
    options = options.check()
    out = Path(out)
    checkpoint = out / "checkpoint.safetensors"
    if out.exists() and not out.is_dir():
        raise InputError(f"{out} is a file, not a training folder: choose another OUT")
    if out.exists() and any(out.iterdir()) and not resume:
        if not (out / "log.jsonl").exists() and not any(out.glob("checkpoint*.safetensors")):  # portable parts too
            raise InputError(f"{out} holds files of another kind, not a training run: choose another OUT")
        raise InputError(f"{out} already exists: pass --resume to continue its training")
    resume_from = resumable(out) if resume else None  # refused before any output
    start = initial_weights(options) if options.init and not resume else None  # refused before any output
    pictures = training_pictures(options)  # refused before any output too
    out.mkdir(parents=True, exist_ok=True)
    device = torch.device(options.device)
    if device.type == "cuda":
        torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = True
        torch.backends.cudnn.benchmark = True
    torch.manual_seed(options.seed)
    model = CSCSR(options.network()).train()
    if start is not None:
        model.load_state_dict(start)
    model.to(device)
    use_channels_last(model, options.channels_last)
    optimiser = torch.optim.Adam(model.parameters(), lr=options.learning_rate)
    step = load_checkpoint(resume_from, model, optimiser, options) if resume else 0
    if resume_from == out:
        log(f"resumed at step {step} from the portable checkpoint in {out} (close to, not bit-exactly, "
            "where the run was: its Adam moments were stored in bfloat16)")
    if step >= options.steps:  # nothing to train: said, and no pool simulated for it
        log(f"already at step {step} of --steps {options.steps}: nothing to train (give more --steps to go on)")
    for group in optimiser.param_groups:  # the schedule scales the configured rate, not a restored one
        group["lr"] = options.learning_rate
        group.pop("initial_lr", None)
    schedule = torch.optim.lr_scheduler.LambdaLR(optimiser, lambda n: learning_rate_factor(n, options))
    with warnings.catch_warnings():  # fast-forwarding the schedule before any optimiser step is intended here
        warnings.simplefilter("ignore", UserWarning)
        for _ in range(step):  # a resumed run continues the schedule where it stopped
            schedule.step()
    validation = validation_batches(options)
    pool = None
    if options.pool and step < options.steps:
        log(f"simulating a pool of {options.pool} clips")
        pool = clip_pool(options)
    batches = _prefetch(step, options, pool, pictures)
    started, seen, recent = time.perf_counter(), 0, []
    budget = Budget(options.time_budget, began)
    while step < options.steps:
        tick = time.perf_counter()
        loss, parts = optimiser_step(model, optimiser, to_tensors(next(batches), options.device), options)
        schedule.step()
        step += 1
        seen += options.batch
        recent = (recent + [loss.item()])[-50:]
        budget.stepped(time.perf_counter() - tick)
        stopping = budget.exhausted()
        if step % options.checkpoint_every == 0 or step == options.steps or stopping:
            tick = time.perf_counter()
            save_checkpoint(checkpoint, model, optimiser, step, options)
            budget.finished("checkpoint", time.perf_counter() - tick)
        if step % options.validate_every == 0 or step == options.steps or stopping:
            tick = time.perf_counter()
            score, base = validate(model, validation, options.device)
            budget.finished("validation", time.perf_counter() - tick)
            rate = seen / (time.perf_counter() - started)
            entry = {"step": step, "loss": float(np.mean(recent)), **parts, "val_psnr": score, "val_base_psnr": base,
                     "samples_per_s": rate, "lr": schedule.get_last_lr()[0], "time": time.time()}
            with open(out / "log.jsonl", "a") as f:
                f.write(json.dumps(entry) + "\n")
            log(f"step {step}/{options.steps}  loss {entry['loss']:.4f}  val {score:.2f} dB (TFP base {base:.2f} dB)"
                f"  {rate:.2f} samples/s")
        if stopping:
            log(f"stopped at step {step} of {options.steps}: the time budget of {options.time_budget:g} s is "
                f"nearly spent; --resume continues")
            break
    batches.close()
    final = out / f"cscsr-{options.config}.safetensors"
    if seen or not final.exists():  # a resume with nothing to train leaves the run's file (and its record) alone
        save_weights(model, final, **_about(step, options, command))
    return final


class Budget:
    """When to stop a run with a time budget: before the next step, the final checkpoint, validation and
    weights could overrun it. Costs are the slowest seen so far (a first guess before any is seen)."""

    def __init__(self, seconds: float, began: float):
        self.deadline = began + seconds if seconds else math.inf
        self.costs = {"step": 0.0, "checkpoint": 5.0, "validation": 10.0}

    def stepped(self, seconds: float) -> None:
        self.finished("step", seconds)

    def finished(self, what: str, seconds: float) -> None:
        self.costs[what] = max(self.costs[what] if what == "step" else 0.0, seconds)

    def exhausted(self) -> bool:
        needed = 2 * self.costs["step"] + 1.5 * (self.costs["checkpoint"] + self.costs["validation"]) + 5
        return time.perf_counter() + needed > self.deadline


def total_steps(recorded: str | None) -> int | None:
    """The optimiser steps a weights file's ``steps`` records: a count, or its runs' counts summed (``529 + 2593``,
    as an older file wrote them); None if it records none."""
    parts = (recorded or "").split("+")
    return sum(int(part) for part in parts) if all(part.strip().isdigit() for part in parts) else None


def _about(step: int, options: TrainOptions, command: str) -> dict:
    """The metadata of a weights file after ``step`` steps of this run: ``steps``, every optimiser step the weights
    have had (this run's and, from ``--init``, that file's), and ``run_steps``, this run's alone."""
    start, before = {}, 0
    if options.init:
        from cscsr.weights.weights_io import read_metadata

        parent = read_metadata(options.init).get("steps")
        start = {"initialised_from": f"{options.init} ({parent or '?'} steps)"}
        before = total_steps(parent) or 0
    return {**start, "steps": str(before + step), "run_steps": str(step), "command": command,
            "options": json.dumps(asdict(options)),
            "data": f"simulated on the fly{f' by the torch synthesis on {options.device}' if options.on_device_synthesis else ''}"
                    ": dead leaves "
                    f"({options.dead_leaves:.0%} of clips) and "
                    + (f"the pictures in {', '.join(options.picture_folders())} (stills along random camera paths, "
                       "runs of consecutive frames with their own motion)"
                        if options.pictures else
                       f"scikit-image pictures ({', '.join(TRAIN_PICTURES)})") + ", random camera paths, alpha 0.6-1.0, both resets, "
                    "realistic noise on half, "
                    + ("a mono sensor (Rec.601 luma)" if options.network().mono else "four CFA phases") + ", x2 and x4"
                    + (f"; a pool of {options.pool} clips under 8 flips and turns" if options.pool else "")}


def export_weights(folder: str | os.PathLike, dest: str | os.PathLike, command: str = "",
                   storage: str = "float32", *, overwrite: bool = False) -> int:
    """The latest checkpoint of a training folder as a weights file (a run need not be finished);
    ``storage="float16"`` halves the file (what comes back from a GPU lease). An existing ``dest`` is
    refused unless ``overwrite`` and it is a weights file; it is replaced only once the new one is written."""
    checkpoint = Path(folder) / "checkpoint.safetensors"
    if not checkpoint.exists():
        raise InputError(f"{checkpoint} does not exist: nothing trained there yet")
    dest = Path(dest)
    _claim_weights_file(dest, overwrite)
    tensors, metadata = read_checkpoint(checkpoint)
    model = CSCSR(CSCSRConfig.from_json(metadata["config"]))
    model.load_state_dict(model_weights(tensors))
    options = TrainOptions(**json.loads(metadata["options"]))
    step = int(metadata["step"])
    # beside it, under a name of this run's own: the old file stays until the new one is whole, and no file of
    # the user's (an x.safetensors.partial) is ever written over or removed
    partial = dest.with_name(f".{dest.name}.{uuid.uuid4().hex[:12]}.partial")
    try:
        save_weights(model, partial, storage=storage,
                     **_about(step, options, command or "cscsr train (exported from a checkpoint)"))
        os.replace(partial, dest)
    finally:
        partial.unlink(missing_ok=True)
    return step


def _claim_weights_file(dest: Path, overwrite: bool) -> None:
    """Refuse an existing ``dest`` unless it is a weights file (what export-weights writes) and ``overwrite``."""
    if not (dest.exists() or dest.is_symlink()):
        return
    if (found := _not_weights_file(dest)) is not None:
        raise not_ours_error(dest, "a weights file", found)
    if not overwrite:
        raise exists_error(dest)


def _not_weights_file(path: Path) -> str | None:
    """What is at ``path`` if it is not a weights file (a safetensors file with a network configuration and no
    optimiser state, not a training checkpoint) nor a file holding nothing; else None."""
    from safetensors import safe_open

    if not path.is_file():
        return "a folder" if path.is_dir() else "not a regular file"
    if path.stat().st_size == 0:
        return None  # nothing to lose
    try:
        with safe_open(str(path), "pt") as handle:
            metadata = handle.metadata() or {}
    except Exception:  # not safetensors at all: safetensors raises its own error types
        return "a file that is not safetensors"
    if "param_groups" in metadata:
        return "a training checkpoint"
    return None if "config" in metadata else "a safetensors file without a CSCSR configuration"


def export_portable(folder: str | os.PathLike, dest: str | os.PathLike, weights: str = "float32",
                    part_bytes: int | None = None, *, overwrite: bool = False) -> tuple[int, list[Path]]:
    """The latest checkpoint of a training folder as a portable checkpoint in ``dest`` (parts of at most
    16 MiB, ``cscsr.weights.portable_checkpoint``), which ``train --resume`` continues on another machine.
    A folder that already holds a portable checkpoint's parts is refused unless ``overwrite`` (its other
    files are never touched). Returns (step, parts)."""
    from cscsr.weights.portable_checkpoint import PART_BYTES, portable_parts, write_portable

    checkpoint = Path(folder) / "checkpoint.safetensors"
    if not checkpoint.exists():
        raise InputError(f"{checkpoint} does not exist: nothing trained there yet")
    dest = Path(dest)
    if dest.exists() and not dest.is_dir():
        raise InputError(f"output {dest} is a file, not a folder: --portable writes a folder of parts")
    if dest.is_dir() and portable_parts(dest, complete=False) and not overwrite:
        raise InputError(f"output {dest} already holds a portable checkpoint's parts "
                         f"(pass --overwrite to replace them)")
    tensors, metadata = read_checkpoint(checkpoint)
    parts = write_portable(tensors, metadata, dest, weights=weights, part_bytes=part_bytes or PART_BYTES)
    return int(metadata["step"]), parts
