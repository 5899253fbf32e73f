"""cscsr: distributed super-resolution reconstruction for colour spike cameras (CSCSR, CVPR 2024).

This package holds the model side (network, baselines, weights, training) and the
bundled sample recordings; :mod:`stages` holds the pure array functions and
:mod:`pipeline` the storage, cluster and command-line side.

The main jobs are also functions (``docs/python.md``)::

    from cscsr import ingest, simulate, reconstruct, evaluate

They live in :mod:`pipeline.api` and are loaded on first use: ``import cscsr`` alone imports
neither the pipeline nor Dask. So is ``cscsr.lazy`` (:mod:`pipeline.lazy`), the stages as lazy Dask graphs on
xarray: ``from cscsr import lazy``.
"""

__version__ = "0.1.0"

API = ("ingest", "simulate", "reconstruct", "evaluate", "Written")
MODULES = {"lazy": "pipeline.lazy"}  # submodules of the pipeline offered here
__all__ = [*API, *MODULES, "__version__"]


def __getattr__(name: str):
    if name in API:
        from importlib import import_module

        value = getattr(import_module("pipeline.api"), name)
        globals()[name] = value  # the next look-up is an ordinary attribute
        return value
    if name in MODULES:
        from importlib import import_module

        globals()[name] = module = import_module(MODULES[name])
        return module
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *API, *MODULES})
