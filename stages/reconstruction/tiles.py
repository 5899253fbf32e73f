"""Cutting a frame into tiles with halos, and cropping the halo off again.

Tiles start on even rows and columns, so every tile sees the frame's CFA phase; the halo
is clipped at the frame's edges, so an edge tile sees exactly what the whole frame sees.
"""

from dataclasses import dataclass

from stages.errors import InputError


@dataclass(frozen=True)
class Tile:
    """A tile ``[y0, y1) x [x0, x1)`` of the LR frame and the halo-padded region it reads."""

    y0: int
    y1: int
    x0: int
    x1: int
    ry0: int  # read region, halo included and clipped to the frame
    ry1: int
    rx0: int
    rx1: int

    def crop(self, scale: int) -> tuple[slice, slice]:
        """Slices of the HR output of the read region that belong to the tile."""
        return (slice((self.y0 - self.ry0) * scale, (self.y1 - self.ry0) * scale),
                slice((self.x0 - self.rx0) * scale, (self.x1 - self.rx0) * scale))


def tile_grid(height: int, width: int, tile: int, halo: int,
              region: tuple[int, int, int, int] | None = None) -> list[list[Tile]]:
    """Rows of tiles of at most ``tile`` x ``tile`` LR pixels (``tile`` a multiple of 8) of a ``height`` x
    ``width`` frame, or of its ``region`` (y0, y1, x0, x1; on even rows and columns for a Bayer CFA): tiles
    cut inside the region from its corner, their halo read from outside it where the frame has pixels."""
    top, bottom, left, right = region or (0, height, 0, width)
    rows = []
    for y0 in range(top, bottom, tile):
        row = []
        for x0 in range(left, right, tile):
            y1, x1 = min(y0 + tile, bottom), min(x0 + tile, right)
            row.append(Tile(y0, y1, x0, x1, max(y0 - halo, 0), min(y1 + halo, height),
                            max(x0 - halo, 0), min(x1 + halo, width)))
        rows.append(row)
    return rows


def device_tile(height: int, width: int, halo: int, budget_bytes: float, bytes_per_pixel: float,
                most_windows: int) -> tuple[int, int]:
    """The tile side and windows per pass that fit ``budget_bytes`` of device memory, a window taking
    ``bytes_per_pixel`` per LR pixel it reads. The whole frame when one window of it fits (no halo
    computed twice), with as many windows per pass as fit (at most ``most_windows``); else the largest
    tile (a multiple of 8) whose halo-padded read fits, one window per pass. -> (tile, windows)."""
    whole = height * width * bytes_per_pixel
    if whole <= budget_bytes:
        return -(-max(height, width) // 8) * 8, max(1, min(most_windows, int(budget_bytes // whole)))
    side = int((budget_bytes / bytes_per_pixel) ** 0.5) - 2 * halo  # read side = tile + 2 halos
    tile = side // 8 * 8
    if tile < 8:
        raise InputError(f"the GPU's memory ({budget_bytes / 2**30:.1f} GiB usable) holds no tile of 8 LR pixels "
                         f"with a {halo}-pixel halo")
    return tile, 1
