"""A training checkpoint small enough to carry between machines: parts of at most 16 MiB.

The exact checkpoint (``checkpoint.safetensors``: float32 weights and Adam's two float32
moments per weight) of ``full`` is about 77 MB, more than a GPU lease brings back (files of at
most 16 MiB) or takes along (64 MiB in all). The portable form keeps everything a resumed run
needs and halves or thirds the bytes:

    weights            float32 (exact) or float16 (``weights="float16"``: relative error 2^-11)
    Adam exp_avg       bfloat16 (relative error 2^-8; bfloat16 keeps float32's range, so the
    Adam exp_avg_sq    bfloat16  tiny squared gradients do not underflow as float16 would)
    Adam step          float32, exact
    step, options, configuration, Adam's param_groups: in the metadata of every part

split into ``checkpoint.part-I-of-N.safetensors`` files of at most ``part_bytes`` each (the
safetensors header included). Nothing else is needed: each step's clips come from
``[seed, step, i]`` and the learning-rate schedule is a function of the step, so no RNG or
scheduler state exists to carry. ``cscsr train OUT --resume`` reads the parts when OUT holds
them and no exact checkpoint; the run then goes on close to, not bit-exactly as, an
uninterrupted one (the rounded moments and weights; tested). The exact checkpoint stays the
one a run writes and resumes from on its own machine.
"""

import json
import re
from pathlib import Path

import torch

from stages.errors import InputError

PART_BYTES = 16 * 2**20  # a file a GPU lease brings back
PART_NAME = "checkpoint.part-{index}-of-{count}.safetensors"
_PART = re.compile(r"checkpoint\.part-(\d+)-of-(\d+)\.safetensors")
WEIGHT_STORAGE = {"float32": torch.float32, "float16": torch.float16}
MOMENTS = ("exp_avg", "exp_avg_sq")
_HEADER_PER_TENSOR = 160  # bytes of safetensors header per tensor, at most (name, dtype, shape, offsets)


def portable_tensors(tensors: dict, weights: str = "float32") -> dict:
    """An exact checkpoint's tensors (``model.*``, ``optimiser.I.name``) in portable storage."""
    if weights not in WEIGHT_STORAGE:
        raise InputError(f"unknown portable weights storage {weights!r}: expected one of {', '.join(WEIGHT_STORAGE)}")
    stored = {}
    for name, value in tensors.items():
        if name.startswith("model.") and value.is_floating_point():
            value = value.to(WEIGHT_STORAGE[weights])
        elif name.rsplit(".", 1)[-1] in MOMENTS:
            value = value.to(torch.bfloat16)
        if not torch.isfinite(value.float()).all():
            raise InputError(f"{name} does not fit in {value.dtype} (values up to {tensors[name].abs().max():.3g}): "
                             f"write the portable weights as float32")
        stored[name] = value.contiguous()
    return stored


def write_portable(tensors: dict, metadata: dict, dest: str | Path, *, weights: str = "float32",
                   part_bytes: int = PART_BYTES) -> list[Path]:
    """Write a checkpoint (``cscsr.training.training_state.read_checkpoint``'s tensors and metadata) into ``dest`` as parts of
    at most ``part_bytes`` bytes each; earlier parts there are replaced. Returns the parts' paths."""
    from safetensors.torch import save

    stored = portable_tensors(tensors, weights)
    metadata = {**metadata, "portable": json.dumps({"weights": weights, "moments": "bfloat16"})}
    groups = _pack(stored, part_bytes - _header_bytes(metadata))
    dest = Path(dest)
    dest.mkdir(parents=True, exist_ok=True)
    for old in portable_parts(dest, complete=False):
        old.unlink()
    paths = []
    for index, names in enumerate(groups, 1):
        blob = save({n: stored[n] for n in names}, metadata={**metadata, "part": f"{index}/{len(groups)}"})
        if len(blob) > part_bytes:  # the header allowance is an upper bound, so this would be a bug
            raise AssertionError(f"part {index} is {len(blob)} bytes, over the limit of {part_bytes}")
        path = dest / PART_NAME.format(index=index, count=len(groups))
        partial = path.with_suffix(".partial")
        partial.write_bytes(blob)
        partial.replace(path)
        paths.append(path)
    return paths


def _header_bytes(metadata: dict) -> int:
    return 8 + len(json.dumps(metadata).encode()) + 64  # length prefix, metadata, "part" and padding


def _pack(tensors: dict, room: int) -> list[list[str]]:
    """Tensor names in groups whose data and header fit ``room`` bytes, in order (first fit, a new part when full)."""
    groups, used = [[]], 0
    for name, value in tensors.items():
        size = value.numel() * value.element_size() + _HEADER_PER_TENSOR + len(name)
        if size > room:
            raise InputError(f"{name} alone ({size} bytes) does not fit in a part of the size asked for")
        if used + size > room:
            groups.append([])
            used = 0
        groups[-1].append(name)
        used += size
    return groups


def portable_parts(folder: str | Path, complete: bool = True) -> list[Path]:
    """The portable parts in ``folder``, in order ([] if none); with ``complete``, refused unless all N of
    one set are there."""
    found = {}
    for path in Path(folder).glob("checkpoint.part-*-of-*.safetensors"):
        match = _PART.fullmatch(path.name)
        if match:
            found[int(match[1]), int(match[2])] = path
    if not found or not complete:
        return [found[k] for k in sorted(found)]
    counts = {count for _, count in found}
    wanted = {(i, count) for count in counts for i in range(1, count + 1)}
    if len(counts) != 1 or set(found) != wanted:
        missing = ", ".join(PART_NAME.format(index=i, count=c) for i, c in sorted(wanted - set(found)))
        raise InputError(f"the portable checkpoint in {folder} is incomplete or mixed: "
                         + (f"missing {missing}" if missing else f"parts of {len(counts)} different sets"))
    return [found[k] for k in sorted(found)]


def read_portable(folder: str | Path) -> tuple[dict, dict]:
    """(tensors as float32, metadata) of the portable checkpoint in ``folder``, as ``read_checkpoint`` gives
    an exact one. Refused if parts are missing or come from different checkpoints."""
    from safetensors import SafetensorError, safe_open

    from stages.errors import describe

    tensors, metadata = {}, None
    for path in portable_parts(folder):
        try:
            with safe_open(str(path), "pt") as f:
                about = {k: v for k, v in (f.metadata() or {}).items() if k != "part"}
                if metadata is None:
                    metadata = about
                elif about != metadata:
                    raise InputError(f"{path} belongs to another checkpoint than the other parts in {folder}")
                for name in f.keys():
                    value = f.get_tensor(name)
                    tensors[name] = value.float() if value.is_floating_point() else value
        except (SafetensorError, OSError) as error:  # cut short, overwritten, not a safetensors file
            raise InputError(f"portable checkpoint part {path} is damaged: {describe(error)}") from None
    if metadata is None:
        raise InputError(f"no portable checkpoint (checkpoint.part-I-of-N.safetensors) in {folder}")
    return tensors, metadata
