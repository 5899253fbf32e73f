"""``cscsr.lazy``: the pipeline's stages as lazy Dask graphs on xarray, for Dask and xarray users.

Every function takes and gives dask-backed :class:`xarray.DataArray` s and computes nothing; only ``to_video``
and ``to_spikes`` compute (on the active ``distributed`` client if there is one, else on dask's default
scheduler)::

    from cscsr import lazy

    spikes = lazy.open_spikes("rec.zarr")                 # (t, y, x) bool, one dask chunk per stored chunk
    win = lazy.windows(spikes, every=20)                  # (t, dt, y, x): 41-frame windows, dask's overlap
    hr = lazy.reconstruct(win, method="cscsr")            # (t, y, x, rgb) uint8, tiles and halos inside
    hr = hr.copy(data=hr.data.map_blocks(my_filter))      # anything a Dask user does, between stages
    lazy.to_video(hr, "hr.zarr")                          # a video store, as cscsr reconstruct writes it

A selection (``isel``/``sel``) of spikes, windows or ``hr`` is honoured exactly, in the recording's frames and
pixels, or refused in one line before anything is written (``docs/python.md``, "Selections");
``open_video(url)`` reads a written store back as the ``hr`` that wrote it.

The same arithmetic, reconstructors and store writers as the jobs: ``to_video(reconstruct(windows(...)))`` writes
the bytes ``cscsr reconstruct`` writes with the same options. Spikes: :mod:`pipeline.lazy.spikes` (reading stores),
:mod:`pipeline.lazy.capture` (reading raw captures, as ``cscsr ingest`` reads them) and :mod:`pipeline.lazy.simulate`
(simulating, writing; the scene frames it takes, as ``cscsr simulate`` reads them: :mod:`pipeline.lazy.frames`);
windows: :mod:`pipeline.lazy.windows`; reconstructions:
:mod:`pipeline.lazy.video`; video stores written and read back: :mod:`pipeline.lazy.written`.
Guide: ``docs/python.md``.
"""

from pipeline.lazy.capture import open_capture
from pipeline.lazy.frames import open_frames
from pipeline.lazy.simulate import SpikesIncomplete, simulate, to_spikes
from pipeline.lazy.spikes import open_spikes
from pipeline.lazy.video import apply, reconstruct, tfi, tfp
from pipeline.lazy.windows import windows
from pipeline.lazy.written import open_video, to_video

__all__ = ["open_spikes", "open_capture", "open_frames", "windows", "tfp", "tfi", "reconstruct", "apply", "simulate",
           "to_video", "to_spikes", "open_video", "SpikesIncomplete"]
