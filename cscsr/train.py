"""Training CSCSR on clips simulated on the fly, with resumable checkpoints.

Each step draws a batch from its own seed (``[seed, step, i]``), so a resumed run sees
exactly the clips an uninterrupted one would. Loss: L1 on the HR rate image plus
``flow_weight`` times L1 of the two key flows against the simulator's exact flows (the
motion is synthetic, so its truth is known). Adam with the sibling paper's step decay, gradients clipped.
Batches are prepared by background threads while the network trains on the previous one; on a
GPU the clips themselves are synthesised there (``cscsr.synthesis``), with bf16 autocast on
request, and ``time_budget`` ends a run cleanly before a command limit.
A checkpoint (weights and optimiser state, safetensors: no pickle) is written atomically
every ``checkpoint_every`` steps; the validation PSNR (fixed held-out clips) is logged to
``log.jsonl`` and printed on the progress line.
"""

import json
import math
import os
import time
import uuid
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from cscsr.config import PRECISIONS, CSCSRConfig, named
from cscsr.network import CSCSR, use_channels_last
from cscsr.training_data import (DEAD_LEAVES_SHARE, TRAIN_PICTURES, Clip, batch_arrays, check_not_test_pictures,
                                 picture_files, random_clip, random_plan, reoriented)
from cscsr.weights_io import save_weights
from stages.errors import InputError, exists_error, not_ours_error
from stages.numbers import check_number
from stages.prefetch import made_ahead

VALIDATION_SEED = 10_000_019  # validation clips: dead leaves from seeds no training step uses
# Bounds of the options that size a run (TrainOptions.check), each with its reason:
MAX_LEARNING_RATE = 0.1  # Adam moves each weight by up to the rate per step; the recipes use 1e-4 to 1e-3
# A lower bound of one training step's memory per LR pixel of each clip in the batch: the tensors autograd keeps
# for the backward pass, measured at LR 16 to 48, x4 (saved-tensor hooks): lite 38 KB in fp32 and 25 KB in bf16,
# full 82 KB in fp32; gradients, Adam's moments and workspaces come on top.
STEP_BYTES_PER_LR_PIXEL = 16 * 2**10
# A pooled clip held in memory, per LR pixel: 41 frames of uint8 spikes, the x4 truth (3 float32 per HR pixel,
# 16 HR pixels per LR pixel) and two float32 (x, y) flows.
CLIP_BYTES_PER_LR_PIXEL = 41 + 3 * 4 * 16 + 2 * 2 * 4


def memory_of(device: torch.device) -> int | None:
    """Bytes of memory of a training device: the GPU's, or the machine's for the CPU (None if unknown)."""
    if device.type == "cuda":
        return torch.cuda.get_device_properties(torch.cuda.current_device() if device.index is None
                                                else device.index).total_memory
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, ValueError, OSError):  # no sysconf (Windows): not checked
        return None


@dataclass(frozen=True)
class TrainOptions:
    config: str = "lite"
    steps: int = 20000
    batch: int = 8
    lr_side: int = 32  # LR crop side (HR 128 at x4)
    learning_rate: float = 2e-4
    decay_every: int = 7500  # learning rate x0.9 every this many steps (the sibling recipe); a resumed run may
    # change it, which drops the rate at once to its place on the new schedule (how the shipped weights were annealed)
    warmup: int = 200  # steps of linear learning-rate warm-up: Adam's first steps move every weight by the full
    # rate at once, which from zero heads threw the output 0.4 off (validation 17.4 -> 5.7 dB in two steps)
    flow_weight: float = 0.1
    clip: float = 0.1  # gradient norm bound: without it the loss oscillated instead of falling
    scale4_share: float = 0.75  # share of steps at x4; the rest at x2
    seed: int = 0
    checkpoint_every: int = 100
    validate_every: int = 250
    validation_clips: int = 8
    distinct_batches: int = 0  # 0: a new batch every step; n: cycle through n batches (tiny data, for tests)
    pool: int = 0  # 0: every clip simulated for its step; n: n clips simulated up front, drawn under 8 orientations
    init: str = ""  # a weights file to start from instead of random weights (fine-tuning, e.g. on larger crops)
    motion: str = "joint"  # the network's ablation switches (cscsr.config): "joint" or "assembled" motion,
    flow_guidance: bool = True  # and flow-guided fusion on or off
    pictures: str = ""  # folders of training pictures, joined by os.pathsep ("": the bundled pictures)
    dead_leaves: float = DEAD_LEAVES_SHARE  # share of clips showing dead leaves instead of a picture
    device: str = "cpu"  # "cpu", "cuda" or "cuda:N"; on a GPU clips are synthesised there (cscsr.synthesis)
    precision: str = "fp32"  # "fp32" or "bf16" (autocast; weights and optimiser stay fp32)
    synthesis: str = "auto"  # clips by "numpy" (stages, the simulator of record) or "torch" (cscsr.synthesis, on
    # the device; the same clips); "auto": torch on a GPU, numpy on the CPU
    time_budget: float = 0.0  # seconds from the start of the run: stop cleanly with a checkpoint before it (0: none)
    channels_last: bool = False  # convolutions on NHWC tensors (cscsr.network.use_channels_last): the same
    # training within float rounding, faster where the device's kernels prefer that layout

    def network(self) -> CSCSRConfig:
        """The configuration this run trains: the named one with its ablation switches applied."""
        return named(self.config).ablate(motion=self.motion, flow_guidance=self.flow_guidance)

    def check(self) -> "TrainOptions":
        """Refuse options that cannot train, before any output exists (the command line and the Python API)."""
        self.network()
        for label, value in (("steps", self.steps), ("batch", self.batch), ("checkpoint_every", self.checkpoint_every),
                             ("validate_every", self.validate_every), ("warmup", self.warmup),
                             ("decay_every", self.decay_every)):
            check_number(label, value, at_least=1, integer=True)
        check_number("lr_side", self.lr_side, integer=True)
        if self.lr_side < 16 or self.lr_side % 2:
            raise InputError(f"lr_side must be even and >= 16, got {self.lr_side}")
        check_number("pool", self.pool, at_least=0, integer=True)  # -1 was truthy: a pool of no clips, then a crash
        # nan and -1 failed in Adam after OUT existed, inf left a NaN checkpoint, 0 ships the random weights
        check_number("learning_rate", self.learning_rate, at_least=0, at_most=MAX_LEARNING_RATE,
                     why="Adam moves every weight by up to the rate at each step, and trained weights are mostly "
                         "smaller: median 0.02 to 0.04")
        if self.learning_rate == 0 and not self.init:
            raise InputError(f"learning_rate must be > 0, got {self.learning_rate}: at 0 the run would ship its random "
                             "initial weights untrained (0 is for --init, to keep the weights it starts from)")
        if self.precision not in PRECISIONS:
            raise InputError(f"unknown precision {self.precision!r}: expected one of {', '.join(PRECISIONS)}")
        if not (math.isfinite(self.time_budget) and self.time_budget >= 0):
            raise InputError(f"time_budget must be a finite number of seconds >= 0, got {self.time_budget}")
        if not (math.isfinite(self.dead_leaves) and 0 <= self.dead_leaves <= 1):
            raise InputError(f"dead_leaves must be a share in [0, 1], got {self.dead_leaves}")
        try:
            device = torch.device(self.device)
        except RuntimeError:
            raise InputError(f"unknown device {self.device!r}: expected cpu, cuda or cuda:N") from None
        if device.type not in ("cpu", "cuda"):
            raise InputError(f"unknown device {self.device!r}: expected cpu, cuda or cuda:N")
        if device.type == "cuda" and not torch.cuda.is_available():
            raise InputError(f"device {self.device!r} asked for, but torch sees no CUDA GPU here")
        if device.type == "cuda" and (device.index or 0) >= torch.cuda.device_count():
            count = torch.cuda.device_count()
            raise InputError(f"device {self.device!r} asked for, but torch sees {count} CUDA GPU(s) here "
                             f"(cuda:0 to cuda:{count - 1})")
        if self.synthesis not in SYNTHESES:
            raise InputError(f"unknown synthesis {self.synthesis!r}: expected one of {', '.join(SYNTHESES)}")
        if self.pool and self.on_device_synthesis:
            raise InputError("--pool is for numpy synthesis on the CPU: on-device synthesis makes every clip fresh")
        self._check_memory(device)
        return self

    def _check_memory(self, device: torch.device) -> None:
        """Refuse a batch, crop or pool that cannot fit in the memory of the machine (or GPU) at all: by a lower
        bound of what it needs, so that no run that could fit is refused (batch 100000 started and was killed)."""
        pixels = self.lr_side**2  # LR pixels of one clip
        step = self.batch * pixels * STEP_BYTES_PER_LR_PIXEL
        memory = memory_of(device)
        if memory is not None and step > memory:
            raise InputError(f"batch {self.batch} of LR {self.lr_side}x{self.lr_side} clips needs at least "
                             f"{step / 2**30:,.1f} GiB for one step (the activations kept for backpropagation, "
                             f"{STEP_BYTES_PER_LR_PIXEL // 1024} KiB per LR pixel of a clip), more than the "
                             f"{memory / 2**30:,.1f} GiB of memory on {device}: lower batch or lr_side")
        held = self.pool * pixels * CLIP_BYTES_PER_LR_PIXEL
        ram = memory_of(torch.device("cpu"))
        if ram is not None and held > ram:
            raise InputError(f"pool {self.pool} of LR {self.lr_side}x{self.lr_side} clips needs at least "
                             f"{held / 2**30:,.1f} GiB held in memory ({CLIP_BYTES_PER_LR_PIXEL} bytes per LR pixel "
                             f"of a clip), more than the {ram / 2**30:,.1f} GiB of this machine: lower pool")

    @property
    def on_device_synthesis(self) -> bool:
        """Clips made by ``cscsr.synthesis`` on the training device rather than by numpy (auto: on a GPU)."""
        if self.synthesis == "auto":
            return torch.device(self.device).type != "cpu"
        return self.synthesis == "torch"

    def picture_folders(self) -> list[str]:
        return [f for f in self.pictures.split(os.pathsep) if f]



# Options a resumed run may change; every other one shapes the weights, the clips or the schedule so far. A larger
# pool brings fresh clips to a run that has seen its pool many times (clip i keeps its seed; its scale may change).
# The device, precision and time budget do not change the clips or the schedule: a run moves between machines.
MAY_CHANGE_ON_RESUME = frozenset({"steps", "decay_every", "checkpoint_every", "validate_every", "validation_clips",
                                  "pool", "device", "precision", "time_budget", "synthesis", "init",
                                  "channels_last"})
SYNTHESES = ("auto", "numpy", "torch")


def scale_of(step: int, options: TrainOptions) -> int:
    return 4 if np.random.default_rng([options.seed, step, 999]).random() < options.scale4_share else 2


def learning_rate_factor(step: int, options: TrainOptions) -> float:
    """Linear warm-up, then x0.9 every ``decay_every`` steps."""
    return min(1.0, (step + 1) / options.warmup) * 0.9 ** (step // options.decay_every)


def make_batch(step: int, options: TrainOptions, cache: dict, pool: dict | None = None,
               pictures: tuple = TRAIN_PICTURES):
    """Step ``step``'s batch: numpy arrays (``batch_arrays``), or for on-device synthesis the CPU's share of it
    (``cscsr.synthesis.PreparedBatch``, the same clips' plans)."""
    if options.distinct_batches:
        step = 1 + (step - 1) % options.distinct_batches
    scale = scale_of(step, options)
    if options.on_device_synthesis:
        from cscsr.synthesis import prepare

        return prepare([random_plan([options.seed, step, i], lr_side=options.lr_side, scale=scale, pictures=pictures,
                                    cache=cache, dead_leaves_share=options.dead_leaves) for i in range(options.batch)])
    if pool:
        rng = np.random.default_rng([options.seed, step, 998])
        clips = pool[scale]
        return batch_arrays([reoriented(clips[i], int(k)) for i, k in
                             zip(rng.integers(len(clips), size=options.batch), rng.integers(8, size=options.batch))])
    clips = [random_clip([options.seed, step, i], lr_side=options.lr_side, scale=scale, pictures=pictures,
                         cache=cache, dead_leaves_share=options.dead_leaves) for i in range(options.batch)]
    return batch_arrays(clips)


def clip_pool(options: TrainOptions) -> dict[int, list]:
    """``options.pool`` clips simulated once, by scale (the x4 share as in the steps), on every core.

    Simulating a clip costs about as much as a training step on it; a pool seen under eight
    orientations halves the time per step. Clip i comes from seed ``[seed, 997, i]``, so a resumed
    run rebuilds the same pool.
    """
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    fours = round(options.pool * options.scale4_share)
    scales = [4 if i < fours else 2 for i in range(options.pool)]
    pool: dict[int, list] = {2: [], 4: []}
    with ProcessPoolExecutor(os.cpu_count(), mp_context=multiprocessing.get_context("spawn")) as workers:
        jobs = workers.map(_pool_clip, [([options.seed, 997, i], options.lr_side, s) for i, s in enumerate(scales)],
                           chunksize=8)
        for clip in jobs:
            pool[clip.scale].append(clip)
    return pool


_WORKER_PICTURES: dict = {}  # a pool worker's decoded pictures, read once per process, not once per clip


def _pool_clip(args) -> Clip:
    seed, lr_side, scale = args
    return random_clip(seed, lr_side=lr_side, scale=scale, pictures=TRAIN_PICTURES, cache=_WORKER_PICTURES)


def validation_batches(options: TrainOptions) -> list[dict]:
    """Fixed held-out clips at x4, alpha spread over [0.6, 1.0]; dead leaves only (no test pictures)."""
    alphas = np.linspace(0.6, 1.0, options.validation_clips)
    return [batch_arrays([random_clip([VALIDATION_SEED, i], lr_side=48, scale=4, pictures=(), alpha=float(a))])
            for i, a in enumerate(alphas)]


def to_tensors(batch, device: str = "cpu") -> dict:
    """A batch (numpy arrays, or a ``PreparedBatch`` to synthesise) as tensors on ``device``."""
    from cscsr.synthesis import PreparedBatch, synthesise

    if isinstance(batch, PreparedBatch):
        return synthesise(batch, device)
    arrays = {"spikes": torch.from_numpy(batch["spikes"]).float(), "truth": torch.from_numpy(batch["truth"]),
              "flows": torch.from_numpy(batch["flows"]), "zero_reset": torch.from_numpy(batch["zero_reset"]),
              "alpha": torch.from_numpy(batch["alpha"]).float()}
    return {**{k: v.to(device) for k, v in arrays.items()}, "cfa": batch["cfa"], "scale": batch["scale"]}


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


# --- checkpoints: safetensors for weights and optimiser state -------------------------------

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
    save_file(tensors, str(partial), metadata=metadata)
    os.replace(partial, path)  # a killed run never leaves half a checkpoint


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
    from cscsr.portable_checkpoint import portable_parts

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
    (``cscsr.portable_checkpoint``: close, not bit-exact). Returns the step it had reached."""
    from cscsr.portable_checkpoint import read_portable
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
    if out.exists() and any(out.iterdir()) and not resume:
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
    if options.pool:
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
            log(f"stopped at step {step} of {options.steps}: the time budget of {options.time_budget:.0f} s is "
                f"nearly spent; --resume continues")
            break
    batches.close()
    final = out / f"cscsr-{options.config}.safetensors"
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


def training_pictures(options: TrainOptions) -> tuple[str, ...]:
    """The pictures a run trains on: the files in ``options.pictures``'s folders (a folder of consecutive frames
    as one sequence, whose real motion makes the clips: ``cscsr.frame_motion``), else the bundled ones.

    Refused if any of them is a held-out test picture.
    """
    from cscsr.frame_motion import group_sequences

    folders = options.picture_folders()
    if not folders:
        return TRAIN_PICTURES
    names = picture_files(folders)
    check_not_test_pictures(names)
    return group_sequences(names)


def initial_weights(options: TrainOptions) -> dict:
    """The state dict of ``options.init``, refused unless it holds the network this run trains."""
    from cscsr.weights_io import load_model

    model, _ = load_model(options.init)
    if model.config != options.network():
        raise InputError(f"cannot start from {options.init}: it holds CSCSR {model.config.name!r} "
                         f"({model.config.to_json()}), this run trains {options.network().to_json()}")
    return model.state_dict()


def _about(step: int, options: TrainOptions, command: str) -> dict:
    start = {}
    if options.init:
        from cscsr.weights_io import read_metadata

        start = {"initialised_from": f"{options.init} ({read_metadata(options.init).get('steps', '?')} steps)"}
    return {**start, "steps": str(step), "command": command, "options": json.dumps(asdict(options)),
            "data": f"simulated on the fly{' on the GPU' if options.on_device_synthesis else ''}: dead leaves "
                    f"({options.dead_leaves:.0%} of clips) and "
                    + (f"the pictures in {', '.join(options.picture_folders())} (sequences of frames with their own motion)"
                        if options.pictures else
                       f"scikit-image pictures ({', '.join(TRAIN_PICTURES)})") + ", random camera paths, alpha 0.6-1.0, both resets, "
                    "realistic noise on half, four CFA phases, x2 and x4"
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
    16 MiB, ``cscsr.portable_checkpoint``), which ``train --resume`` continues on another machine.
    A folder that already holds a portable checkpoint's parts is refused unless ``overwrite`` (its other
    files are never touched). Returns (step, parts)."""
    from cscsr.portable_checkpoint import PART_BYTES, portable_parts, write_portable

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


def _prefetch(step: int, options: TrainOptions, pool: dict | None = None,
              pictures: tuple = TRAIN_PICTURES, depth: int = 2):
    """Batches for steps step+1, step+2, ... made in the background, in order.

    On the CPU one thread (the cores train). With on-device synthesis the CPU's share of each batch
    (scene crops, dead leaves, plans, sensor draws: about 15 ms a clip, most of it Python) is spread
    over worker processes, so that the GIL does not hold back the GPU.
    """
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor

    if options.on_device_synthesis:
        processes = max(1, min(12, (os.cpu_count() or 1) - 2))
        workers = ProcessPoolExecutor(processes, mp_context=multiprocessing.get_context("spawn"),
                                      initializer=_start_batch_worker, initargs=(options, pictures))
        make, ahead = _worker_batch, depth * processes
    else:
        cache: dict = {}
        workers = ThreadPoolExecutor(1, thread_name_prefix="batches")
        make, ahead = (lambda n: make_batch(n, options, cache, pool, pictures)), depth
    return made_ahead(make, range(step + 1, options.steps + 1), workers, ahead)


_WORKER: dict = {}  # a batch worker process's options, pictures and decoded-picture cache


def _start_batch_worker(options: TrainOptions, pictures: tuple) -> None:
    import cv2

    cv2.setNumThreads(1)
    torch.set_num_threads(1)
    _WORKER.update(options=options, pictures=pictures, cache={})


def _worker_batch(step: int):
    return make_batch(step, _WORKER["options"], _WORKER["cache"], None, _WORKER["pictures"])
