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
    where = pixel_grid(h, w, x.device, x.dtype) + flow  # (B, 2, H, W) absolute positions
    gx = 2 * where[:, 0] / max(w - 1, 1) - 1
    gy = 2 * where[:, 1] / max(h - 1, 1) - 1
    grid = torch.stack([gx, gy], dim=-1)  # (B, H, W, 2) in [-1, 1]
    return F.grid_sample(x, grid, mode="bilinear", padding_mode=padding, align_corners=True)
