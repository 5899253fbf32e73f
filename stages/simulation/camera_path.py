"""A still image moved along a smooth random camera path: latent frames with exact optical flow.

The simulator needs one latent frame per spike frame and, for training and evaluation, the true
motion between any two of them. A :class:`CameraPath` is a closed-form warp, so both come from
the same formula: latent frame ``t`` at pixel ``p`` shows the source image at

    M_t(p) = c + A(t) (p - c) + T(t) + U(t, p)

with ``c`` the image centre, ``A = exp(zoom) * rotation(angle)``, ``T`` a translation and ``U``
an optional smooth local deformation. Translation, angle and zoom are sums of a few sinusoids
(``amplitude * (sin(omega t + phase) - sin(phase))``, so frame 0 has no global motion) plus, for
translation, a constant drift; ``U`` is a sum of plane waves ``a sin(k . (p - c) + omega t + phase)``.
Being sinusoids, the excursion stays bounded however long the clip: fast paths oscillate
rather than wander off the image. The flow from frame ``t0`` to ``t1`` is ``M_t1^-1(M_t0(x)) - x``:
closed form without deformation, Newton's method (to 1e-6 px) with it.

Frames are rendered with ``cv2.remap``, bicubic, ``BORDER_REFLECT_101``; OpenCV quantises
sampling positions to 1/32 px, the only gap between rendered frames and the exact flow.
Everything is computed per pixel without reductions, so results do not depend on thread count.
"""

import math
from dataclasses import dataclass

import numpy as np

from stages.errors import InputError

_EXCURSION = 0.1  # global motion stays within about this fraction of the shorter side
_ROTATION_WEIGHT, _ZOOM_WEIGHT = 0.35, 0.25  # their share of the motion, relative to translation
_WAVES_PER_CHANNEL, _DEFORMATION_WAVES = 3, 3
_WAVELENGTHS = (0.5, 1.0)  # deformation wavelengths, as fractions of the shorter side
_MAX_STRETCH = 0.8  # bound on the deformation's Jacobian norm: keeps every frame fold-free
_NEWTON_STEPS, _NEWTON_TOLERANCE = 30, 1e-6


def check_image(image: np.ndarray, name: str = "image") -> np.ndarray:
    """A float (H, W) or (H, W, C) image as a float32 array; InputError for anything else."""
    image = np.asarray(image)
    if image.ndim not in (2, 3) or (image.ndim == 3 and not 1 <= image.shape[2] <= 4) or min(image.shape[:2]) < 2:
        raise InputError(f"{name} must be (H, W) or (H, W, 3) with H, W >= 2, got shape {image.shape}")
    if not np.issubdtype(image.dtype, np.floating):
        raise InputError(f"{name} must be float in [0, 1], got {image.dtype}")
    return image.astype(np.float32, copy=False)


def _floats(rows, width: int, name: str) -> tuple:
    """Rows of ``width`` numbers -> tuple of tuples of Python floats (hashable, picklable)."""
    array = np.asarray(rows, np.float64).reshape(-1, width)
    if not np.isfinite(array).all():
        raise InputError(f"{name} must be finite numbers")
    return tuple(tuple(float(v) for v in row) for row in array)


def _sinusoids(waves: tuple, t: float) -> float:
    """Sum of ``amplitude * (sin(omega t + phase) - sin(phase))``: zero at t = 0."""
    return sum(a * (math.sin(omega * t + phase) - math.sin(phase)) for a, omega, phase in waves)


@dataclass(frozen=True)
class CameraPath:
    """A smooth random camera motion over frames 0..n_frames-1: translation, small rotation and
    zoom, plus an optional smooth local deformation field; all from the seed.

    Sinusoid rows are ``(amplitude, omega rad/frame, phase rad)``; amplitudes are pixels for
    ``shift_x``/``shift_y``, radians for ``rotation`` and natural-log scale for ``zoom``.
    ``deformation`` rows are plane waves ``(ax, ay, kx, ky, omega, phase)``: displacement
    ``(ax, ay)`` px, wave vector ``(kx, ky)`` rad/px. ``drift`` is a constant (dx, dy) px/frame
    added to the translation, so ``CameraPath(h, w, drift=(-3, -2))`` moves the scene by (3, 2)
    px per frame. The path is defined for any real t; ``n_frames`` only records its design span.
    """

    height: int
    width: int
    n_frames: int = 1
    drift: tuple = (0.0, 0.0)
    shift_x: tuple = ()
    shift_y: tuple = ()
    rotation: tuple = ()
    zoom: tuple = ()
    deformation: tuple = ()

    def __post_init__(self):
        if min(self.height, self.width) < 2 or self.n_frames < 1:
            raise InputError(f"a camera path needs height, width >= 2 and n_frames >= 1, got "
                             f"{self.height}x{self.width}, {self.n_frames} frames")
        for name in ("height", "width", "n_frames"):
            object.__setattr__(self, name, int(getattr(self, name)))
        object.__setattr__(self, "drift", _floats(self.drift, 2, "drift")[0])
        for name in ("shift_x", "shift_y", "rotation", "zoom"):
            object.__setattr__(self, name, _floats(getattr(self, name), 3, name))
        object.__setattr__(self, "deformation", _floats(self.deformation, 6, "deformation"))

    @classmethod
    def random(cls, n_frames: int, height: int, width: int, *, seed: int, speed: float = 0.5,
               deform: float = 0.0) -> "CameraPath":
        """A smooth random path. ``speed``: the RMS image velocity of the global motion in px/frame
        (over time and over the frame's pixels); ``deform``: the RMS local displacement in px.

        Each of translation x/y, rotation and zoom is 3 sinusoids with angular frequencies in
        [w, 3w], w = max(pi / n_frames, 2 speed / excursion): at least half a cycle over the clip,
        and fast enough that motion of that speed stays within ``excursion`` = 10 % of the
        shorter side. The deformation is 3 plane waves of wavelength 0.5-1x the shorter side;
        ``deform`` is limited so that no frame folds over (InputError beyond that).
        """
        if not (math.isfinite(speed) and speed >= 0 and math.isfinite(deform) and deform >= 0):
            raise InputError(f"speed and deform must be finite and >= 0, got {speed}, {deform}")
        if min(height, width) < 2 or n_frames < 1:
            raise InputError(f"a camera path needs height, width >= 2 and n_frames >= 1, got "
                             f"{height}x{width}, {n_frames} frames")
        side = min(height, width)
        max_deform = _MAX_STRETCH * _WAVELENGTHS[0] * side / (2 * math.pi * math.sqrt(2 * _DEFORMATION_WAVES))
        if deform > max_deform:
            raise InputError(f"deform {deform} px would fold a {height}x{width} frame; at most {max_deform:.2f} px")
        rng = np.random.default_rng(seed)
        lowest = max(math.pi / n_frames, 2 * speed / (_EXCURSION * side))

        # Global motion: (4 channels, 3 waves), amplitudes in px at the RMS radius, scaled to `speed`.
        omega = lowest * rng.uniform(1, 3, (4, _WAVES_PER_CHANNEL))
        phase = rng.uniform(0, 2 * math.pi, (4, _WAVES_PER_CHANNEL))
        weight = np.array([[1], [1], [_ROTATION_WEIGHT], [_ZOOM_WEIGHT]])
        amplitude = rng.standard_normal((4, _WAVES_PER_CHANNEL)) * weight
        rms_velocity = math.sqrt(float(np.sum((amplitude * omega) ** 2)) / 2)
        amplitude *= speed / rms_velocity
        radius = math.sqrt((height**2 + width**2) / 12)  # RMS distance of a pixel from the centre
        amplitude[2:] /= radius  # px at that radius -> radians / log scale
        x, y, angle, zoom = (np.stack([amplitude[i], omega[i], phase[i]], 1) for i in range(4))

        # Deformation: plane waves, each of displacement sqrt(2/N) * deform so the RMS is `deform`.
        direction = rng.uniform(0, 2 * math.pi, (2, _DEFORMATION_WAVES))
        wavenumber = 2 * math.pi / (side * rng.uniform(*_WAVELENGTHS, _DEFORMATION_WAVES))
        size = deform * math.sqrt(2 / _DEFORMATION_WAVES)
        waves = np.stack([size * np.cos(direction[0]), size * np.sin(direction[0]),
                          wavenumber * np.cos(direction[1]), wavenumber * np.sin(direction[1]),
                          lowest * rng.uniform(1, 3, _DEFORMATION_WAVES),
                          rng.uniform(0, 2 * math.pi, _DEFORMATION_WAVES)], 1)
        return cls(height, width, n_frames, (0.0, 0.0), x, y, angle, zoom, waves if deform > 0 else ())

    def scaled(self, factor: float) -> "CameraPath":
        """The same motion on a grid ``factor`` times the size (e.g. 1/4 for low resolution).

        Pixel centres follow cv2.resize: x_new + 0.5 = factor * (x + 0.5), so the centre maps
        to the centre and the new size must be a whole number of pixels.
        """
        height, width = self.height * factor, self.width * factor
        if not (factor > 0 and abs(height - round(height)) < 1e-6 and abs(width - round(width)) < 1e-6):
            raise InputError(f"scaling a {self.height}x{self.width} path by {factor} does not give whole pixels")
        def pixels(waves):
            return [(a * factor, omega, phase) for a, omega, phase in waves]

        waves = [(ax * factor, ay * factor, kx / factor, ky / factor, omega, phase)
                 for ax, ay, kx, ky, omega, phase in self.deformation]
        return CameraPath(round(height), round(width), self.n_frames, (self.drift[0] * factor, self.drift[1] * factor),
                          pixels(self.shift_x), pixels(self.shift_y), self.rotation, self.zoom, waves)

    def _affine(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(2, 2) matrix A and (2,) translation T of the global motion at time t."""
        angle, scale = _sinusoids(self.rotation, t), math.exp(_sinusoids(self.zoom, t))
        matrix = scale * np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
        shift = np.array([self.drift[0] * t + _sinusoids(self.shift_x, t),
                          self.drift[1] * t + _sinusoids(self.shift_y, t)])
        return matrix, shift

    def _deform(self, t: float, x: np.ndarray, y: np.ndarray, jacobian: bool = False):
        """Displacement (ux, uy) at centred points (x, y); with ``jacobian``, also d(ux, uy)/d(x, y)."""
        ux, uy = np.zeros_like(x), np.zeros_like(x)
        d = [np.zeros_like(x) for _ in range(4)]  # dux/dx, dux/dy, duy/dx, duy/dy
        for ax, ay, kx, ky, omega, phase in self.deformation:
            argument = kx * x + ky * y + (omega * t + phase)
            ux += ax * np.sin(argument)
            uy += ay * np.sin(argument)
            if jacobian:
                cos = np.cos(argument)
                d[0] += ax * kx * cos
                d[1] += ax * ky * cos
                d[2] += ay * kx * cos
                d[3] += ay * ky * cos
        return (ux, uy, d) if jacobian else (ux, uy)

    def _centred_grid(self) -> tuple[np.ndarray, np.ndarray]:
        """(H, W) float64 pixel coordinates x, y relative to the image centre."""
        y, x = np.mgrid[0 : self.height, 0 : self.width].astype(np.float64)
        return x - (self.width - 1) / 2, y - (self.height - 1) / 2

    def _forward(self, t: float, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """M_t at centred points: the centred source position each shows."""
        matrix, shift = self._affine(t)
        (a, b), (c, d) = matrix
        ux, uy = self._deform(t, x, y)
        return a * x + b * y + shift[0] + ux, c * x + d * y + shift[1] + uy

    def _inverse(self, t: float, qx: np.ndarray, qy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """M_t^-1 at centred source points: closed form, then Newton steps on the deformation."""
        matrix, shift = self._affine(t)
        (a, b), (c, d) = matrix
        inverse = np.linalg.inv(matrix)
        rx, ry = qx - shift[0], qy - shift[1]
        x, y = inverse[0, 0] * rx + inverse[0, 1] * ry, inverse[1, 0] * rx + inverse[1, 1] * ry
        for _ in range(_NEWTON_STEPS if self.deformation else 0):
            ux, uy, (dxx, dxy, dyx, dyy) = self._deform(t, x, y, jacobian=True)
            ex, ey = a * x + b * y + ux - rx, c * x + d * y + uy - ry  # residual M_t(x) - q
            if max(np.abs(ex).max(), np.abs(ey).max()) < _NEWTON_TOLERANCE:
                break
            jxx, jxy, jyx, jyy = a + dxx, b + dxy, c + dyx, d + dyy
            determinant = jxx * jyy - jxy * jyx
            x = x - (jyy * ex - jxy * ey) / determinant
            y = y - (jxx * ey - jyx * ex) / determinant
        return x, y

    def sample_map(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(map_x, map_y) float32 (H, W): latent frame t at pixel (x, y) shows the source image at
        (map_x, map_y) (cv2.remap convention)."""
        x, y = self._centred_grid()
        qx, qy = self._forward(t, x, y)
        return (qx + (self.width - 1) / 2).astype(np.float32), (qy + (self.height - 1) / 2).astype(np.float32)

    def flow(self, t0: float, t1: float) -> np.ndarray:
        """(H, W, 2) float32 (dx, dy) in pixels: the scene point seen at pixel x in frame t0 is seen
        at x + flow(x) in frame t1."""
        x, y = self._centred_grid()
        seen_x, seen_y = self._inverse(t1, *self._forward(t0, x, y))
        return np.stack([seen_x - x, seen_y - y], axis=2).astype(np.float32)


def render(image: np.ndarray, path: CameraPath, t: float) -> np.ndarray:
    """Latent frame t: ``image`` warped by the path (cv2.remap, bicubic, BORDER_REFLECT_101), same
    shape, float32, clipped to [0, 1]."""
    import cv2

    image = check_image(image)
    if image.shape[:2] != (path.height, path.width):
        raise InputError(f"image is {image.shape[0]}x{image.shape[1]} but the path is {path.height}x{path.width}")
    map_x, map_y = path.sample_map(t)
    frame = cv2.remap(image, map_x, map_y, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT_101)
    return np.clip(frame.reshape(image.shape), 0, 1)


def backward_warp(image: np.ndarray, flow: np.ndarray, phase: tuple[int, int] | None = None) -> np.ndarray:
    """Sample ``image`` at x + flow(x) (bilinear, BORDER_REFLECT_101), float32 of its shape:
    ``backward_warp(frame_t1, path.flow(t0, t1))`` ~ frame_t0. Any (H, W, C<=4) array works.

    ``phase=(dy, dx)``: only the pixels of one 2x2 Bayer phase, ``backward_warp(image, flow)[dy::2, dx::2]``
    with the same bytes, each sample computed alone at a quarter of the cost."""
    import cv2

    image = np.asarray(image, np.float32)
    flow = np.asarray(flow, np.float32)
    if image.ndim not in (2, 3) or flow.shape != (*image.shape[:2], 2):
        raise InputError(f"flow must be (H, W, 2) for an (H, W[, C]) image, got {flow.shape} for {image.shape}")
    height, width = flow.shape[:2]
    rows, cols = (slice(None), slice(None)) if phase is None else (slice(phase[0], None, 2), slice(phase[1], None, 2))
    map_x = flow[rows, cols, 0] + np.arange(width, dtype=np.float32)[cols]
    map_y = flow[rows, cols, 1] + np.arange(height, dtype=np.float32)[rows, None]
    warped = cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)
    return warped.reshape((*map_x.shape, *image.shape[2:]))
