"""The Python API: the main jobs as functions, importable as ``from cscsr import ingest, simulate, reconstruct,
evaluate`` (``cscsr`` loads this module only when one of them is first used).

Every function takes its inputs and output as paths or URLs (``file://``, ``s3://``, ``memory://``, ...), the
command's options as keyword arguments (the fields of :class:`~pipeline.jobs.ingest.IngestOptions`,
:class:`~pipeline.jobs.simulate.SimulateOptions`, :class:`~pipeline.jobs.reconstruct.ReconstructOptions`), and an
optional connected :class:`distributed.Client`. It returns a :class:`Written`: what it wrote and what it found.

Where the work runs, for the jobs on Dask (``simulate``, ``reconstruct``, ``evaluate``):

1. ``client=``: that client's cluster;
2. else ``scheduler=ADDRESS``, else ``DASK_SCHEDULER_ADDRESS``, else ``scheduler-address`` in Dask's
   configuration (a file in ``~/.config/dask/``, ``DASK_CONFIG``, or ``dask.config.set``): that scheduler;
3. else a local cluster of ``workers=`` processes (default one per core), started and stopped by the call.

``ingest`` runs there too by 1 and 2 (``DASK_SCHEDULER_ADDRESS`` included), but on a local cluster only when
given ``workers=``: otherwise it reads the capture as one stream in bounded memory in the calling process
(the same bytes). Bad input raises :class:`stages.errors.InputError` (a ``ValueError``) before any output
exists, with the same one-line message the command prints. A wrong type (``out=None``, ``every="5"``,
``flip="no"``, ``client="..."``) raises :class:`stages.errors.InputTypeError`, a ``TypeError`` (and an
``InputError``) naming the argument; a closed client, an ``InputError``. Paths may be ``str`` or
``os.PathLike``.
"""

import dataclasses
import os
from collections.abc import Iterable
from dataclasses import dataclass, field

from stages.errors import InputError, InputTypeError
from stages.numbers import check_flag, check_text


@dataclass(frozen=True)
class Written:
    """What a job wrote.

    ``url``: the store (or, for ``evaluate``, the folder) written. ``attrs``: the store's attributes as
    written (shape, CFA, gain, ``spike_count``, ... of a spike store; ``method``, ``every``, ``state`` ... of
    a video store). ``counts``: what the job did (``reconstruct``: ``frames``, ``tasks_run``,
    ``tasks_skipped``; ``ingest``/``simulate``: ``frames``, ``spikes``). ``rows``: ``evaluate``'s summary,
    one dict per method (``method``, ``psnr``, ``ssim``, ``frames``, ``seconds_per_image``).
    """

    url: str
    attrs: dict = field(default_factory=dict)
    counts: dict = field(default_factory=dict)
    rows: tuple = ()


def _options(kind, job, given: dict):
    """``kind(**given)``, checked (its ``check()``: the command's own checks), with an unknown option named in
    one line with every keyword ``job`` (the API function) takes, its own and the options; a path given as
    ``os.PathLike`` (``weights=Path(...)``) as a string."""
    import inspect

    names = [f.name for f in dataclasses.fields(kind)]
    if unknown := [name for name in given if name not in names]:
        own = [name for name, parameter in inspect.signature(job).parameters.items()
               if parameter.kind is inspect.Parameter.KEYWORD_ONLY]
        raise TypeError(f"{job.__name__}() got an unknown option {unknown[0]!r}: expected some of "
                        f"{', '.join(own + names)}")
    options = kind(**{name: _plain(value) for name, value in given.items()})
    options.check()
    return options


def _plain(value):
    """An option as the command line would give it: a path (``os.PathLike``) as a string, a numpy number
    (``np.int64(41)``, what arithmetic on arrays gives) as Python's, within tuples and lists too (it passed the
    checks and then failed to be recorded: "Object of type int64 is not JSON serializable")."""
    import numpy as np

    if isinstance(value, os.PathLike):
        return os.fspath(value)
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, (tuple, list)):
        return type(value)(_plain(item) for item in value)
    return value


def _path(job: str, name: str, value) -> str:
    """A path or URL argument as a string: ``None`` (which would write to ``./None``), a number or bytes are
    refused by name."""
    text = os.fspath(value) if isinstance(value, os.PathLike) else value
    if not isinstance(text, str):
        raise InputTypeError(f"{job}(): {name} must be a path or URL (str or os.PathLike), got {value!r}")
    if not text.strip():
        raise InputError(f"{job}(): {name} is empty: give a path or URL")
    return text


def _checked(job: str, *, client=None, workers=None, scheduler=None, progress=False) -> None:
    """The arguments every job takes, checked before anything is read or written: ``client`` a running
    :class:`distributed.Client` (or None), ``workers`` as ``--workers``, ``scheduler`` an address (or None),
    ``progress`` True or False."""
    from pipeline.compute.cluster import check_workers

    if client is not None:
        from distributed import Client

        if not isinstance(client, Client):
            raise InputTypeError(f"{job}(): client must be a distributed.Client (or None), got {client!r}")
        if client.status != "running":
            raise InputError(f"{job}(): client is {client.status}, not running: pass a connected Client, "
                             "or leave client out")
    check_text("scheduler", scheduler, optional=True)
    if scheduler is not None and not scheduler.strip():
        raise InputError(f"{job}(): scheduler is empty: give an address (tcp://HOST:8786), or leave it out")
    if client is not None and (workers is not None or scheduler is not None):
        given = f"workers={workers!r}" if workers is not None else f"scheduler={scheduler!r}"
        raise InputError(f"{job}(): client= and {given} contradict each other: the job runs on the client's "
                         f"cluster: give one")
    check_workers(workers, scheduler)
    check_flag("progress", progress)


def _spike_counts(url: str) -> dict:
    from pipeline.stores.spike_store import open_spike_store

    store = open_spike_store(url)
    return {"frames": store.n_frames, "spikes": int(store.attrs.get("spike_count", 0))}


def _address_of(client) -> str:
    """The address other clients reach ``client``'s scheduler at (``simulate`` connects its own client)."""
    address = client.scheduler.address
    if address.startswith("inproc://"):
        raise InputError(f"simulate needs a cluster it can reach by address; {address} is in this process only "
                         "(start the LocalCluster with processes=True)")
    return address


def ingest(src: str, store: str, *, client=None, workers: int | None = None, scheduler: str | None = None,
           progress: bool = False, dry_run: bool = False, **options) -> Written:
    """A raw capture (``.dat``, ``.npy``, ``.npz``) into a new spike store at ``store``.

    ``options``: ``height``, ``width`` (required for ``.dat``), ``cfa`` (``"mono"``), ``fps``, ``flip``,
    ``head_columns``, ``key``, ``reset``, ``overwrite``, ``resume``, ``task_frames``, ``layout`` (``"sps100"``:
    the megapixel camera's raw packets) as in ``cscsr ingest``.
    With ``client``, ``workers`` or ``scheduler`` it runs in parallel on Dask (``.dat`` and ``.npy``), as
    ``cscsr ingest --workers/--scheduler``; without any, in this process, one stream (the same bytes).
    ``dry_run=True`` writes nothing: ``counts`` then holds the plan (as ``cscsr ingest --dry-run --json``).
    """
    from pipeline.jobs.ingest import IngestOptions, plan_ingest, run_ingest

    src, store = _path("ingest", "src", src), _path("ingest", "store", store)
    _checked("ingest", client=client, workers=workers, scheduler=scheduler, progress=progress)
    check_flag("dry_run", dry_run)
    checked = _options(IngestOptions, ingest, options)
    if dry_run:
        return Written(str(store), {}, plan_ingest(src, store, checked, workers=workers, scheduler=scheduler,
                                                   client=client))
    done = run_ingest(src, store, checked, progress=progress, workers=workers, scheduler=scheduler, client=client)
    return Written(str(store), dict(done["attrs"]), _spike_counts(store))


def simulate(src: str, store: str, *, client=None, workers: int | None = None, scheduler: str | None = None,
             progress: bool = False, **options) -> Written:
    """An LR Bayer spike recording with HR ground truth, simulated from ``src`` (a video, a folder of frames,
    a Zarr video or one image) into a new spike store at ``store``, on Dask.

    ``options``: the fields of ``SimulateOptions`` (``scale``, ``cfa``, ``brightness``, ``threshold``,
    ``frames``, ``motion``, ``seed``, ``noise``, ``reset``, ``interp``, ``truth_every``, ``speed``,
    ``deform``, ``fps``, ``chunk_frames``, ``overwrite``) as in ``cscsr simulate``.
    """
    from pipeline.jobs.simulate import SimulateOptions, simulate as run

    src, store = _path("simulate", "src", src), _path("simulate", "store", store)
    _checked("simulate", client=client, workers=workers, scheduler=scheduler, progress=progress)
    checked = _options(SimulateOptions, simulate, options)
    attrs = run(src, store, checked, workers=workers, progress=progress,
                scheduler=_address_of(client) if client is not None else scheduler)
    return Written(str(store), dict(attrs), _spike_counts(store))


def reconstruct(store: str, out: str, *, client=None, workers: int | None = None, scheduler: str | None = None,
                progress: bool = False, dry_run: bool = False, **options) -> Written:
    """HR colour video from the spike store at ``store`` into a new video store at ``out``, on Dask.

    ``options``: the fields of ``ReconstructOptions`` (``method`` ``"tfp"``/``"tfi"``/``"cscsr"``/
    ``"cscsr-ensemble"``, ``weights``, ``every``, ``window``, ``gain``, ``scale``, ``tile``, ``precision``,
    ``backend``, ``gpu_batch``, ``fast_gpu``, ``segment_tasks``, ``resume``, ``overwrite``, and the part of the
    recording: ``start``, ``stop`` (spike frames, or text such as ``"2.5s"``), ``region`` (``"Y0:Y1,X0:X1"`` or
    ``(y0, y1, x0, x1)`` in LR pixels)) as in ``cscsr reconstruct``. ``dry_run``: every check, nothing created;
    ``counts`` holds the plan that ``cscsr reconstruct --dry-run --json`` prints (``attrs`` is empty).
    """
    from pipeline.jobs.reconstruct import ReconstructOptions, reconstruct as run
    from pipeline.stores.video_store import open_video_store

    store, out = _path("reconstruct", "store", store), _path("reconstruct", "out", out)
    _checked("reconstruct", client=client, workers=workers, scheduler=scheduler, progress=progress)
    check_flag("dry_run", dry_run)
    counts = run(store, out, _options(ReconstructOptions, reconstruct, options), workers=workers,
                 scheduler=scheduler, client=client, progress=progress, dry_run=dry_run)
    if dry_run:
        return Written(str(out), {}, dict(counts))
    return Written(str(out), dict(open_video_store(out).attrs), dict(counts))


def evaluate(store: str, methods: str | Iterable[str] = ("tfp", "tfi"), out: str = "evaluation", *,
             weights: str | None = None, client=None, workers: int | None = None, scheduler: str | None = None,
             progress: bool = False, overwrite: bool = False, videos: dict | None = None, **unknown) -> Written:
    """PSNR / SSIM of ``methods`` (a list, or ``"tfp,tfi"``) against a simulated store's truth, as ``cscsr
    evaluate``: the reconstructions, ``metrics.csv``, ``summary.csv`` and ``comparison.png`` in the folder
    ``out`` (an existing one is refused unless ``overwrite``, and replaced only if it is an evaluation);
    ``rows`` holds the summary, one dict per method, then one per written video of ``videos`` ({name: URL}, as
    ``--video NAME=URL``: your own method's output, scored alike)."""
    from pipeline.jobs.evaluate import evaluate as run

    if unknown:  # as the other jobs name theirs
        known = "weights, client, workers, scheduler, progress, overwrite, videos"
        raise TypeError(f"evaluate() got an unknown option {next(iter(unknown))!r}: expected some of {known}")
    store, out = _path("evaluate", "store", store), _path("evaluate", "out", out)
    weights = None if weights is None else _path("evaluate", "weights", weights)
    _checked("evaluate", client=client, workers=workers, scheduler=scheduler, progress=progress)
    check_flag("--overwrite", overwrite)
    listed = (methods.split(",") if isinstance(methods, str) else
              list(methods) if isinstance(methods, Iterable) else None)
    if listed is None or not all(isinstance(m, str) for m in listed):
        raise InputTypeError(f"evaluate(): methods must be a string (\"tfp,tfi\") or a list of strings, "
                             f"got {methods!r}")
    names = [m.strip() for m in listed if m.strip()]
    if videos is not None:
        if not isinstance(videos, dict):
            raise InputTypeError(f"evaluate(): videos must be a dict of names to video store URLs, got {videos!r}")
        videos = {name: _path("evaluate", f"videos[{name!r}]", url) for name, url in videos.items()}
    rows = run(store, names, out, weights=weights, workers=workers, scheduler=scheduler, client=client,
               progress=progress, overwrite=overwrite, videos=videos)
    return Written(str(out), {}, {"methods": len(rows) - len(videos or {}), "videos": len(videos or {})}, tuple(rows))
