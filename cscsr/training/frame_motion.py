"""Real motion for training clips, from folders of consecutive frames of footage.

**Which folders are sequences.** A folder (its files directly, not its sub-folders) is a
sequence of frames when it holds at least 3 picture files, all named ``<prefix><number><suffix>``
with one prefix, one suffix and one extension, and the numbers are consecutive (n, n+1, n+2, ...):
``00000.jpg ... 00006.jpg`` (DAVIS), ``frame_001.png ... frame_007.png`` (Vid4). Any other
folder holds stills: BSDS500's numbered photographs are not consecutive, Urban100's
``img_001 ... img_099`` go in steps of 2. A folder of stills that happens to be numbered
consecutively is taken as footage: rename or thin it to keep it still.

**A clip of footage.** Three consecutive frames k-1, k, k+1, cropped alike, make the 41 frames of
a clip: spike frame 0 is frame k-1, frame 20 (the truth) is frame k, frame 40 is frame k+1, and
the frames between are interpolated along the optical flow between them (DIS, estimated on the
crops: ``A(p) ~ B(p + f(p))``). At time ``a`` in (0, 1] towards a neighbour B, with f the flow
from the centre A to B:

    frame(p) = (1 - a) A(p - a f(p)) + a B(p + (1 - a) f(p))     (bicubic, reflect-101)

which at a = 0 is A itself and at a = 1 is B itself; a picture moving by d per frame gives its
shift by a d at every a (tested). The clip's key flows (middle to frames 11 and 29) are the
estimated flows times 9/20, not exact ones as for a camera path.
"""

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np


MIN_FRAMES = 3
_NUMBERED = re.compile(r"(.*?)(\d+)(\D*)")


def sequence_frames(files: list[str]) -> tuple[str, ...] | None:
    """The files of one folder in frame order if they are a sequence of frames (the rule above), else None."""
    if len(files) < MIN_FRAMES:
        return None
    parsed = []
    for name in files:
        path = Path(name)
        match = _NUMBERED.fullmatch(path.stem)
        if not match:
            return None
        parsed.append(((match[1], match[3], path.suffix.lower()), int(match[2]), name))
    if len({key for key, _, _ in parsed}) != 1:
        return None
    parsed.sort(key=lambda item: item[1])
    numbers = [number for _, number, _ in parsed]
    if numbers != list(range(numbers[0], numbers[0] + len(numbers))):
        return None
    return tuple(name for _, _, name in parsed)


def group_sequences(names: tuple[str, ...]) -> tuple:
    """Picture files -> training sources: each still a name, each folder that is a sequence one tuple of its
    frames in order (in the place of its first frame)."""
    by_folder: dict[str, list[str]] = {}
    for name in names:
        by_folder.setdefault(str(Path(name).parent), []).append(name)
    sequences = {folder: sequence_frames(files) for folder, files in by_folder.items()}
    sources, placed = [], set()
    for name in names:
        frames = sequences.get(str(Path(name).parent))
        if frames is None:
            sources.append(name)
        elif frames not in placed:
            sources.append(frames)
            placed.add(frames)
    return tuple(sources)


def source_names(sources) -> list[str]:
    """Every picture file of training sources (stills and the frames of sequences)."""
    return [n for s in sources for n in ((s,) if isinstance(s, str) else s)]


def choices(source) -> int:
    """How many clips a source offers: one for a still, one per frame with a neighbour on each side."""
    return 1 if isinstance(source, str) else len(source) - 2


def estimate_flow(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(H, W, 2) float32 (dx, dy): the point seen at p in frame ``a`` is seen at p + flow(p) in ``b``
    (DIS optical flow on the grey frames; (H, W, 3) float32 in [0, 1] each)."""
    import cv2

    def grey(image):
        return np.ascontiguousarray(np.clip(image.mean(2) * 255 + 0.5, 0, 255).astype(np.uint8))

    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    return dis.calc(grey(a), grey(b), None).astype(np.float32)


@dataclass(frozen=True)
class FrameMotion:
    """The motion of a clip of footage: the centre frame's neighbours (cropped as the centre, which is the
    plan's picture) and the flows from the centre to each; plays the part of a camera path."""

    before: np.ndarray  # (S, S, 3) float32 frame k-1
    after: np.ndarray  # (S, S, 3) float32 frame k+1
    flow_before: np.ndarray  # (S, S, 2) float32 centre -> frame k-1, HR pixels (x, y)
    flow_after: np.ndarray  # (S, S, 2) float32 centre -> frame k+1

    @classmethod
    def between(cls, before: np.ndarray, centre: np.ndarray, after: np.ndarray) -> "FrameMotion":
        return cls(before, after, estimate_flow(centre, before), estimate_flow(centre, after))

    @staticmethod
    def towards(t: float, frames: int) -> tuple[float, str]:
        """Frame t's place between the centre (0) and a neighbour (1), and which neighbour."""
        middle = (frames - 1) / 2
        return abs(t - middle) / middle, ("after" if t > middle else "before")

    def flow(self, t: float, frames: int) -> np.ndarray:
        """(S, S, 2) float32 flow from the middle frame to frame t (the estimated flow, scaled)."""
        a, side = self.towards(t, frames)
        return (a * getattr(self, f"flow_{side}")).astype(np.float32)

    def render(self, centre: np.ndarray, t: float, frames: int) -> np.ndarray:
        """Latent frame t: (S, S, 3) float32 in [0, 1], interpolated along the flow (module docstring)."""
        a, side = self.towards(t, frames)
        if a == 0:
            return centre
        flow, other = getattr(self, f"flow_{side}"), getattr(self, side)
        frame = (1 - a) * _sample(centre, -a * flow) + a * _sample(other, (1 - a) * flow)
        return np.clip(frame, 0, 1)


def _sample(image: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """``image`` sampled at p + offset(p) (cv2.remap, bicubic, BORDER_REFLECT_101)."""
    import cv2

    height, width = offset.shape[:2]
    map_x = (offset[..., 0] + np.arange(width, dtype=np.float32)).astype(np.float32)
    map_y = (offset[..., 1] + np.arange(height, dtype=np.float32)[:, None]).astype(np.float32)
    return cv2.remap(image, map_x, map_y, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT_101)

