"""Named configurations of the CSCSR network, and the ablation switches the paper studies.

A configuration is plain data: it travels in the weights file's metadata (as JSON) so a
file always rebuilds the network that made it. ``full`` is sized like the paper (about
5.4 M parameters without the flow network); ``lite`` (about 1 M) is for CPU work.
"""

import json
from dataclasses import asdict, dataclass, fields, replace

from stages.errors import InputError
from stages.reconstruction.methods import WINDOW

PRECISIONS = ("fp32", "bf16")  # the network's arithmetic: float32, or bfloat16 autocast (weights stay float32)
BACKENDS = ("torch", "onnx")  # what runs the network: PyTorch, or ONNX Runtime on the CPU (cscsr.inference.onnx_runtime)

MOTIONS = ("joint", "assembled")
COLOURS = (3, 1)  # colour branches: a Bayer network's R, G, B, or a mono network's one


@dataclass(frozen=True)
class CSCSRConfig:
    name: str
    frames: int = WINDOW  # N: spike frames per clip, the output is at frame N // 2
    length: int = 11  # w: frames per BSSR time point
    stride: int = 3  # s: frames between BSSR time points -> N' = (N - w + s) / s
    colour_features: int = 32  # C: features per colour and time point (BSSR, alignment)
    features: int = 64  # F: width of the integration trunk
    blocks: int = 16  # ResBlocks in the integration trunk
    flow_features: int = 32  # width of the compact spike-flow network (counted apart)
    flow_frames: int = 21  # spike frames seen per motion time point (as Spike2Flow)
    flow_span: int = 9  # motion time points are the centre -/+ this many frames (11 and 29 of 41)
    motion: str = "joint"  # "joint": one flow from R, G1, G2, B together; "assembled": per channel
    flow_guidance: bool = True  # False: time points are fused unaligned (ablation)
    colours: int = 3  # 3: a Bayer (RGB) network; 1: mono (one branch, all-pixel mask, grey output as 3 equal channels)

    @property
    def mono(self) -> bool:
        return self.colours == 1

    @property
    def time_points(self) -> int:
        """N' = (N - w + s) / s, centred on frames w//2, w//2 + s, ..."""
        return (self.frames - self.length + self.stride) // self.stride

    def centres(self) -> list[int]:
        return [self.length // 2 + i * self.stride for i in range(self.time_points)]

    def check(self) -> "CSCSRConfig":
        """Refuse settings that cannot cover the clip symmetrically (supplement, eq. 1)."""
        for name in ("frames", "length", "stride", "colour_features", "features", "blocks", "flow_features",
                     "flow_frames", "flow_span"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < (0 if name == "blocks" else 1):
                raise InputError(f"configuration {name} must be a positive integer, got {value!r}")
        if self.colours not in COLOURS:
            raise InputError(f"configuration colours must be 3 (Bayer) or 1 (mono), got {self.colours!r}")
        if self.motion not in MOTIONS:
            raise InputError(f"unknown motion estimation {self.motion!r}: expected one of {', '.join(MOTIONS)}")
        if self.frames % 2 == 0 or self.length % 2 == 0:
            raise InputError(f"frames ({self.frames}) and window length w ({self.length}) must be odd")
        if (self.frames - self.length) % self.stride or self.frames // 2 not in self.centres():
            raise InputError(f"w={self.length}, s={self.stride} do not put a time point on the middle frame of "
                             f"{self.frames} (need (N - w) divisible by s and N' odd)")
        middle = self.frames // 2
        half = self.flow_frames // 2
        if middle - self.flow_span - half < 0 or middle + self.flow_span + half >= self.frames:
            raise InputError(f"motion time points {middle - self.flow_span} and {middle + self.flow_span} with "
                             f"{self.flow_frames} frames each do not fit in {self.frames} frames")
        return self

    def to_json(self) -> str:
        return json.dumps(asdict(self), sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> "CSCSRConfig":
        values = json.loads(text)
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise InputError(f"unknown configuration fields {', '.join(unknown)}")
        return cls(**values).check()

    def ablate(self, **changes) -> "CSCSRConfig":
        """This configuration with switches changed (``motion``, ``flow_guidance``, ``length``, ``stride``)."""
        return replace(self, **changes).check()


CONFIGS = {
    "full": CSCSRConfig("full", colour_features=50, features=96, blocks=21, flow_features=48),
    "lite": CSCSRConfig("lite", colour_features=24, features=48, blocks=13, flow_features=24),
    "lite-mono": CSCSRConfig("lite-mono", colour_features=24, features=48, blocks=13, flow_features=24, colours=1),
}


def named(name: str) -> CSCSRConfig:
    if name not in CONFIGS:
        raise InputError(f"unknown configuration {name!r}: expected one of {', '.join(CONFIGS)}")
    return CONFIGS[name]
