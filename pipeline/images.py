"""Reading and writing single images (PNG, JPEG, ...) at any URL, through imageio."""

import os

import imageio.v3 as iio
import numpy as np

from pipeline.storage import resolve
from stages.errors import InputError

_TIFF = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")  # little/big endian, classic/BigTIFF
# The images we read and write, by suffix: a test of a file's first 16 bytes saying it is one
# (what ``--overwrite`` replaces: ``pipeline.outputs``).
IMAGE_MAGIC = {".png": lambda b: b.startswith(b"\x89PNG\r\n\x1a\n"), ".jpg": lambda b: b.startswith(b"\xff\xd8\xff"),
               ".jpeg": lambda b: b.startswith(b"\xff\xd8\xff"), ".tif": lambda b: b[:4] in _TIFF,
               ".tiff": lambda b: b[:4] in _TIFF, ".bmp": lambda b: b.startswith(b"BM"),
               ".webp": lambda b: b[:4] == b"RIFF" and b[8:12] == b"WEBP"}
IMAGE_SUFFIXES = tuple(IMAGE_MAGIC)


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
    from pipeline.outputs import new_output  # which imports this module's IMAGE_MAGIC

    fs, path = resolve(url)
    encoded = iio.imwrite("<bytes>", image, extension=image_suffix(url))
    with new_output(url, overwrite=overwrite, kind=image_suffix(url)):  # only an image replaces an image
        fs.makedirs(fs._parent(path), exist_ok=True)
        with fs.open(path, "wb") as handle:
            handle.write(encoded)
