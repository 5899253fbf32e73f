"""Reading and writing single images (PNG, JPEG, ...) at any URL, through imageio."""

import os

import imageio.v3 as iio
import numpy as np
from fsspec.implementations.local import LocalFileSystem

from pipeline.stores.outputs import IMAGE_MAGIC, new_output
from pipeline.stores.storage import resolve
from stages.errors import InputError, describe

IMAGE_SUFFIXES = tuple(IMAGE_MAGIC)  # the images we read and write


def image_suffix(url: str) -> str:
    """The image kind of a name (``.png``, ...); a one-line error naming it if it is not one we read and write."""
    suffix = os.path.splitext(str(url))[1].lower()
    if suffix not in IMAGE_SUFFIXES:
        raise InputError(f"{url}: unknown image extension {repr(suffix) if suffix else '(none)'}: expected one of "
                         f"{', '.join(IMAGE_SUFFIXES)}")
    return suffix


def decode_image(data: bytes, name: str) -> np.ndarray:
    """The image in ``data`` (the bytes of the file ``name``); a one-line error naming the file if it is not
    an image of the kind its name says (a text file called ``.png``)."""
    suffix = image_suffix(name)
    try:
        return iio.imread(data, extension=suffix)
    except (OSError, ValueError, RuntimeError, SyntaxError):  # what imageio's plugins raise on bad bytes
        raise InputError(f"{name} is not a valid {suffix[1:].upper()} image: it cannot be decoded (it starts with "
                         f"{data[:8]!r})") from None


def read_image(url: str) -> np.ndarray:
    fs, path = resolve(url)
    image_suffix(url)
    with fs.open(path, "rb") as handle:
        return decode_image(handle.read(), url)


def write_image(url: str, image: np.ndarray, *, overwrite: bool = True) -> None:
    fs, path = resolve(url)
    encoded = iio.imwrite("<bytes>", image, extension=image_suffix(url))
    with new_output(url, overwrite=overwrite, kind=image_suffix(url)):  # only an image replaces an image
        if isinstance(fs, LocalFileSystem):  # an object store has no folders (and s3fs would make a bucket)
            fs.makedirs(fs._parent(path), exist_ok=True)
        try:
            with fs.open(path, "wb") as handle:
                handle.write(encoded)
        except FileNotFoundError as error:  # no such bucket: said of the output
            raise InputError(f"cannot write {url}: {describe(error)}") from None
