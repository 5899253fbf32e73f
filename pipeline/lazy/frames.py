"""Scene frames as lazy xarray (``cscsr.lazy``, issue #56): :func:`open_frames`, what ``cscsr simulate`` reads.

A video file, a folder of pictures, a Zarr video (``cscsr reconstruct``'s output) or one picture, as the HR scene
frames ``(t, y, x, rgb)`` that :func:`pipeline.lazy.simulate.simulate` takes, read a block at a time when something
computes it: a source's own frames as the job's reader gives them (uint8; uint16 for a 16-bit grey picture; grey
frames with ``rgb`` of size 1, RGBA with 4), or the scene the ``simulate`` job makes of it (``pipeline.jobs.
simulate_plan``): a picture under ``--motion``, a video spread over ``--frames`` spike frames. So
``to_spikes(simulate(frames), url, truth=frames)`` is ``cscsr simulate`` with the same options: its tasks, its store.
"""

import weakref

import xarray as xr

from pipeline.jobs.simulate import frames_array
from pipeline.jobs.simulate_plan import (MAX_FRAMES, MAX_FRAMES_WHY, TRUTH_SCALES, CameraFrames, VideoFrames,
                                         check_path_options, open_scene)
from pipeline.lazy.spikes import check_here, place, python_words
from pipeline.stores.frame_sources import open_frame_source
from pipeline.stores.storage import recorded
from stages.errors import InputError
from stages.numbers import check_number, check_text
from stages.simulation.interpolate import INTERPOLATIONS

FRAME_DIMS = ("t", "y", "x", "rgb")
_SCENES: "weakref.WeakValueDictionary" = weakref.WeakValueDictionary()  # a graph's name -> its scene (made_scene),
# kept while a graph holds it


def open_frames(url, *, chunk_frames: int | None = None, frames: int | None = None, motion: str | None = None,
                seed: int = 0, speed: float | None = None, deform: float | None = None, interp: str = "flow",
                scale: int = 4) -> xr.DataArray:
    """The frames at ``url`` (a video, a folder of pictures, a Zarr video, a picture) as lazy scene frames
    ``(t, y, x, rgb)``, ``chunk_frames`` frames a block (default: about ``pipeline.jobs.simulate.BLOCK_BYTES``);
    attributes ``source`` (the place, as a store records it) and ``motion``. The first frame is read now (its dtype
    and colours are every frame's); a frame of another size, dtype or colours is refused, in one line naming it, when
    its block is read.

    A picture is a scene of ``frames`` frames under ``motion``, as ``cscsr simulate PICTURE --motion`` makes it:
    ``"static"``, the picture in every frame as stored; ``"random"``, the camera path of ``seed``, ``speed`` and
    ``deform`` (``stages.simulation.camera_path.CameraPath.random``: the job's own, of its ``--seed``), each frame
    rendered as float32 intensities in [0, 1]; the attributes ``seed`` and ``frames`` say which path, and
    ``simulate`` must be given that seed (the job's one ``--seed`` draws both). ``motion`` is for a picture alone.

    A video (a folder, a Zarr video) given ``frames`` is the scene ``cscsr simulate --frames --interp --scale`` makes
    of it: its frames spread evenly over ``frames`` spike frames and ``interp``-olated between (``"flow"``: each
    pair's motion estimated on the frames area-downsampled by ``scale``, as the job estimates it at LR; ``"linear"``),
    as float32 intensities in [0, 1]; ``simulate`` makes its LR spikes as the job does (LR frames interpolated at LR,
    ``stages.simulation.latent``) and must be given that ``scale``. Without ``frames``, a video's frames are the
    scene's, one per spike frame."""
    url = place(url)
    with python_words():
        for name, value in (("chunk_frames", chunk_frames), ("frames", frames)):
            if value is not None:
                check_number(name, value, at_least=1, at_most=MAX_FRAMES, integer=True, why=MAX_FRAMES_WHY)
        check_text("motion", motion, optional=True)
        check_text("interp", interp)
        check_number("seed", seed, at_least=0, integer=True)
        check_path_options(motion, speed, deform)
        if interp not in INTERPOLATIONS:
            raise InputError(f"unknown interpolation {interp!r}: expected one of {', '.join(INTERPOLATIONS)}")
        if scale not in TRUTH_SCALES:
            raise InputError(f"scale must be one of {', '.join(map(str, TRUTH_SCALES))}, got {scale!r}")
        check_here([url])  # a memory:// source is this process's alone
        scene = open_scene(open_frame_source(url), frames=frames, motion=motion, seed=seed, speed=speed,
                           deform=deform, interp=interp, scale=scale)
    data = frames_array(scene, chunk_frames)
    attrs = {"source": recorded(url), "motion": motion or "video"}
    if motion == "random":  # the path's: lazy.simulate records the job's options only for the job's scene
        attrs.update(seed=seed, frames=frames)
    if isinstance(scene, (CameraFrames, VideoFrames)):  # lazy.simulate and to_spikes make it as the job does
        _SCENES[data.name] = scene
        attrs["interp"] = interp  # recorded by lazy.simulate, as the job records its --interp
    if isinstance(scene, VideoFrames):
        attrs["scale"] = scale
    return xr.DataArray(data, dims=FRAME_DIMS, attrs=attrs)


def made_scene(data) -> "CameraFrames | VideoFrames | None":
    """The scene ``data`` are all the frames of, as :func:`open_frames` made it of a picture or of a video given
    ``frames`` (a selection, a function or a rechunk since makes a new array): ``lazy.simulate`` then makes its LR
    mosaics as the ``simulate`` job does (a video's at LR, a picture's without its HR frames held a block at a
    time), and ``to_spikes`` its truth (and a camera path's flow). Else None."""
    return _SCENES.get(getattr(data, "name", None))
