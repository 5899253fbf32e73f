"""The release: what stores and outputs record as ``cscsr_version`` (one home, read without the package's face)."""

__version__ = "0.1.0"
