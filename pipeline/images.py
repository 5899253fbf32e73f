"""Reading and writing single images (PNG, JPEG, ...) at any URL, through imageio."""

import imageio.v3 as iio
import numpy as np

from pipeline.storage import new_output, resolve


def read_image(url: str) -> np.ndarray:
    fs, path = resolve(url)
    with fs.open(path, "rb") as handle:
        return iio.imread(handle.read(), extension="." + path.rsplit(".", 1)[-1])


def write_image(url: str, image: np.ndarray, *, overwrite: bool = True) -> None:
    fs, path = resolve(url)
    encoded = iio.imwrite("<bytes>", image, extension="." + path.rsplit(".", 1)[-1])
    with new_output(url, overwrite=overwrite):
        fs.makedirs(fs._parent(path), exist_ok=True)
        with fs.open(path, "wb") as handle:
            handle.write(encoded)
