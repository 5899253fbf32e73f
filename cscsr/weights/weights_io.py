"""Weights files: safetensors only (no pickle), with the configuration in the metadata.

A file carries everything needed to rebuild its network: the configuration as JSON, the
conventions of the data it was trained on (CFA naming, output units, scales), and free
text on how it was made (training command, steps, data). Loading checks all of it and
says plainly what is wrong with a file that does not fit.
"""

import hashlib
import json
import os
import struct
from pathlib import Path

import torch

from cscsr.network.config import CSCSRConfig
from cscsr.network.integration import NETWORK_SCALES
from stages.errors import InputError

FORMAT = "cscsr-weights/1"
CONVENTIONS = {
    "format": FORMAT,
    "cfa": "pattern names the top-left 2x2 cell row by row, row 0 at the top of the frame as stored",
    "output": "linear firing rate alpha*I/theta per colour (RGB); exposure is applied after",
    "scales": ",".join(map(str, NETWORK_SCALES)),
}
MONO_OUTPUT = "linear firing rate alpha*I/theta per pixel (grey, as three equal channels); exposure is applied after"


def conventions(config: CSCSRConfig) -> dict:
    """The conventions a file of ``config`` records: a mono network's output is grey, not per colour."""
    return {**CONVENTIONS, "output": MONO_OUTPUT} if config.mono else dict(CONVENTIONS)
SHIPPED = Path(__file__).parent  # the shipped files live beside it


STORAGE = {"float32": torch.float32, "float16": torch.float16, "bfloat16": torch.bfloat16}


def save_weights(model, path: str | os.PathLike, storage: str = "float32", **about: str) -> None:
    """Write ``model``'s parameters and configuration; ``about`` adds free-text metadata.

    ``storage`` "float16" or "bfloat16" halves the file (recorded in the metadata); loading
    converts back to float32. Refused if a parameter would not survive the conversion.
    """
    from safetensors.torch import save_file

    if storage not in STORAGE:
        raise InputError(f"unknown weights storage {storage!r}: expected one of {', '.join(STORAGE)}")
    metadata = {**conventions(model.config), "config": model.config.to_json(), "storage": storage,
                **{k: str(v) for k, v in about.items()}}
    tensors = {}
    for name, value in model.state_dict().items():
        value = value.detach().cpu()
        if value.is_floating_point():
            stored = value.to(STORAGE[storage])
            if not torch.isfinite(stored).all():
                raise InputError(f"parameter {name} does not fit in {storage} (values up to "
                                 f"{value.abs().max().item():.3g}): store the weights as float32")
            value = stored
        tensors[name] = value.contiguous()
    save_file(tensors, str(path), metadata=metadata)
    readable(path)


def readable(path: str | os.PathLike) -> None:
    """Give a file safetensors wrote (mode 0600, as its temporary file is) the mode any new file gets here (0644
    under the usual umask): weights and checkpoints are read by other users, containers and workers."""
    os.chmod(path, 0o666 & ~_UMASK)


def _umask() -> int:
    mask = os.umask(0)  # read by setting it: done once, at import, before a training's threads start
    os.umask(mask)
    return mask


_UMASK = _umask()


def annotate(source: str | os.PathLike, dest: str | os.PathLike, **about: str) -> None:
    """Copy a weights file, tensors as stored, with metadata added or replaced (e.g. a training record)."""
    from safetensors.torch import load_file, save_file

    metadata = {**read_metadata(source), **{k: str(v) for k, v in about.items()}}
    save_file(load_file(str(source)), str(dest), metadata=metadata)
    readable(dest)


def resolve_weights(path: str | os.PathLike) -> Path:
    """A weights file, or the name of a shipped one ("lite", "full") where no file of that name exists."""
    from cscsr.network.config import CONFIGS

    if str(path) in CONFIGS and not Path(path).exists():
        return default_weights(str(path))
    return Path(path)


def weights_file(weights: str | os.PathLike | None) -> Path:
    """A network's weights file: ``weights`` (a file, or a shipped one's name), else the shipped ``lite``."""
    return resolve_weights(weights) if weights else default_weights("lite")


def existing_weights_file(path: str | os.PathLike) -> Path:
    """``resolve_weights(path)``, refused in one line if it is a folder or no file."""
    path = resolve_weights(path)
    if path.is_dir():
        raise InputError(f"weights {path} is a folder, not a weights file: give the .safetensors file itself")
    if not path.is_file():
        raise InputError(f"weights file {path} not found")
    return path


def weights_sha256(path: str | os.PathLike) -> str:
    """The SHA-256 of a weights file's bytes (or a shipped one's, by name): what an output records of
    the weights it was made with, and ``--resume`` compares (another file at the same path differs)."""
    path = existing_weights_file(path)
    try:
        with open(path, "rb") as handle:
            return hashlib.file_digest(handle, "sha256").hexdigest()
    except OSError as error:
        raise InputError(f"cannot read weights file {path}: {error.strerror or error}") from None


def read_metadata(path: str | os.PathLike) -> dict[str, str]:
    """The metadata of a safetensors file (or a shipped one by name), read from its header alone."""
    path = existing_weights_file(path)
    with open(path, "rb") as f:
        head = f.read(8)
        if len(head) < 8:
            raise InputError(f"{path} is not a safetensors file (only {len(head)} bytes)")
        (length,) = struct.unpack("<Q", head)
        if length > min(100_000_000, path.stat().st_size - 8):
            raise InputError(f"{path} is not a safetensors file (bad header length)")
        try:
            header = json.loads(f.read(length))
        except ValueError:
            raise InputError(f"{path} is not a safetensors file (its header is not JSON)") from None
    if not isinstance(header, dict):
        raise InputError(f"{path} is not a safetensors file (its header is not a JSON object)")
    metadata = header.get("__metadata__") or {}
    if not isinstance(metadata, dict):
        metadata = {}
    if metadata.get("format") != FORMAT:
        raise InputError(f"{path} is not a cscsr weights file (metadata format {metadata.get('format')!r}, "
                         f"expected {FORMAT!r})")
    return metadata


def load_model(path: str | os.PathLike, device: str | torch.device = "cpu"):
    """-> (network in eval mode on ``device``, metadata). Clear errors for missing or mismatching files."""
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    from cscsr.network.model import CSCSR

    path = resolve_weights(path)
    metadata = read_metadata(path)
    try:
        config = CSCSRConfig.from_json(metadata["config"])
    except (KeyError, TypeError, ValueError) as error:
        raise InputError(f"{path} has no valid network configuration in its metadata ({error})") from None
    try:
        tensors = load_file(str(path), device="cpu")
    except SafetensorError as error:
        raise InputError(f"{path} is damaged: {error}") from None
    model = CSCSR(config)
    expected = model.state_dict()
    missing = sorted(set(expected) - set(tensors))
    extra = sorted(set(tensors) - set(expected))
    wrong = sorted(k for k in set(expected) & set(tensors) if expected[k].shape != tensors[k].shape)
    if missing or extra or wrong:
        what = (f"missing {missing[0]}" if missing else f"unexpected {extra[0]}" if extra else
                f"{wrong[0]} is {tuple(tensors[wrong[0]].shape)}, expected {tuple(expected[wrong[0]].shape)}")
        raise InputError(f"{path} does not match its configuration {config.name!r}: {what}")
    for name in sorted(tensors):  # NaN or infinity in one weight makes every output pixel NaN (a black video)
        tensor = tensors[name]
        if tensor.is_floating_point() and not torch.isfinite(tensor).all():
            bad = int((~torch.isfinite(tensor)).sum())
            raise InputError(f"{path} is damaged: tensor {name} holds {bad} non-finite values (NaN or infinity)")
    model.load_state_dict({k: v.to(expected[k].dtype) for k, v in tensors.items()})  # half storage -> float32
    return model.to(device).eval(), metadata


def default_weights(config: str = "lite") -> Path:
    """The weights shipped in the package for ``config``; an error if there are none yet."""
    path = SHIPPED / f"cscsr-{config}.safetensors"
    if not path.is_file():
        raise InputError(f"no shipped weights for CSCSR {config!r} ({path.name}): pass --weights FILE")
    return path
