"""cscsr: distributed super-resolution reconstruction for colour spike cameras (CSCSR, CVPR 2024).

This package holds the model side (network, baselines, weights, training) and the
bundled sample recordings; :mod:`stages` holds the pure array functions and
:mod:`pipeline` the storage, cluster and command-line side.
"""

__version__ = "0.1.0"
