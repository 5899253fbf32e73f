"""``cscsr info``: what a spike store holds, as a flat summary."""

from pipeline.spike_store import open_spike_store
from pipeline.storage import size_of


def summarize(url: str) -> dict:
    """Shape, duration, CFA, firing rate, chunking and size at rest of a spike store."""
    store = open_spike_store(url, allow_incomplete=True)
    meta = store.meta
    pixels = store.n_frames * meta.height * meta.width
    stored = size_of(f"{str(url).rstrip('/')}/spikes")
    spikes = store.spike_count
    return {
        "store": str(url),
        "state": store.attrs.get("state"),
        "frames": store.n_frames,
        "height": meta.height,
        "width": meta.width,
        "duration_s": store.n_frames / meta.fps,
        "fps": meta.fps,
        "cfa": meta.cfa,
        "reset": meta.reset,
        "flipped": meta.flipped,
        "firing_rate": None if spikes is None else spikes / pixels,
        "chunks": list(store.spikes.chunks),
        "codec": " + ".join(type(c).__name__ for c in store.spikes.compressors) or "none",
        "size_on_disk_bytes": stored,
        "bits_per_pixel": 8 * stored / pixels,
        "source": meta.source,
        "format_version": store.attrs.get("format_version"),
    }
