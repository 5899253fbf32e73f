"""``cscsr ingest``: a raw capture streamed into a new spike store."""

from dataclasses import asdict, dataclass

from pipeline.captures import open_capture
from stages.prefetch import prefetched
from pipeline.progress import progress_bar
from pipeline.spike_store import SpikeMeta, SpikeStoreWriter, chunk_frames_for
from pipeline.lease import claimed
from pipeline.outputs import SPIKE_STORE, new_output
from pipeline.storage import check_apart, recorded
from stages.bits import count_spikes, packed_width
from stages.cfa import check_cfa, flip_vertically
from stages.numbers import check_flag, check_number, check_text
from stages.sensor import check_reset

BLOCK_BYTES = 64 * 2**20  # packed bytes per block read: bounds memory, amortises I/O


@dataclass(frozen=True)
class IngestOptions:
    height: int | None = None
    width: int | None = None
    cfa: str = "mono"
    fps: float = 20000.0
    flip: bool = False
    head_columns: int = 0
    key: str | None = None
    reset: str = "subtract"
    overwrite: bool = False

    def check(self) -> None:
        """Every check of the options that needs no capture, types first (only the Python API can get them
        wrong: ``flip="no"`` is a true string, ``height="16"`` no number). The capture and the store's
        metadata check the sizes and ``fps`` against the recording."""
        for name in ("height", "width"):
            if getattr(self, name) is not None:
                check_number(f"--{name}", getattr(self, name), integer=True)
        check_text("--cfa", self.cfa)
        check_number("--fps", self.fps, above=0)
        check_flag("--flip", self.flip)
        check_number("--head-columns", self.head_columns, integer=True)
        check_text("--key", self.key, optional=True)
        check_text("--reset", self.reset)
        check_flag("--overwrite", self.overwrite)
        check_cfa(self.cfa)
        check_reset(self.reset)


def capture_fields(options: IngestOptions) -> dict:
    """What the capture is taken to be (every field but ``overwrite``): the watcher keys its work on these."""
    fields = asdict(options)
    del fields["overwrite"]
    return fields


def ingest(src: str, dest: str, options: IngestOptions = IngestOptions(), *, progress: bool = True) -> dict:
    """Copy ``src`` into a spike store at ``dest``; return the store's final attributes.

    ``options.cfa`` is the pattern as recorded by the sensor; with ``flip`` the store
    records the pattern of the upright image it holds.
    """
    options.check()
    check_apart(dest, src)
    capture = open_capture(src, height=options.height, width=options.width, flip=options.flip,
                           head_columns=options.head_columns, key=options.key)
    sensor_cfa = check_cfa(options.cfa, capture.height, capture.width)
    meta = SpikeMeta(
        height=capture.height, width=capture.width,
        cfa=flip_vertically(sensor_cfa, capture.height) if options.flip else sensor_cfa,
        fps=options.fps, source=recorded(src), flipped=options.flip, head_columns=options.head_columns, reset=options.reset,
    )
    chunk = chunk_frames_for(meta, capture.n_frames)
    frames_per_block = chunk * max(1, BLOCK_BYTES // (chunk * capture.height * packed_width(capture.width)))
    with claimed(dest), new_output(dest, overwrite=options.overwrite, kind=SPIKE_STORE):
        writer = SpikeStoreWriter(dest, meta, capture.n_frames, chunk_frames=chunk)
        spikes = 0
        with progress_bar(f"ingest {src}", capture.n_frames, enabled=progress) as advance:
            for start, packed in prefetched(capture.blocks(frames_per_block)):
                writer.write(start, packed)
                spikes += count_spikes(packed)
                advance(packed.shape[0])
        writer.finish(spike_count=spikes)
    return dict(writer.group.attrs)
