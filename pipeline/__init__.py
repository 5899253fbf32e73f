"""Everything that touches storage and the cluster: stores, captures, CLI.

The pipeline moves blocks between storage and :mod:`stages`; it never computes on pixels.
"""

from stages.moved import keep_importable  # noqa: E402

keep_importable("pipeline", {  # the old paths of the modules now in rooms (docs/layout.md): still importable
    "cluster": "compute.cluster", "executor": "compute.executor", "estimate": "compute.estimate",
    "progress": "compute.progress", "hold": "compute.hold", "stopping": "compute.stopping",
    "storage": "stores.storage", "outputs": "stores.outputs", "lease": "stores.lease",
    "spike_store": "stores.spike_store", "video_store": "stores.video_store", "ground_truth": "stores.ground_truth",
    "captures": "stores.captures", "frame_sources": "stores.frame_sources", "images": "stores.images",
    "ingest": "jobs.ingest", "simulate": "jobs.simulate", "simulate_plan": "jobs.simulate_plan",
    "reconstruct": "jobs.reconstruct", "reconstruct_plan": "jobs.reconstruct_plan", "evaluate": "jobs.evaluate",
    "testset": "jobs.testset", "export": "jobs.export", "info": "jobs.info", "preview": "jobs.preview",
    "lazy_spikes": "lazy.spikes", "lazy_simulate": "lazy.simulate", "lazy_video": "lazy.video",
    "watch": "inbox.watch", "ledger": "inbox.ledger",
})
