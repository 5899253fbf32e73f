"""Cutting a frame into tiles with halos, and cropping the halo off again.

Tiles start on even rows and columns, so every tile sees the frame's CFA phase; the halo
is clipped at the frame's edges, so an edge tile sees exactly what the whole frame sees.
"""

from dataclasses import dataclass


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


def tile_grid(height: int, width: int, tile: int, halo: int) -> list[list[Tile]]:
    """Rows of tiles of at most ``tile`` x ``tile`` LR pixels (``tile`` a multiple of 8)."""
    rows = []
    for y0 in range(0, height, tile):
        row = []
        for x0 in range(0, width, tile):
            y1, x1 = min(y0 + tile, height), min(x0 + tile, width)
            row.append(Tile(y0, y1, x0, x1, max(y0 - halo, 0), min(y1 + halo, height),
                            max(x0 - halo, 0), min(x1 + halo, width)))
        rows.append(row)
    return rows
