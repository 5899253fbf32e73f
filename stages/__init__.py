"""Pure, composable array functions: decode, pack, represent, reconstruct.

A stage takes numpy arrays and returns numpy arrays. It never opens a file, never sees a
URL and never knows about Dask; :mod:`pipeline` does all of that around it.
"""
