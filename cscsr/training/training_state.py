"""A training run's state on disk: its checkpoints, resuming from them, and the weights it starts from.

A checkpoint (weights and optimiser state, safetensors: no pickle) is written atomically into the run
folder; ``--resume`` continues from it, or from a portable checkpoint's parts (``cscsr.weights.portable_checkpoint``),
refusing options that would change the weights, the clips or the schedule so far.
"""

import json
import os
from dataclasses import asdict
from pathlib import Path

import torch

from cscsr.network.model import CSCSR
from cscsr.training.training_options import TrainOptions
from cscsr.weights.weights_io import readable
from stages.errors import InputError


# Options a resumed run may change; every other one shapes the weights, the clips or the schedule so far. A larger
# pool brings fresh clips to a run that has seen its pool many times (clip i keeps its seed; its scale may change).
# The device, precision and time budget do not change the clips or the schedule: a run moves between machines.
MAY_CHANGE_ON_RESUME = frozenset({"steps", "decay_every", "checkpoint_every", "validate_every", "validation_clips",
                                  "pool", "device", "precision", "time_budget", "synthesis", "init",
                                  "channels_last"})


def save_checkpoint(path: Path, model: CSCSR, optimiser: torch.optim.Optimizer, step: int, options: TrainOptions) -> None:
    from safetensors.torch import save_file

    tensors = {f"model.{k}": v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    state = optimiser.state_dict()
    for index, values in state["state"].items():
        for key, value in values.items():
            tensors[f"optimiser.{index}.{key}"] = torch.as_tensor(value).detach().cpu().contiguous()
    metadata = {"step": str(step), "options": json.dumps(asdict(options), sort_keys=True),
                "config": model.config.to_json(), "param_groups": json.dumps(state["param_groups"])}
    partial = path.with_suffix(".partial")
    try:
        save_file(tensors, str(partial), metadata=metadata)
        readable(partial)
        os.replace(partial, path)  # a killed run never leaves half a checkpoint
    except BaseException:  # an interrupt (Ctrl-C, SIGTERM) mid-save: nothing half-written left behind either
        partial.unlink(missing_ok=True)
        raise


def read_checkpoint(path: Path) -> tuple[dict, dict]:
    """(tensors, metadata) of a checkpoint file; one that cannot be read (cut short, overwritten, not a
    safetensors file) is refused in one line naming it."""
    from safetensors import SafetensorError, safe_open
    from safetensors.torch import load_file

    from stages.errors import describe

    try:
        with safe_open(str(path), "pt") as f:
            metadata = f.metadata()
        return load_file(str(path)), metadata or {}
    except (SafetensorError, OSError) as error:
        raise InputError(f"checkpoint {path} is damaged: {describe(error)}") from None


def resumable(out: Path) -> Path:
    """What ``--resume`` continues from: ``out``'s exact checkpoint, else ``out`` itself when it holds the parts
    of a portable one (carried from another machine)."""
    from cscsr.weights.portable_checkpoint import portable_parts

    checkpoint = out / "checkpoint.safetensors"
    if checkpoint.exists():
        return checkpoint
    if portable_parts(out, complete=False):
        portable_parts(out)  # refused unless every part is there
        return out
    raise InputError(f"cannot resume: {checkpoint} does not exist (nor a portable checkpoint's parts in {out})")


def model_weights(tensors: dict) -> dict:
    """The network's part of a checkpoint's tensors, as a state dict."""
    return {k.removeprefix("model."): v for k, v in tensors.items() if k.startswith("model.")}


def load_checkpoint(path: Path, model: CSCSR, optimiser: torch.optim.Optimizer, options: TrainOptions) -> int:
    """Restore a run from its exact checkpoint file, or from a folder holding a portable checkpoint's parts
    (``cscsr.weights.portable_checkpoint``: close, not bit-exact). Returns the step it had reached."""
    from cscsr.weights.portable_checkpoint import read_portable
    from stages.errors import describe

    tensors, metadata = read_portable(path) if Path(path).is_dir() else read_checkpoint(path)
    try:
        recorded = json.loads(metadata["options"])
        changed = [k for k, value in asdict(options).items()
                   if k not in MAY_CHANGE_ON_RESUME and recorded.get(k, getattr(TrainOptions, k)) != value]
        if changed:
            raise InputError(f"cannot resume {path}: it was trained with other options ({', '.join(changed)})")
        model.load_state_dict(model_weights(tensors))
        state = {"state": {}, "param_groups": json.loads(metadata["param_groups"])}
        for key, value in tensors.items():
            if key.startswith("optimiser."):
                _, index, name = key.split(".", 2)
                state["state"].setdefault(int(index), {})[name] = value
        optimiser.load_state_dict(state)
        return int(metadata["step"])
    except InputError:
        raise
    except (KeyError, TypeError, ValueError, AttributeError, RuntimeError) as error:  # readable, but not ours
        cause = describe(error)
        cause = cause if len(cause) <= 200 else cause[:200] + "..."  # torch names every missing parameter
        raise InputError(f"cannot resume from {path}: it is damaged or not a cscsr training checkpoint "
                         f"({type(error).__name__}: {cause})") from None


def initial_weights(options: TrainOptions) -> dict:
    """The state dict of ``options.init``, refused unless it holds the network this run trains."""
    from cscsr.weights.mono_init import mono_config_of, mono_state
    from cscsr.weights.weights_io import load_model

    model, _ = load_model(options.init)
    target = options.network()
    if target.mono and model.config.colours == 3 and mono_config_of(model.config, target.name) == target:

        return mono_state(model.state_dict(), model.config)  # a mono run from a colour file: its green branch
    if model.config != target:
        raise InputError(f"cannot start from {options.init}: it holds CSCSR {model.config.name!r} "
                         f"({model.config.to_json()}), this run trains {options.network().to_json()}")
    return model.state_dict()
