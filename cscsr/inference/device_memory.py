"""How much device memory the network takes, for sizing a GPU worker's tiles and passes.

Peak memory allocated by one forward pass at ×4 grows with the LR pixels of the window; the
figures are the H100 lease's (``docs/gpu.md``: one 1000×1000 LR window, batch 1, peak allocated),
per megapixel of LR input. A pass of ``n`` windows takes about ``n`` times as much.
"""

MIB = 2**20
PEAK_MIB_PER_LR_MEGAPIXEL = {  # (configuration, precision) -> MiB per 10^6 LR pixels of one window, at ×4
    ("lite", "fp32"): 15_356,
    ("lite", "bf16"): 12_351,
    ("full", "fp32"): 25_369,
    ("full", "bf16"): 15_905,
}
RESERVE = 0.2  # of the device's memory kept free: the CUDA context, cuDNN's workspaces, the allocator's slack


def bytes_per_lr_pixel(config: str, precision: str) -> float:
    """Device bytes one window takes per LR pixel; a configuration not measured takes the largest figure."""
    mib = PEAK_MIB_PER_LR_MEGAPIXEL.get((config, precision), max(PEAK_MIB_PER_LR_MEGAPIXEL.values()))
    return mib * MIB / 1e6


def usable_bytes(total_bytes: int) -> int:
    """What the network's passes may take of a device with ``total_bytes`` of memory. From the total, not
    from what is free now: the same GPU model always gets the same tiles, so a run is identical to itself."""
    return int(total_bytes * (1 - RESERVE))
