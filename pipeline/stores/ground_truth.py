"""The ground truth a simulated spike store carries beside its spikes ([formats](../docs/formats.md)).

Layout, in the same Zarr group as ``spikes`` (``pipeline.stores.spike_store``):

- ``truth`` uint8 ``(K, s*H, s*W, 3)``, dimensions ``k, hr_y, hr_x, c``: the HR picture at each
  41-frame window centre, one chunk per frame;
- ``truth_frames`` int64 ``(K,)``, dimension ``k``: the spike frame each picture shows (the
  coordinate of ``truth``);
- ``flow`` float32 ``(K-1, s*H, s*W, 2)``, dimensions ``k_flow, hr_y, hr_x, d``, only under
  synthetic camera motion: ``flow[k]`` (dx, dy) in HR pixels carries ``truth[k]`` at x to
  ``truth[k+1]`` at x + flow.

The simulator declares the arrays here and its workers fill them one frame each; ``evaluate`` and
the test set read them back here.
"""

import numpy as np
import zarr

from pipeline.stores.spike_store import SpikeStore, SpikeStoreWriter, write_region
from stages.errors import InputError

TRUTH, TRUTH_FRAMES, FLOW = "truth", "truth_frames", "flow"
TRUTH_UNITS = "8-bit RGB, the source's values"
FLOW_CONVENTION = "flow[k] (dx, dy) HR pixels: truth[k] at x is truth[k+1] at x + flow"


def declare_truth(writer: SpikeStoreWriter, centres: list[int], hr_size: tuple[int, int], fps: float,
                  with_flow: bool) -> None:
    """Declare ``truth`` and ``truth_frames`` (filled with ``centres``), and ``flow`` if ``with_flow``."""
    n = len(centres)
    writer.add_array(TRUTH, (n, *hr_size, 3), (1, *hr_size, 3), np.uint8, ("k", "hr_y", "hr_x", "c"),
                     {"units": TRUTH_UNITS, "coordinates": TRUTH_FRAMES})
    writer.add_array(TRUTH_FRAMES, (n,), (max(n, 1),), np.int64, ("k",), {"units": "spike frame index", "fps": fps})
    writer.group[TRUTH_FRAMES][:] = np.asarray(centres, np.int64)
    if with_flow and n > 1:
        writer.add_array(FLOW, (n - 1, *hr_size, 2), (1, *hr_size, 2), np.float32,
                         ("k_flow", "hr_y", "hr_x", "d"), {"units": "HR pixels, (dx, dy)"})
        writer.group.attrs["flow_convention"] = FLOW_CONVENTION


def write_truth(url: str, index: int, image: np.ndarray) -> None:
    """Fill ``truth[index]`` with an (s*H, s*W, 3) uint8 picture (run by a worker)."""
    write_region(url, TRUTH, index, image[None])


def write_flow(url: str, index: int, flow: np.ndarray) -> None:
    """Fill ``flow[index]`` with an (s*H, s*W, 2) float32 field (run by a worker)."""
    write_region(url, FLOW, index, flow[None])


def has_truth(group: zarr.Group) -> bool:
    return TRUTH in group and TRUTH_FRAMES in group


def read_truth(store: SpikeStore) -> tuple[zarr.Array, np.ndarray]:
    """(``truth``, its spike frames) of a simulated store; a one-line error for a store without them."""
    if not has_truth(store.group):
        raise InputError(f"{store.url} has no ground truth ('{TRUTH}', '{TRUTH_FRAMES}'): make one with cscsr simulate")
    return store.group[TRUTH], store.group[TRUTH_FRAMES][:]
