"""Bundled sample recordings (see README.md here for provenance and known answers)."""

from importlib.resources import files

REDS_DAT = "synthetic_reds_200_part1_250x400.dat"
REDS_GT = "synthetic_reds_200_part1_gt.png"
HELICOPTER_NPZ = "uhsr_u_caltech_helicopter.npz"

# Known answers for the synthetic REDS clip (Spike-Zoo's data/data.dat).
REDS_HEIGHT, REDS_WIDTH, REDS_FRAMES = 250, 400, 301
REDS_KEY_FRAME, REDS_GAIN = 151, 1 / 0.6


def path(name: str) -> str:
    """Filesystem path of a bundled sample."""
    return str(files(__name__) / name)
