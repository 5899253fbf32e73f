"""Backward warping by a dense flow, at sub-pixel precision (bilinear ``grid_sample``).

``warp(x, flow)[p] = x[p + flow[p]]``: with the flow from the middle time point to time
point k, it brings time point k's features onto the middle one's pixel grid.
"""

import torch
import torch.nn.functional as F


def pixel_grid(height: int, width: int, device=None, dtype=torch.float32) -> torch.Tensor:
    """(1, 2, H, W) x and y pixel coordinates."""
    ys, xs = torch.meshgrid(torch.arange(height, device=device, dtype=dtype),
                            torch.arange(width, device=device, dtype=dtype), indexing="ij")
    return torch.stack([xs, ys])[None]


def warp(x: torch.Tensor, flow: torch.Tensor, padding: str = "border") -> torch.Tensor:
    """(B, C, H, W) features, (B, 2, H, W) flow in pixels (x, y) -> (B, C, H, W) warped.

    ``padding="zeros"`` makes what comes from outside the frame 0: warp a mask that way to
    know where real samples landed.
    """
    _, _, h, w = x.shape
    if uses_sampler(x):  # reduced-precision features (the bf16 GPU path): no cast of them
        return sample(x, sampling_plan(flow, h, w, padding, x.dtype))
    # (B, 2, H, W) absolute positions, float32 whatever the features' dtype or autocast: bfloat16 holds integers
    # exactly only up to 256 (at LR 1008 a bf16 grid put samples up to 4.3 px off); a bf16 flow adds to the
    # float32 grid by type promotion, so the sum is float32 too, with no cast
    where = pixel_grid(h, w, x.device) + flow
    gx = 2 * where[:, 0] / max(w - 1, 1) - 1
    gy = 2 * where[:, 1] / max(h - 1, 1) - 1
    grid = torch.stack([gx, gy], dim=-1)  # (B, H, W, 2) in [-1, 1], float32
    return F.grid_sample(x, grid, mode="bilinear", padding_mode=padding, align_corners=True)


def uses_sampler(x: torch.Tensor) -> bool:
    """Features in a reduced precision outside autocast (the GPU path's bf16) go through :func:`sample`;
    float32, and anything under autocast (which runs ``grid_sample`` in float32), through ``grid_sample``."""
    return x.dtype not in (torch.float32, torch.float64) and not torch.is_autocast_enabled(x.device.type)


class SharedFlow:
    """A flow (B, 2, H, W) that several tensors are warped by (every colour's features and masks): the
    sampler's plan is worked out once per padding and dtype, not once per tensor (and its indices once for
    both paddings). ``warp(x, padding)``."""

    def __init__(self, flow: torch.Tensor):
        self.flow, self._plans, self._indices = flow, {}, {}

    def warp(self, x: torch.Tensor, padding: str = "border") -> torch.Tensor:
        if not uses_sampler(x):
            return warp(x, self.flow, padding)
        h, w = x.shape[-2:]
        key = (padding, x.dtype, h, w)
        if key not in self._plans:
            if (h, w) not in self._indices:
                self._indices[(h, w)] = sampling_indices(self.flow, h, w)
            self._plans[key] = sampling_plan(self.flow, h, w, padding, x.dtype, self._indices[(h, w)])
        return sample(x, self._plans[key])


def sampling_indices(flow: torch.Tensor, h: int, w: int):
    """The float32 positions' corners for a (B, 2, H, W) flow: the four neighbours' rows of a (B*H*W, C) NHWC
    table, (B, H, W, 4) int32, clamped into the frame; per axis (x, y), the top-left corner, (B, H, W) float32
    (exact integers), and the fraction, (B, H, W) float32 in [0, 1).

    Positions become pixel indices with no dtype conversion: ``floor(p)`` clamped into [0, W-1] is the number of
    pixel boundaries 1..W-1 at or before ``p``, and ``floor(p) + 1`` clamped the number of boundaries 0..W-2,
    which ``torch.bucketize`` counts straight into int32."""
    b = flow.shape[0]
    edges = torch.arange(max(h, w), device=flow.device, dtype=torch.float32)  # pixel boundaries 0, 1, 2, ...
    grids = edges[:w], edges[:h, None]  # x of each column, y of each row: float32 integers
    first = torch.arange(b, device=flow.device, dtype=torch.int32)[:, None, None] * (h * w)  # each clip's row 0
    corners, fractions, near = [], [], []
    for axis, size in ((0, w), (1, h)):
        where = torch.empty((b, h, w), dtype=torch.float32, device=flow.device)  # contiguous, as bucketize reads
        torch.add(grids[axis], flow[:, axis], out=where)  # float32 positions (a bf16 flow promotes by the add)
        corners.append(where.floor())
        fractions.append(where - corners[-1])
        if torch.compiler.is_compiling():  # inductor (torch 2.11, CUDA) cannot lower bucketize over a slice
            near.append([(corners[-1] + (1 - d)).clamp(0, size - 1).int() for d in (1, 0)])  # the same counts
        else:
            near.append([torch.bucketize(where, edges[d : size - 1 + d], out_int32=True, right=True) for d in (1, 0)])
    cols, rows = near[0], [r.mul_(w).add_(first) for r in near[1]]  # floor(p) + d clamped; rows of the table
    if torch.compiler.is_compiling():  # out= into a view breaks a graph; the compiler fuses these anyway
        return torch.stack([rows[dy] + cols[dx] for dy, dx in CORNERS], -1), corners, fractions
    index = torch.empty((b, h, w, 4), dtype=torch.int32, device=flow.device)
    for k, (dy, dx) in enumerate(CORNERS):
        torch.add(rows[dy], cols[dx], out=index[..., k])
    return index, corners, fractions


CORNERS = ((0, 0), (0, 1), (1, 0), (1, 1))  # (dy, dx) of the four neighbours, in the plan's order


def sampling_plan(flow: torch.Tensor, h: int, w: int, padding: str, dtype: torch.dtype, indices=None):
    """Where ``grid_sample`` (bilinear, ``align_corners=True``) reads for a (B, 2, H, W) flow: the four
    neighbours' rows of a (B*H*W, C) NHWC table, (B, H, W, 4) int32, and their weights, (B, H, W, 4) in
    ``dtype``. Positions and weights are worked out in float32; the weights are written in ``dtype``.
    ``border``: corners clamped into the frame with their weights kept, which is grid_sample's clamping of
    the position (both corners outside land on the edge pixel, their weights summing to 1); ``zeros``:
    corners outside weigh 0."""
    b = flow.shape[0]
    index, corner, fraction = indices or sampling_indices(flow, h, w)
    fx, fy = fraction
    wx, wy = [1 - fx, fx], [1 - fy, fy]
    if padding == "zeros":  # corner + d outside [0, size - 1], compared in float32 (exact integers)
        ix, iy = corner
        for d in (0, 1):
            wx[d] = wx[d].masked_fill((ix < -d) | (ix >= w - d), 0)
            wy[d] = wy[d].masked_fill((iy < -d) | (iy >= h - d), 0)
    if torch.compiler.is_compiling():
        return index, torch.stack([wy[dy] * wx[dx] for dy, dx in CORNERS], -1).to(dtype)
    weights = torch.empty((b, h, w, 4), dtype=dtype, device=flow.device)
    for k, (dy, dx) in enumerate(CORNERS):
        torch.mul(wy[dy], wx[dx], out=weights[..., k])  # float32 product written in dtype: no cast op
    return index, weights


def sample(x: torch.Tensor, plan) -> torch.Tensor:
    """(B, C, H, W) features (any dtype; no cast of them) and a :func:`sampling_plan` -> (B, C, H, W) warped,
    stored channels-last: each output pixel the weighted sum of four rows of the NHWC table (one
    ``embedding_bag``)."""
    index, weights = plan
    b, c, h, w = x.shape
    table = x.permute(0, 2, 3, 1).reshape(b * h * w, c)  # (B*H*W, C): a view of a channels-last x
    out = F.embedding_bag(index.view(-1, 4), table, mode="sum", per_sample_weights=weights.view(-1, 4))
    return out.view(b, h, w, c).permute(0, 3, 1, 2)  # (B, C, H, W) stored channels-last

