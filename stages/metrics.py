"""Image agreement measures (scikit-image's PSNR; Pearson correlation from numpy)."""

import numpy as np


def grey(image: np.ndarray) -> np.ndarray:
    """(H, W) or (H, W, 3) -> (H, W) float64 mean over colours."""
    image = np.asarray(image, np.float64)
    return image.mean(axis=2) if image.ndim == 3 else image


def correlation(a: np.ndarray, b: np.ndarray) -> float:
    """Pearson correlation of two images of the same size (colour averaged to grey)."""
    return float(np.corrcoef(grey(a).ravel(), grey(b).ravel())[0, 1])


def psnr(estimate: np.ndarray, truth: np.ndarray) -> float:
    """PSNR in dB of uint8 images (data range 255)."""
    from skimage.metrics import peak_signal_noise_ratio

    return float(peak_signal_noise_ratio(np.asarray(truth), np.asarray(estimate), data_range=255))


def side_by_side(*images: np.ndarray) -> np.ndarray:
    """Equal-height uint8 images (grey or RGB) joined left to right as RGB, 4-pixel gaps."""
    rgb = [np.repeat(i[:, :, None], 3, 2) if i.ndim == 2 else i for i in images]
    gap = np.full((rgb[0].shape[0], 4, 3), 255, np.uint8)
    parts = [p for image in rgb for p in (image, gap)][:-1]
    return np.concatenate(parts, axis=1)
