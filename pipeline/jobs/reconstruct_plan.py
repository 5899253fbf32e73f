"""What a reconstruction job will do, as frozen data: its options, what every task shares (``Plan``)
and which tiles join one network pass (``tile_blocks``). Nothing here touches a cluster or a store;
``pipeline.jobs.reconstruct`` checks a job, makes its plan, cuts its blocks (``pipeline.jobs.reconstruct_tasks``) and runs
them (``pipeline.compute.executor``).
"""

from dataclasses import dataclass
from typing import NamedTuple


from cscsr.network.config import BACKENDS, PRECISIONS
from pipeline.stores.storage import recorded
from stages.errors import InputError
from stages.reconstruction.methods import METHODS, NETWORKS, WINDOW, output_centres
from stages.reconstruction.colour import check_gain
from stages.numbers import check_flag, check_number, check_text
from stages.reconstruction.ranges import first_at, parse_region, parse_time, region, time_range
from stages.reconstruction.tiles import Tile

SEGMENT_TASKS = 10_000  # minutes of work on any real frame size; a fresh process and cluster cost ~5 s
DEFAULT_TILE = 256  # LR pixels, on CPU workers: a 1000x1000 frame becomes 16 tasks of 1024x1024 HR (on GPU workers
# the tile is sized for the device's memory: cscsr.inference.device_memory, stages.reconstruction.tiles.device_tile)
GPU_BATCH = 16  # the most windows per network pass on a GPU worker (fewer where the device's memory holds fewer)
DEFAULT_WEIGHTS = {"gpu": "full", "cpu": "lite"}  # where the network runs -> the weights a job takes by default
MONO_WEIGHTS = "lite-mono"  # a mono recording's default, wherever the network runs (no full-mono yet)


def default_weights(gpus: bool, cfa: str) -> str:
    """The weights a network job takes without ``--weights``: the mono ones for a mono recording, else ``full``
    on GPU workers and ``lite`` on CPUs."""
    return MONO_WEIGHTS if cfa == "mono" else DEFAULT_WEIGHTS["gpu" if gpus else "cpu"]


@dataclass(frozen=True)
class ReconstructOptions:
    method: str = "tfp"
    every: int = WINDOW
    window: int = WINDOW
    gain: float | None = None
    scale: int | None = None  # default: the store's scale, else 4
    tile: int | None = None  # None: DEFAULT_TILE on CPU workers, sized for the device's memory on GPU workers
    weights: str | None = None  # None: DEFAULT_WEIGHTS by where the network runs
    resume: bool = False
    overwrite: bool = False
    segment_tasks: int = SEGMENT_TASKS  # tasks per fresh cluster when the job starts its own (bounded memory)
    precision: str = "fp32"  # the network's: fp32, or bf16 (autocast on the worker's device)
    gpu_batch: int | None = None  # windows per task and per network pass on GPU workers (None: what fits, <= GPU_BATCH)
    backend: str = "torch"  # what runs the network: torch, or onnx (ONNX Runtime, CPU)
    fast_gpu: bool = False  # on GPU workers: channels-last, cuDNN autotuning, torch.compile (a CPU ignores it)
    # the part of the recording to reconstruct (stages.reconstruction.ranges): spike frames (int, or "1200") or seconds with a
    # unit ("2.5s", "1500ms"); a region "Y0:Y1,X0:X1" or (y0, y1, x0, x1) in LR pixels. None: the whole of it
    start: int | str | None = None
    stop: int | str | None = None
    region: str | tuple | None = None

    def check(self) -> None:
        """Every check that needs no recording (see :func:`check_options` for the rest)."""
        # types first (only the Python API can get them wrong): "5" < 1 would fail deep inside, "no" is true
        for name in ("method", "precision", "backend"):
            check_text(f"--{name}", getattr(self, name))
        check_text("--weights", self.weights, optional=True)
        for name in ("every", "window", "segment_tasks"):
            check_number(f"--{name.replace('_', '-')}", getattr(self, name), integer=True)
        for name in ("tile", "gpu_batch"):
            if getattr(self, name) is not None:
                check_number(f"--{name.replace('_', '-')}", getattr(self, name), integer=True)
        for name in ("resume", "overwrite", "fast_gpu"):
            check_flag(f"--{name.replace('_', '-')}", getattr(self, name))
        if self.method not in METHODS:
            raise InputError(f"unknown method {self.method!r}: expected one of {', '.join(METHODS)}")
        if self.window <= 0 or self.window % 2 == 0:
            raise InputError(f"--window must be a positive odd number of frames, got {self.window}")
        if self.every <= 0:
            raise InputError(f"--every must be >= 1, got {self.every}")
        if self.gain is not None:  # inf would pass "> 0" and expose every pixel to NaN, 1e30 to full white
            check_gain("--gain", self.gain)
        if self.scale is not None:  # 0 must not mean "the default"
            check_number("--scale", self.scale, at_least=1, integer=True)
        if self.tile is not None and (self.tile <= 0 or self.tile % 8):
            raise InputError(f"--tile must be a positive multiple of 8 LR pixels, got {self.tile}")
        if self.resume and self.overwrite:
            raise InputError("--resume and --overwrite contradict each other: choose one")
        if self.segment_tasks < 1:
            raise InputError(f"--segment-tasks must be >= 1, got {self.segment_tasks}")
        if self.precision not in PRECISIONS:
            raise InputError(f"--precision must be {' or '.join(PRECISIONS)}, got {self.precision!r}")
        if self.precision != "fp32" and self.method not in NETWORKS:
            raise InputError(f"--precision {self.precision} is for the network (--method cscsr or cscsr-ensemble); "
                             f"{self.method} has no network to run in it")
        if self.backend not in BACKENDS:
            raise InputError(f"--backend must be {' or '.join(BACKENDS)}, got {self.backend!r}")
        if self.backend != "torch" and self.method not in NETWORKS:
            raise InputError(f"--backend {self.backend} is for the network (--method cscsr or cscsr-ensemble); "
                             f"{self.method} has no network to run on it")
        if self.weights is not None and self.method not in NETWORKS:  # a classic method has none: never recorded
            raise InputError(f"--weights is for the network (--method cscsr or cscsr-ensemble); {self.method} has "
                             f"no weights to load: leave --weights out")
        if self.gpu_batch is not None and self.gpu_batch < 1:
            raise InputError(f"--gpu-batch must be >= 1, got {self.gpu_batch}")
        if self.gpu_batch is not None and self.method not in NETWORKS:
            raise InputError(f"--gpu-batch is for the network (--method cscsr or cscsr-ensemble); {self.method} has "
                             f"no network passes to batch: leave --gpu-batch out")
        if self.fast_gpu and (self.method not in NETWORKS or self.backend != "torch"):
            raise InputError("--fast-gpu is for the network on torch (--method cscsr or cscsr-ensemble, --backend "
                             "torch)")
        parse_time("--start", self.start)  # their text here; against the recording in job_part
        parse_time("--stop", self.stop)
        parse_region(self.region)


class Part(NamedTuple):
    """The part of a recording a job reconstructs: spike frames ``[start, stop)``, LR pixels ``region`` (y0, y1,
    x0, x1), and its output frames: ``centres``, the whole recording's from index ``first`` on (so a part's
    frames are exactly the matching frames of a whole run)."""

    start: int
    stop: int
    region: tuple[int, int, int, int]
    first: int
    centres: list[int]


def job_part(options: ReconstructOptions, n_frames: int, fps: float, height: int, width: int, cfa: str) -> Part:
    """``--start``/``--stop``/``--region`` checked against a recording (``stages.reconstruction.ranges``; one line each, before
    anything is created): the output frames are those of the whole recording whose centre lies in [start,
    stop); a window near the range's edges reads the spikes it needs outside it. A range edge closer than
    W//2 to the recording's ends simply has no centre there (no window fits)."""
    every_centre = output_centres(n_frames, options.window, options.every)
    start, stop = time_range(options.start, options.stop, n_frames, fps, every_centre, options.window, options.every)
    first = first_at(every_centre, start, options.every)
    last = first_at(every_centre, stop, options.every)
    return Part(start, stop, region(options.region, height, width, cfa), first, every_centre[first:last])


@dataclass(frozen=True)
class Plan:
    """What every task shares: where to read and write, and how to reconstruct.

    Constant in size: a task's own centre and tile travel beside it, so task messages do not
    grow with the recording (the scheduler keeps recent messages).
    """

    spikes: str
    out: str
    method: str
    weights: str | None
    window: int
    every: int
    gain: float
    scale: int
    cfa: str
    reset: str
    tile: int  # LR tile side
    run: str  # unique per call: worker-side caches of opened stores never outlive their run
    precision: str | None = None  # the network's (None for classic methods)
    gpu_batch: int = GPU_BATCH  # most windows per network pass, where a reconstructor joins tiles (GPU)
    backend: str | None = None  # what runs the network (None for classic methods)
    fast_gpu: bool | None = None  # channels-last, cuDNN autotuning, torch.compile on GPU workers (None: classic)
    # what the output is made from (made_from): the same paths may hold another recording or other weights later
    source_identity: str | None = None  # the spike store's identity (pipeline.stores.spike_store.store_identity)
    source_shape: tuple[int, int, int] | None = None  # its (frames, height, width)
    weights_sha256: str | None = None  # the weights file's SHA-256 (None for classic methods)
    # the part of the recording (Part): spike frames [start, stop), LR region (y0, y1, x0, x1); None: all of it
    start: int | None = None
    stop: int | None = None
    region: tuple[int, int, int, int] | None = None
    # the LR pixels (y0, y1, x0, x1) taken as the frame's edges, where lazy windows were made of a selection of the
    # recording's pixels (a method's halo stops there); None: the recording's own frame (a job's halo reads beyond
    # its --region): the two give other pixels near the region's edges, so neither resumes the other's output
    edges: tuple[int, int, int, int] | None = None

    def attrs(self) -> dict:
        """What the output store records (and ``--resume`` checks)."""
        return {"method": self.method, "weights": self.weights, "precision": self.precision, "backend": self.backend,
                "fast_gpu": self.fast_gpu, "window": self.window,
                "every": self.every, "gain": self.gain, "scale": self.scale, "source": recorded(self.spikes), "cfa": self.cfa,
                "reset": self.reset, "tile_lr": self.tile, "source_identity": self.source_identity,
                "source_shape": None if self.source_shape is None else list(self.source_shape),
                "weights_sha256": self.weights_sha256, "start": self.start, "stop": self.stop,
                "region": None if self.region is None else list(self.region),
                "edges": None if self.edges is None else list(self.edges)}

    def whole(self) -> dict:
        """The part an output from before ``start``/``stop``/``region`` were recorded holds: all of its recording
        (what ``--resume`` takes them to be)."""
        frames, height, width = self.source_shape or (None, None, None)
        return {"start": 0, "stop": frames, "region": None if height is None else [0, height, 0, width]}

    def other_data(self, found: dict) -> str | None:
        """Why an output whose attributes are ``found`` was made from other data than this plan reads (another
        recording, or other weights, at the same path); None if the same. An output from before this record
        (the attribute absent) is not refused here: ``_prepare_output`` adopts the plan's record into it."""
        was, now = found.get("source_identity"), self.source_identity
        shape = found.get("source_shape")
        if (was is not None and was != now) or (shape is not None and list(shape) != list(self.source_shape or ())):
            return (f"its input {self.spikes} is not the recording it was made from (identity {_short(was)}, "
                    f"{_frames(shape)} -> identity {_short(now)}, {_frames(self.source_shape)}): "
                    f"give that recording, or start again with --overwrite")
        was = found.get("weights_sha256")  # weights from another path: a changed parameter, said as such
        if was is not None and was != self.weights_sha256 and found.get("weights") == self.weights:
            return (f"its weights {self.weights} are not the ones it was made with (sha256 {_short(was)} -> "
                    f"{_short(self.weights_sha256)}): give those weights, or start again with --overwrite")
        return None


MADE_FROM = ("source_identity", "source_shape", "weights_sha256")  # Plan.attrs() that name data, not parameters


def made_from(store, weights_sha256: str | None) -> dict:
    """The ``Plan`` fields that say what an output is made from: the identity and shape of ``store`` (an open
    ``SpikeStore``; a hash of its metadata if it predates identities) and the SHA-256 of the
    weights file the network was loaded from (``method.weights_sha256``; None for classic methods)."""
    from pipeline.stores.spike_store import store_identity

    return {"source_identity": store_identity(store), "source_shape": store.shape, "weights_sha256": weights_sha256}


def _short(digest: str | None) -> str:
    if digest is None:
        return "none"
    kind, _, value = digest.rpartition("-")
    return f"{kind}-{value[:12]}" if kind else value[:12]


def _frames(shape) -> str:
    return "unknown shape" if not shape else f"{shape[0]} frames of {shape[1]}x{shape[2]}"


def tile_blocks(grid: list[list[Tile]], per_task: int) -> list[tuple[tuple[int, int], ...]]:
    """The tiles (ty, tx) that go into one task together: ``per_task`` tiles of the same read shape
    (so that they can run as one batch), in the grid's order of their first tiles. One tile per
    task gives the grid in row-major order."""
    by_shape: dict[tuple[int, int], list[tuple[int, int]]] = {}
    for ty, row in enumerate(grid):
        for tx, tile in enumerate(row):
            by_shape.setdefault((tile.ry1 - tile.ry0, tile.rx1 - tile.rx0), []).append((ty, tx))
    blocks = [tuple(tiles[i : i + per_task]) for tiles in by_shape.values() for i in range(0, len(tiles), per_task)]
    return sorted(blocks)


class Placement(NamedTuple):
    """Where a job's network tasks run: on GPU workers or not, and the memory of the smallest GPU (None
    when not known: no GPU, or workers that advertise one without CUDA, as in the tests)."""

    gpus: bool
    memory: int | None
