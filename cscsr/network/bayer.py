"""The CFA phase as tensors: colour masks and the four half-resolution channels.

The network never guesses the pattern: every clip comes with its CFA string, turned here
into masks that the representation multiplies the spikes with. A crop, flip or shift that
changes the phase changes the string, and so the masks, with it.
"""

import torch
import torch.nn.functional as F

from stages.reconstruction.cfa import BAYER_PATTERNS
from stages.errors import InputError

# The four half-resolution channels of the joint motion estimation (supplement, Fig. 3a):
# G1 is the green on the red row, G2 the green on the blue row.
HALF_CHANNELS = ("r", "g1", "g2", "b")
MONO_PHASES = ((0, 0), (0, 1), (1, 0), (1, 1))  # a mono network's four cells: the same split, one colour


def check_cfa(cfa: str, mono: bool) -> str:
    """The clip's CFA for a Bayer network (a Bayer pattern) or a mono one (``mono``), else one line naming both."""
    name = str(cfa).lower()
    if mono and name != "mono":
        raise InputError(f"this is a mono CSCSR network and the clip's CFA is {cfa!r}: it takes mono clips only")
    if not mono and name == "mono":
        raise InputError("this is a colour (Bayer) CSCSR network and the clip is mono: use a mono network")
    return name if mono else check_bayer(name)


def check_bayer(cfa: str) -> str:
    name = str(cfa).lower()
    if name not in BAYER_PATTERNS:
        raise InputError(f"the CSCSR network needs a Bayer CFA ({', '.join(BAYER_PATTERNS)}), got {cfa!r}")
    return name


def positions(cfa: str) -> dict[str, tuple[int, int]]:
    """(row, column) inside the 2x2 cell of R, G1, G2 and B."""
    cell = {(0, 0): cfa[0], (0, 1): cfa[1], (1, 0): cfa[2], (1, 1): cfa[3]}
    red = next(p for p, c in cell.items() if c == "r")
    blue = next(p for p, c in cell.items() if c == "b")
    return {"r": red, "g1": (red[0], 1 - red[1]), "g2": (blue[0], 1 - blue[1]), "b": blue}


def cell_masks(cfas: list[str], height: int, width: int, device=None, dtype=torch.float32) -> torch.Tensor:
    """(B, 4, H, W) float 0/1 masks of R, G1, G2, B for each clip's pattern (mono: the 2x2 cell's four phases)."""
    masks = torch.zeros(len(cfas), 4, height, width, device=device, dtype=dtype)  # 0/1: exact in any dtype
    for b, cfa in enumerate(cfas):
        cells = MONO_PHASES if cfa == "mono" else positions(check_bayer(cfa)).values()
        for c, (dy, dx) in enumerate(cells):
            masks[b, c, dy::2, dx::2] = 1
    return masks


def colour_masks(cells: torch.Tensor, mono: bool = False) -> torch.Tensor:
    """(B, 4, H, W) R, G1, G2, B masks -> (B, 3, H, W) R, G, B masks (G1 and G2 together); ``mono``: the four
    phases together, (B, 1, H, W) ones (sums of slices, as for colour: shapes an ONNX trace can follow)."""
    if mono:
        return (cells[:, 0] + cells[:, 1] + cells[:, 2] + cells[:, 3])[:, None]
    return torch.stack([cells[:, 0], cells[:, 1] + cells[:, 2], cells[:, 3]], dim=1)


def split_half(spikes: torch.Tensor, cells: torch.Tensor) -> torch.Tensor:
    """(B, T, H, W) spikes -> (B, 4, T, H/2, W/2): each of R, G1, G2, B with no missing pixels.

    The supplement's "split": multiply by the channel's mask, then 2x2 max pooling.
    """
    b, t, h, w = spikes.shape
    masked = spikes[:, None] * cells[:, :, None]  # (B, 4, T, H, W)
    return F.max_pool2d(masked.reshape(b * 4 * t, 1, h, w), 2).reshape(b, 4, t, h // 2, w // 2)


def pick_half(spikes: torch.Tensor, cells: torch.Tensor) -> torch.Tensor:
    """:func:`split_half` for spikes that are not negative (0/1) and masks with one pixel per 2x2 cell (every
    channel of :func:`cell_masks`, Bayer or mono): the maximum of a cell's masked spikes is the spike at the
    channel's pixel, so that pixel is picked out, by one gather (the GPU path: no (B, 4, T, H, W) product, no
    pooling). (B, T, H, W) -> (B, 4, T, H/2, W/2), the same values."""
    b, t, h, w = spikes.shape
    where = cells[:, :, :2, :2].flatten(2).argmax(2)  # (B, 4): each channel's pixel in the cell, 2 dy + dx
    cell = spikes.view(b, t, h // 2, 2, w // 2, 2).permute(0, 3, 5, 1, 2, 4)  # (B, 2, 2, T, H/2, W/2), a view
    return cell[torch.arange(b, device=spikes.device)[:, None], where // 2, where % 2]  # (B, 4, T, H/2, W/2)
