"""The options of a training run (``TrainOptions``, what ``cscsr train``'s flags fill in) and their checks.

``TrainOptions.check`` refuses options that cannot train before any output exists: numbers out of their
bounds, an unknown device, precision or synthesis, and a batch, crop or pool that cannot fit in memory.
The training loop is ``cscsr.training.train``; what a resumed run may change is ``cscsr.training.training_state``.
"""

import math
import os
from dataclasses import dataclass

import torch

from cscsr.network.config import PRECISIONS, CSCSRConfig, named
from cscsr.training.training_data import DEAD_LEAVES_SHARE
from stages.errors import InputError
from stages.numbers import check_number
from stages.reconstruction.methods import WINDOW


# Bounds of the options that size a run (TrainOptions.check), each with its reason:
MAX_LEARNING_RATE = 0.1  # Adam moves each weight by up to the rate per step; the recipes use 1e-4 to 1e-3
# A lower bound of one training step's memory per LR pixel of each clip in the batch: the tensors autograd keeps
# for the backward pass, measured at LR 16 to 48, x4 (saved-tensor hooks): lite 38 KB in fp32 and 25 KB in bf16,
# full 82 KB in fp32; gradients, Adam's moments and workspaces come on top.
STEP_BYTES_PER_LR_PIXEL = 16 * 2**10
# A pooled clip held in memory, per LR pixel: 41 frames of uint8 spikes, the x4 truth (3 float32 per HR pixel,
# 16 HR pixels per LR pixel) and two float32 (x, y) flows.
CLIP_BYTES_PER_LR_PIXEL = WINDOW + 3 * 4 * 16 + 2 * 2 * 4


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
    motion: str = "joint"  # the network's ablation switches (cscsr.network.config): "joint" or "assembled" motion,
    flow_guidance: bool = True  # and flow-guided fusion on or off
    pictures: str = ""  # folders of training pictures, joined by os.pathsep ("": the bundled pictures)
    dead_leaves: float = DEAD_LEAVES_SHARE  # share of clips showing dead leaves instead of a picture
    device: str = "cpu"  # "cpu", "cuda" or "cuda:N"; on a GPU clips are synthesised there (cscsr.training.synthesis)
    precision: str = "fp32"  # "fp32" or "bf16" (autocast; weights and optimiser stay fp32)
    synthesis: str = "auto"  # clips by "numpy" (stages, the simulator of record) or "torch" (cscsr.training.synthesis, on
    # the device; the same clips); "auto": torch on a GPU, numpy on the CPU
    time_budget: float = 0.0  # seconds from the start of the run: stop cleanly with a checkpoint before it (0: none)
    channels_last: bool = False  # convolutions on NHWC tensors (cscsr.network.model.use_channels_last): the same
    # training within float rounding, faster where the device's kernels prefer that layout

    def network(self) -> CSCSRConfig:
        """The configuration this run trains: the named one with its ablation switches applied."""
        return named(self.config).ablate(motion=self.motion, flow_guidance=self.flow_guidance)

    def check(self) -> "TrainOptions":
        """Refuse options that cannot train, before any output exists (the command line and the Python API)."""
        self.network()
        for label, value in (("steps", self.steps), ("batch", self.batch), ("checkpoint_every", self.checkpoint_every),
                             ("validate_every", self.validate_every), ("validation_clips", self.validation_clips),
                             ("warmup", self.warmup), ("decay_every", self.decay_every)):
            check_number(label, value, at_least=1, integer=True)
        check_number("lr_side", self.lr_side, integer=True)
        if self.lr_side < 16 or self.lr_side % 2:
            raise InputError(f"lr_side must be even and >= 16, got {self.lr_side}")
        check_number("pool", self.pool, at_least=0, integer=True)  # -1 was truthy: a pool of no clips, then a crash
        check_number("seed", self.seed, at_least=0, at_most=2**63 - 1, integer=True)  # -1 failed after OUT existed
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
        """Clips made by ``cscsr.training.synthesis`` on the training device rather than by numpy (auto: on a GPU)."""
        if self.synthesis == "auto":
            return torch.device(self.device).type != "cpu"
        return self.synthesis == "torch"

    def picture_folders(self) -> list[str]:
        return [f for f in self.pictures.split(os.pathsep) if f]


SYNTHESES = ("auto", "numpy", "torch")
