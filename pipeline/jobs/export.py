"""``cscsr export``: a spike store to a raw ``.dat``; an HR video store to ``.mp4`` or PNGs.

The ``.dat`` file gets the geometry the capture came with: flipped back if ingest flipped
it, and with zero-filled header columns where ingest dropped some, so that a capture
ingested and exported again is byte-identical to the original (header columns aside).
A video goes out frame by frame (H.264 through imageio-ffmpeg, or one PNG per frame named
by its centre spike frame), so memory stays at one frame.
"""

import logging
import os
import tempfile

from pipeline.stores.lease import claimed
from pipeline.compute.progress import progress_bar
from pipeline.compute.stopping import interrupts_deferred
from pipeline.stores.spike_store import open_spike_store
from pipeline.stores.outputs import FRAME_FOLDER, new_output
from pipeline.stores.storage import check_apart, open_group, resolve, source_of
from pipeline.stores.video_store import FRAMES, VIDEO, lost_frames, open_video_store
from stages.capture.dat import DatLayout, packed_to_dat
from stages.errors import InputError
from stages.measures.montage import padded_to

FRAMES_PER_READ_BYTES = 64 * 2**20


VIDEO_FPS = 10
MP4_BLOCK = 2  # yuv420p (what players expect of H.264) halves the chroma: both sides must be even
log = logging.getLogger("cscsr.export")  # the package is ``pipeline``; the logger is named for the command


def export(store_url: str, dest: str, *, overwrite: bool = False, progress: bool = True) -> None:
    """Write the store at ``store_url`` to ``dest``: the kind of store and ``dest``'s extension decide how."""
    check_apart(dest, store_url, source_of(store_url))  # nor what the store was made from, before the claim
    is_video = VIDEO in open_group(store_url)
    suffix = str(dest).lower().rsplit(".", 1)[-1] if "." in str(dest).rsplit("/", 1)[-1] else ""
    if is_video:
        if suffix not in ("mp4", ""):
            raise InputError(f"cannot export a video store to {dest}: expected a .mp4 file or a folder")
        write = export_mp4 if suffix == "mp4" else export_pngs
    elif suffix == "dat":
        write = export_dat
    else:
        raise InputError(f"cannot export a spike store to {dest}: expected a .dat destination")
    with claimed(dest):  # one job per output, taken atomically before the output is touched
        write(store_url, dest, overwrite=overwrite, progress=progress)


def _complete_video(store_url: str):
    group = open_video_store(store_url)
    if group.attrs.get("state") != "complete":
        raise InputError(f"video store {store_url} is incomplete: finish it with cscsr reconstruct --resume")
    if lost := lost_frames(group):  # read back, they would be black frames in a video that looks whole
        raise InputError(f"video store {store_url} is damaged: {lost} missing (lost data); nothing exported: "
                         f"make it again with cscsr reconstruct --overwrite")
    return group


LEVEL_52_MACROBLOCKS = 36864  # H.264 level 5.2's largest frame (4096x2304): where many hardware decoders stop


def beyond_common_players(height: int, width: int) -> str | None:
    """What to say of an H.264 video of ``height`` x ``width`` frames that only level 6 holds (a 4000x4000 HR
    frame: a 1000x1000 sensor at x4), which many hardware players, phones and browsers do not decode; else None."""
    macroblocks = -(-height // 16) * -(-width // 16)
    if macroblocks <= LEVEL_52_MACROBLOCKS:
        return None
    return (f"frames of {height}x{width} make an H.264 level 6 video (over level 5.2's 2304x4096): ffmpeg and "
            f"software players play it, many hardware players and browsers do not; export PNG frames (a FOLDER/) "
            f"or reconstruct a --region for them")


def export_mp4(store_url: str, dest: str, *, overwrite: bool = False, progress: bool = True) -> None:
    """H.264 at 10 frames per second (libx264, yuv420p), written locally then moved to ``dest``. Frames keep their
    size; yuv420p needs even sides, so an odd side grows by one repeated row or column, said in one log line
    (never resampled: imageio's default would stretch every frame to multiples of 16, with a warning of its own)."""
    import imageio.v2 as iio2

    check_apart(dest, store_url, source_of(store_url))  # nor what the store was made from
    group = _complete_video(store_url)
    video = group[VIDEO]
    height, width = video.shape[1:3]
    if odd := [name for name, side in (("row", height), ("column", width)) if side % MP4_BLOCK]:
        log.warning("%s: frames are %dx%d and H.264 (yuv420p) needs even sides: the video is %dx%d, its last %s "
                    "repeated", dest, width, height, width + -width % MP4_BLOCK, height + -height % MP4_BLOCK,
                    " and last ".join(odd))
    if note := beyond_common_players(height, width):
        log.warning("%s: %s", dest, note)
    fs, path = resolve(dest)
    # the old video (only an MP4: .mp4 is the kind written here) is kept until the new one is in place
    with new_output(dest, overwrite=overwrite, kind=".mp4"), tempfile.TemporaryDirectory() as scratch:
        local = os.path.join(scratch, "video.mp4")  # ffmpeg writes files, not streams
        with iio2.get_writer(local, format="FFMPEG", mode="I", fps=VIDEO_FPS, codec="libx264", quality=8,
                             pixelformat="yuv420p", macro_block_size=MP4_BLOCK, ffmpeg_log_level="error") as writer, \
                progress_bar(f"export {dest}", video.shape[0], enabled=progress) as advance:
            for index in range(video.shape[0]):
                frame = padded_to(video[index], MP4_BLOCK)  # sides already even: imageio resizes nothing
                with interrupts_deferred():  # never half a frame in ffmpeg's pipe
                    writer.append_data(frame)
                advance(1)
        fs.put_file(local, path)


def export_pngs(store_url: str, dest: str, *, overwrite: bool = False, progress: bool = True) -> None:
    """One PNG per output frame, ``frame_<centre spike frame>.png``."""
    from pipeline.stores.images import write_image

    check_apart(dest, store_url, source_of(store_url))  # nor what the store was made from
    group = _complete_video(store_url)
    video, frames = group[VIDEO], group[FRAMES][:]
    # replaces only a folder of our frames (frame_<centre>.png and nothing else), kept until the new one is written
    with new_output(dest, overwrite=overwrite, kind=FRAME_FOLDER), \
            progress_bar(f"export {dest}", video.shape[0], enabled=progress) as advance:
        for index, centre in enumerate(frames):
            write_image(f"{str(dest).rstrip('/')}/frame_{centre:08d}.png", video[index], overwrite=False)
            advance(1)


def export_dat(store_url: str, dest: str, *, overwrite: bool = False, progress: bool = True) -> None:
    source = source_of(store_url)  # nor what the store was made from
    check_apart(dest, store_url, source)
    check_apart(f"{dest}.partial", store_url, source)
    store = open_spike_store(store_url)
    meta = store.meta
    layout = DatLayout(meta.height, meta.width, head_columns=meta.head_columns, flip=meta.flipped, head_at=meta.head_at)
    chunk = store.spikes.chunks[0]
    frames_per_read = chunk * max(1, FRAMES_PER_READ_BYTES // (chunk * layout.frame_bytes))
    partial = f"{dest}.partial"  # a .dat cannot say it is complete: written aside, renamed when it is
    fs, path = resolve(partial)
    with new_output(dest, overwrite=overwrite, kind=".dat"), new_output(partial, overwrite=True, kind=".dat"):
        with fs.open(path, "wb") as out, progress_bar(f"export {dest}", store.n_frames, enabled=progress) as advance:
            for start in range(0, store.n_frames, frames_per_read):
                packed = store.read(start, min(start + frames_per_read, store.n_frames))
                out.write(packed_to_dat(packed, layout).tobytes())
                advance(packed.shape[0])
        fs.mv(path, resolve(dest)[1])
