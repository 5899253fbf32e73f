"""Image agreement measures: PSNR and SSIM (scikit-image), Pearson correlation (numpy)."""

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


SSIM_SIDE = 11  # the side of SSIM's Gaussian window (sigma 1.5, truncated at 3.5 sigma): the least image it scores


def ssim(estimate: np.ndarray, truth: np.ndarray) -> float:
    """SSIM of uint8 images (scikit-image, Gaussian-weighted as in Wang et al. 2004), at least
    :data:`SSIM_SIDE` pixels a side."""
    from skimage.metrics import structural_similarity

    channel_axis = 2 if np.ndim(truth) == 3 else None
    return float(structural_similarity(np.asarray(truth), np.asarray(estimate), data_range=255,
                                       channel_axis=channel_axis, gaussian_weights=True, sigma=1.5,
                                       use_sample_covariance=False))
