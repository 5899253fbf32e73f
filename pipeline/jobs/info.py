"""``cscsr info``: what a spike store or an HR video store holds, as a flat summary."""

import contextlib

from pipeline.stores.spike_store import open_spike_store
from pipeline.stores.storage import list_chunks, open_group, size_of
from pipeline.stores.video_store import COMMITTED, FRAMES, VIDEO, check_video_store, is_video_store, lost_frames
from stages.errors import InputError

SHOWN = 4  # missing frame ranges named in full


def summarize(url: str) -> dict:
    """A spike store's or a video store's summary (``kind`` says which)."""
    group = open_group(url, "spike store")
    return summarize_video(url, group) if is_video_store(group) else summarize_spikes(url)


def summarize_spikes(url: str) -> dict:
    """Shape, duration, CFA, firing rate, chunking and size at rest of a spike store; a store whose
    chunks are not all there is never called complete, and the missing frames are named."""
    store = open_spike_store(url, allow_incomplete=True)
    meta = store.meta
    pixels = store.n_frames * meta.height * meta.width
    if not pixels:  # no writer of ours makes one (ingest and simulate refuse an empty recording)
        raise InputError(f"{url} is a spike store of {store.n_frames} frames of {meta.height}x{meta.width} pixels: "
                         f"it holds no spikes to describe (make it again from its capture)")
    stored = size_of(f"{str(url).rstrip('/')}/spikes")
    spikes = store.spike_count
    lost = missing_frames(store.spikes)
    state = store.attrs.get("state")
    if lost and state == "complete":  # its writer finished: what is missing now is lost
        state = f"damaged: {lost} missing (lost data)"
    return {
        "kind": "spike store",
        "store": str(url),
        "state": state,
        "frames": store.n_frames,
        "height": meta.height,
        "width": meta.width,
        "duration_s": store.n_frames / meta.fps,
        "fps": meta.fps,
        "cfa": meta.cfa,
        "reset": meta.reset,
        "flipped": meta.flipped,
        "firing_rate": None if spikes is None or lost else spikes / pixels,  # counted over chunks not all there
        "missing_chunks": lost,
        "chunks": list(store.spikes.chunks),
        "codec": " + ".join(type(c).__name__ for c in store.spikes.compressors) or "none",
        "size_on_disk_bytes": stored,
        "bits_per_pixel": 8 * stored / pixels,
        "source": meta.source,
        "identity": store.attrs.get("identity"),  # what outputs made from it record (None: a store from before)
        "format_version": store.attrs.get("format_version"),
    }


def missing_frames(spikes) -> str | None:
    """``N of M chunks (frames a..b, ...)`` for the chunks of a spike array that are not in its store: counted from
    what is stored, only the first :data:`SHOWN` named."""
    listing = list_chunks(spikes)
    if not listing.missing:
        return None
    step, n = spikes.chunks[0], spikes.shape[0]
    ranges = [f"{t * step}..{min((t + 1) * step, n) - 1}" for t, *_ in listing.first_missing(SHOWN)]
    more = listing.missing - len(ranges)
    return f"{listing.missing} of {listing.total} chunks of spikes (frames {', '.join(ranges)}" + \
        (f", and {more} more)" if more else ")")


def summarize_video(url: str, group) -> dict:
    """Frames, size, frame rate, method, state and the part of its recording (spike frames ``start``..``stop``,
    LR ``region``) of an HR video store; a store whose written tiles are not all there is never called complete,
    and the frames they belong to are named."""
    check_video_store(url, group)  # a format_version it does not know, arrays that disagree: refused by name
    attrs = dict(group.attrs)
    video, frames = group[VIDEO], group[FRAMES]
    n, height, width = video.shape[:3]
    fps = attrs.get("fps")  # recorded since format_version 1; before, from the source, which may be gone
    with contextlib.suppress(InputError, KeyError, TypeError, ZeroDivisionError):
        fps = fps or float(open_group(attrs["source"]).attrs["fps"]) / int(attrs["every"])
    committed = group[COMMITTED] if COMMITTED in group else None  # one chunk per task, written when it commits
    done = None if committed is None else len(list_chunks(committed).stored)
    lost = lost_frames(group)  # written (committed, or the store complete) and gone: they would read as black
    state = attrs.get("state")
    if lost:  # an unfinished store says so too: --resume never redoes a tile recorded committed
        state = f"damaged: {lost} missing (lost data)" + ("" if state == "complete" else f"; state {state}")
    return {
        "kind": "video store",
        "store": str(url),
        "state": state,
        "frames": n,
        "height": height,
        "width": width,
        "fps": fps,
        "duration_s": None if fps is None else n / fps,
        "spike_frames": f"{frames[0]}..{frames[n - 1]}" if n else "",  # two reads, whatever the length
        # the part of the recording it holds (reconstruct --start/--stop/--region); None: a store from before them
        "start": attrs.get("start"),
        "stop": attrs.get("stop"),
        "region": attrs.get("region"),  # [y0, y1, x0, x1] in LR pixels
        "method": attrs.get("method"),
        "weights": attrs.get("weights"),
        "scale": attrs.get("scale"),
        "window": attrs.get("window"),
        "every": attrs.get("every"),
        "gain": attrs.get("gain"),
        "tiles_committed": None if committed is None else f"{done} of {committed.size}",
        "missing_chunks": lost,
        "chunks": list(video.chunks),
        "size_on_disk_bytes": size_of(f"{str(url).rstrip('/')}/{VIDEO}"),
        "source": attrs.get("source"),
        "source_identity": attrs.get("source_identity"),  # the spike store's it was made from (--resume checks it)
    }
