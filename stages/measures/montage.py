"""Pictures for people: images side by side, with a label above each."""

import numpy as np


def as_rgb(image: np.ndarray) -> np.ndarray:
    return np.repeat(image[:, :, None], 3, 2) if image.ndim == 2 else image


def labelled(image: np.ndarray, text: str) -> np.ndarray:
    """A uint8 image with a white band above it carrying ``text``."""
    import cv2

    image = as_rgb(image)
    band = np.full((22, image.shape[1], 3), 255, np.uint8)
    cv2.putText(band, text, (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([band, image], axis=0)


def side_by_side(*images: np.ndarray) -> np.ndarray:
    """Equal-height uint8 images (grey or RGB) joined left to right as RGB, 4-pixel white gaps."""
    rgb = [as_rgb(image) for image in images]
    gap = np.full((rgb[0].shape[0], 4, 3), 255, np.uint8)
    parts = [part for image in rgb for part in (image, gap)][:-1]
    return np.concatenate(parts, axis=1)


def padded_to(image: np.ndarray, multiple: int) -> np.ndarray:
    """``image`` (H, W, ...) grown at the bottom and right to sides that are multiples of ``multiple``, its last
    row and column repeated (no resampling: every pixel keeps its place and value)."""
    grow = [(0, -side % multiple) for side in image.shape[:2]] + [(0, 0)] * (image.ndim - 2)
    return np.pad(image, grow, mode="edge") if any(after for _, after in grow) else image
