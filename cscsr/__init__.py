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

from cscsr.version import __version__

from stages.moved import keep_importable  # noqa: E402

keep_importable("cscsr", {  # the old paths of the modules now in rooms (docs/layout.md): still importable
    "blocks": "network.blocks", "bssr": "network.bssr", "temporal_pixels": "network.temporal_pixels",
    "spike_flow": "network.spike_flow", "motion_estimation": "network.motion_estimation", "warp": "network.warp",
    "base_image": "network.base_image", "bayer": "network.bayer", "integration": "network.integration",
    "config": "network.config", "weights_io": "weights.weights_io",
    "portable_checkpoint": "weights.portable_checkpoint", "model_info": "weights.model_info",
    "reconstructor": "inference.reconstructor", "device_steps": "inference.device_steps",
    "device_memory": "inference.device_memory", "onnx_runtime": "inference.onnx_runtime", "train": "training.train",
    "training_batches": "training.training_batches", "training_losses": "training.training_losses",
    "training_options": "training.training_options", "training_state": "training.training_state",
    "training_data": "training.training_data", "synthesis": "training.synthesis",
    "frame_motion": "training.frame_motion",
})

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
