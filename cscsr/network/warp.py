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
    # (B, 2, H, W) absolute positions, float32 whatever the features' dtype or autocast: bfloat16 holds integers
    # exactly only up to 256 (at LR 1008 a bf16 grid put samples up to 4.3 px off); a bf16 flow adds to the
    # float32 grid by type promotion, so the sum is float32 too, with no cast
    where = pixel_grid(h, w, x.device) + flow
    if x.dtype != torch.float32 and not torch.is_autocast_enabled(x.device.type):
        return bilinear(x, where, padding)  # reduced-precision features (the bf16 GPU path): no cast of them
    gx = 2 * where[:, 0] / max(w - 1, 1) - 1
    gy = 2 * where[:, 1] / max(h - 1, 1) - 1
    grid = torch.stack([gx, gy], dim=-1)  # (B, H, W, 2) in [-1, 1], float32
    return F.grid_sample(x, grid, mode="bilinear", padding_mode=padding, align_corners=True)


def bilinear(x: torch.Tensor, where: torch.Tensor, padding: str = "border") -> torch.Tensor:
    """``grid_sample`` (bilinear, ``align_corners=True``) for features of any dtype at float32 positions, with no
    cast of the features: each output pixel is the weighted sum of its four neighbours' rows of the NHWC table
    (one ``embedding_bag``). Positions and weights are float32; only the four weights a pixel are rounded to the
    features' dtype. (B, C, H, W) features, (B, 2, H, W) positions (x, y) in pixels -> (B, C, H, W), channels-last."""
    b, c, h, w = x.shape
    px, py = where[:, 0], where[:, 1]  # (B, H, W) each, float32
    if padding == "border":  # grid_sample's border padding clips the positions to the frame
        px, py = px.clamp(0, w - 1), py.clamp(0, h - 1)
    x0, y0 = px.floor(), py.floor()
    fx, fy = px - x0, py - y0  # (B, H, W) in [0, 1)
    ix, iy = x0.long(), y0.long()
    base = torch.arange(b, device=x.device)[:, None, None] * (h * w)  # (B, 1, 1): each clip's first row
    index, weights = [], []
    for dy in (0, 1):
        for dx in (0, 1):
            cx, cy = ix + dx, iy + dy  # (B, H, W) the corner's pixel
            weight = (fx if dx else 1 - fx) * (fy if dy else 1 - fy)
            inside = (cx >= 0) & (cx < w) & (cy >= 0) & (cy < h)  # zeros padding: corners outside give 0
            weights.append(weight * inside)
            index.append(base + cy.clamp(0, h - 1) * w + cx.clamp(0, w - 1))
    table = x.permute(0, 2, 3, 1).reshape(b * h * w, c)  # (B*H*W, C): a view of a channels-last x
    out = F.embedding_bag(torch.stack(index, -1).view(-1, 4), table, mode="sum",
                          per_sample_weights=torch.stack(weights, -1).view(-1, 4).to(x.dtype))  # (B*H*W, C)
    return out.view(b, h, w, c).permute(0, 3, 1, 2)  # (B, C, H, W) stored channels-last
