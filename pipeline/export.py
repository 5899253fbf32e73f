"""``cscsr export``: a spike store streamed back out to a raw ``.dat`` capture.

The ``.dat`` file gets the geometry the capture came with: flipped back if ingest flipped
it, and with zero-filled header columns where ingest dropped some, so that a capture
ingested and exported again is byte-identical to the original (header columns aside).
"""

from pipeline.progress import progress_bar
from pipeline.spike_store import open_spike_store
from pipeline.storage import claim_output, new_output, resolve
from stages.dat import DatLayout, packed_to_dat
from stages.errors import InputError

FRAMES_PER_READ_BYTES = 64 * 2**20


def export(store_url: str, dest: str, *, overwrite: bool = False, progress: bool = True) -> None:
    """Write the store at ``store_url`` to ``dest``, chosen by the destination's extension."""
    if not str(dest).lower().endswith(".dat"):
        raise InputError(f"cannot export a spike store to {dest}: expected a .dat destination")
    export_dat(store_url, dest, overwrite=overwrite, progress=progress)


def export_dat(store_url: str, dest: str, *, overwrite: bool = False, progress: bool = True) -> None:
    store = open_spike_store(store_url)
    meta = store.meta
    layout = DatLayout(meta.height, meta.width, head_columns=meta.head_columns, flip=meta.flipped)
    chunk = store.spikes.chunks[0]
    frames_per_read = chunk * max(1, FRAMES_PER_READ_BYTES // (chunk * layout.frame_bytes))
    claim_output(dest, overwrite=overwrite)
    partial = f"{dest}.partial"
    fs, path = resolve(partial)
    with new_output(partial, overwrite=True):
        with fs.open(path, "wb") as out, progress_bar(f"export {dest}", store.n_frames, enabled=progress) as advance:
            for start in range(0, store.n_frames, frames_per_read):
                packed = store.read(start, min(start + frames_per_read, store.n_frames))
                out.write(packed_to_dat(packed, layout).tobytes())
                advance(packed.shape[0])
        fs.mv(path, resolve(dest)[1])
