"""Pure, composable array functions: decode, pack, represent, reconstruct.

A stage takes numpy arrays and returns numpy arrays. It never opens a file, never sees a
URL and never knows about Dask; :mod:`pipeline` does all of that around it.
"""

from stages.moved import keep_importable  # noqa: E402

keep_importable("stages", {  # the old paths of the modules now in rooms (docs/layout.md): still importable
    "bits": "capture.bits", "dat": "capture.dat", "sps100": "capture.sps100", "spike_arrays": "capture.spike_arrays",
    "methods": "reconstruction.methods", "tfp": "reconstruction.tfp", "tfi": "reconstruction.tfi",
    "colour": "reconstruction.colour", "cfa": "reconstruction.cfa", "tiles": "reconstruction.tiles",
    "ranges": "reconstruction.ranges", "sensor": "simulation.sensor", "intensities": "simulation.intensities",
    "camera_path": "simulation.camera_path", "interpolate": "simulation.interpolate", "latent": "simulation.latent",
    "metrics": "measures.metrics", "references": "measures.references", "montage": "measures.montage",
})
