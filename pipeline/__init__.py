"""Everything that touches storage and the cluster: stores, captures, CLI.

The pipeline moves blocks between storage and :mod:`stages`; it never computes on pixels.
"""
