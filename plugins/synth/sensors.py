"""Randomised depth sensors and camera errors: a structured-light sensor with a depth bias field, a
time-of-flight sensor, intrinsics stated off the rendered ones and colour a pixel or two off depth.

Every draw takes its numbers from a ``numpy.random.Generator`` and returns frozen dataclasses whose
``record()`` is what ``truth.json`` keeps, so that results can be analysed by the sensor drawn.

Notes
-----
Structured light (Kinect v1, RealSense D400) measures disparity d and returns z = f b / d, so a
disparity error e moves depth by z**2 e / (f b): both the quantisation step and a calibration
residual grow with the square of the range. Khoshelham & Elberink (2012) measure the random error
growing from a few millimetres at 1 m to 4 cm at 5 m; plane scans show a smooth, roughly radial
distortion of a few millimetres at 1 m that grows with range (Smisek et al. 2011; Clarkson et al.
2013 correct it to +-3 mm). Intel's D400 papers give depth RMS = z**2 s / (f b), with a subpixel s of
about 0.05-0.1 px. Here the bias is a fixed disparity error over the image, drawn so that its RMS
is 1-4 mm at 1 m.

Time of flight (Kinect v2, Azure Kinect) measures phase: its noise grows as the returned amplitude
falls (sigma proportional to 1 / sqrt(amplitude); amplitude ~ reflectance cos(theta) / z**2), so dark
and grazing surfaces are noisy and below an amplitude they return nothing; light scattered from a
neighbouring surface into a concave corner lengthens the path (multipath, up to centimetres); a pixel
that straddles an edge mixes the two depths (flying pixels); and the phase-to-depth map has a
periodic "wiggling" error of a few millimetres (Sarbolandi, Lefloch & Kolb 2015; Corti et al. 2016;
Tolgyessy et al. 2021).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import cv2
import numpy as np

from .render import CleanFrame, Intrinsics, NoiseLevel, _depth_edges, _flying_pixels, _noisy_colour

__all__ = [
    "SENSOR_KINDS",
    "CameraDraw",
    "StructuredLight",
    "TimeOfFlight",
    "add_tof_noise",
    "bias_field_1m",
    "draw_camera",
    "draw_sensor",
    "sensor_header",
    "shift_colour",
]

#: Sensor kinds a randomised sequence may draw.
SENSOR_KINDS = ("structured_light", "time_of_flight")
#: The reference width: pixel offsets and errors are drawn for 640 px and scaled with the image.
_REFERENCE_WIDTH_PX = 640
#: Reflectance and distance at which a time-of-flight sensor's stated noise holds (a grey card at 1 m).
_TOF_REFERENCE_ALBEDO = 0.5
#: Delivered depth unit, metres.
_DEPTH_STEP_M = 0.001


def _u(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(rng.uniform(lo, hi))


def _rounded(d: dict, digits: int = 6) -> dict:
    return {k: round(v, digits) if isinstance(v, float) else v for k, v in d.items()}


def sensor_header(*, fx_px: float, axial_a_m: float, axial_b_per_m: float, depth_step_m: float) -> dict:
    """The first keys of ``truth.json`` ``sensor``, the ones the observable pair truth reads: the
    focal length and the axial noise ``a + b (z - 0.4)**2``, metres, and the delivered depth unit."""
    return {
        "fx_px": fx_px,
        "axial_a_m": axial_a_m,
        "axial_b_per_m": axial_b_per_m,
        "axial_reference_m": 0.4,
        "depth_step_m": depth_step_m,
    }


# ------------------------------------------------------------------ camera


@dataclass(frozen=True)
class CameraDraw:
    """The camera of a randomised sequence.

    Attributes
    ----------
    rendered : Intrinsics
        What the images were rendered with.
    stated : Intrinsics
        What ``meta.json`` says (a calibration a few percent off).
    colour_offset_px : tuple of 2 floats
        Colour pixel (u + dx, v + dy) sees what depth pixel (u, v) sees.
    """

    rendered: Intrinsics
    stated: Intrinsics
    colour_offset_px: tuple[float, float]

    def record(self) -> dict:
        def k(i: Intrinsics) -> dict:
            return {n: round(getattr(i, f"{n}_px"), 6) for n in ("fx", "fy", "cx", "cy")}

        return {
            "rendered": k(self.rendered),
            "stated": k(self.stated),
            "colour_offset_px": [round(v, 6) for v in self.colour_offset_px],
        }


#: Bounds of the camera draw at 640 px wide (pixel quantities scale with the width).
FOCAL_RANGE = (0.9, 1.1)  # rendered focal length, times the resolution's nominal one
PRINCIPAL_SPREAD_PX = 8.0  # rendered principal point off the image centre
STATED_FOCAL_ERROR = 0.03  # stated focal length off the rendered one, relative
STATED_ASPECT_ERROR = 0.005  # fy's error beyond fx's, relative
STATED_PRINCIPAL_ERROR_PX = 5.0
COLOUR_OFFSET_MAX_PX = 2.0


def draw_camera(width_px: int, height_px: int, rng: np.random.Generator) -> CameraDraw:
    """A rendered camera around ``Intrinsics.for_resolution``, the intrinsics a user would state for
    it (focal length within +-3 %, principal point within +-5 px at 640 px wide) and a colour-depth
    offset of 0-2 px (in a random direction), pixel quantities scaled with the image width."""
    nominal = Intrinsics.for_resolution(width_px, height_px)
    px = width_px / _REFERENCE_WIDTH_PX
    f = nominal.fx_px * _u(rng, *FOCAL_RANGE)
    spread = PRINCIPAL_SPREAD_PX * px
    rendered = Intrinsics(
        width_px,
        height_px,
        f,
        f * nominal.fy_px / nominal.fx_px,
        nominal.cx_px + _u(rng, -spread, spread),
        nominal.cy_px + _u(rng, -spread, spread),
    )
    e = _u(rng, -STATED_FOCAL_ERROR, STATED_FOCAL_ERROR)
    e_aspect = _u(rng, -STATED_ASPECT_ERROR, STATED_ASPECT_ERROR)
    c = STATED_PRINCIPAL_ERROR_PX * px
    stated = Intrinsics(
        width_px,
        height_px,
        rendered.fx_px * (1 + e),
        rendered.fy_px * (1 + e + e_aspect),
        rendered.cx_px + _u(rng, -c, c),
        rendered.cy_px + _u(rng, -c, c),
    )
    r, a = _u(rng, 0.0, COLOUR_OFFSET_MAX_PX) * px, _u(rng, 0.0, 2 * math.pi)
    return CameraDraw(rendered, stated, (r * math.cos(a), r * math.sin(a)))


def shift_colour(rgb: np.ndarray, offset_px) -> np.ndarray:
    """``rgb`` (H, W, C) moved by ``offset_px`` = (dx, dy): out(u, v) = rgb(u - dx, v - dy), bilinear,
    the border repeated."""
    dx, dy = (float(v) for v in offset_px)
    if dx == 0.0 and dy == 0.0:
        return rgb
    h, w = rgb.shape[:2]
    M = np.float32([[1.0, 0.0, dx], [0.0, 1.0, dy]])
    return cv2.warpAffine(rgb, M, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


# ------------------------------------------------------------------ structured light


@dataclass(frozen=True)
class StructuredLight:
    """A structured-light (or active-stereo) sensor: ``NoiseLevel``'s model with drawn parameters and
    a fixed disparity bias over the image.

    Attributes
    ----------
    level : NoiseLevel
        Random noise, dropouts, flying pixels, quantisation (its ``focal_px`` and ``baseline_m`` are
        the sensor's).
    bias_rms_1m_m : float
        RMS over the image of the depth bias at 1 m, metres.
    bias_terms : tuple of tuple
        The bias pattern (see ``bias_field_1m``).
    """

    level: NoiseLevel
    bias_rms_1m_m: float
    bias_terms: tuple

    kind = "structured_light"

    def disparity_bias_px(self, intrinsics: Intrinsics) -> np.ndarray:
        """The disparity error over the image, pixels of ``level.focal_px``, shape (H, W)."""
        field_m = bias_field_1m(intrinsics, self.bias_terms, rms_m=self.bias_rms_1m_m)
        return field_m * self.level.focal_px * self.level.baseline_m

    def record(self, intrinsics: Intrinsics) -> dict:
        """``truth.json`` ``sensor``: the keys the observable pair truth reads, then the draw."""
        lv = self.level
        out = {
            **sensor_header(
                fx_px=intrinsics.fx_px,
                axial_a_m=lv.axial_a_m,
                axial_b_per_m=lv.axial_b_per_m,
                depth_step_m=lv.depth_step_m,
            ),
            "kind": self.kind,
            "bias_rms_1m_m": self.bias_rms_1m_m,
            "bias_terms": [list(t) for t in self.bias_terms],
        }
        out.update({k: v for k, v in asdict(lv).items() if k not in out and k != "name"})
        return _rounded(out, 8)


def bias_field_1m(intrinsics: Intrinsics, terms, *, rms_m: float) -> np.ndarray:
    """A smooth depth bias over the image at 1 m, metres, shape (H, W), with RMS ``rms_m``.

    ``terms`` are ``(kind, a, b, c, weight)``: ``("radial", ...)`` adds ``weight * r**2`` (r the
    distance from the principal point over the half-diagonal; a plane scanned by a Kinect bows this
    way), ``("wave", kx, ky, phase, weight)`` adds ``weight * cos(2 pi (kx x + ky y) + phase)`` over
    normalised image coordinates x, y in [-1, 1] (a few cycles across the image at most), and
    ``("offset", 0, 0, 0, weight)`` a constant (a scale error of the range).
    """
    h, w = intrinsics.height_px, intrinsics.width_px
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    x = (u - intrinsics.cx_px) / (w / 2.0)
    y = (v - intrinsics.cy_px) / (h / 2.0)
    field = np.zeros((h, w))
    for kind, a, b, c, weight in terms:
        if kind == "radial":
            field += weight * (x * x + y * y) / 2.0
        elif kind == "wave":
            field += weight * np.cos(2 * math.pi * (a * x + b * y) + c)
        elif kind == "offset":
            field += weight
        else:
            raise ValueError(f"unknown bias term {kind!r}")
    rms = float(np.sqrt(np.mean(field**2)))
    return field * (rms_m / rms) if rms > 0 else field


#: Bounds of the structured-light draw.
SL_BIAS_RMS_1M_M = (0.001, 0.004)


def _draw_structured_light(rng: np.random.Generator, focal_px: float) -> StructuredLight:
    a = _u(rng, 0.0008, 0.003)
    start = _u(rng, 62.0, 75.0)
    level = NoiseLevel(
        "structured_light",
        axial_a_m=a,
        axial_b_per_m=a * _u(rng, 1.3, 1.9),
        disparity_subpixel=_u(rng, 1 / 16, 1 / 4),
        grazing_start_deg=start,
        grazing_end_deg=min(start + _u(rng, 8.0, 14.0), 88.0),
        grazing_drop_prob=_u(rng, 0.8, 0.97),
        edge_drop_prob=_u(rng, 0.2, 0.6),
        lateral_fraction=_u(rng, 0.2, 0.5),
        random_drop_fraction=_u(rng, 0.002, 0.012),
        speckle_fraction=_u(rng, 1e-4, 1.5e-3),
        projector_shadow=True,
        rgb_sigma=_u(rng, 0.4, 3.0),
        min_range_m=_u(rng, 0.2, 0.45),
        max_range_m=_u(rng, 3.0, 6.0),
        flying_fraction=_u(rng, 0.2, 0.6),
        depth_step_m=_DEPTH_STEP_M,
        baseline_m=_u(rng, 0.05, 0.08),
        focal_px=focal_px,
    )
    terms = [("offset", 0.0, 0.0, 0.0, _u(rng, -1.0, 1.0)), ("radial", 0.0, 0.0, 0.0, _u(rng, -2.0, 2.0))]
    for _ in range(3):
        f, ang = _u(rng, 0.15, 1.0), _u(rng, 0.0, math.pi)
        terms.append(
            ("wave", f * math.cos(ang), f * math.sin(ang), _u(rng, 0, 2 * math.pi), _u(rng, 0.3, 1.0))
        )
    terms = tuple(tuple(round(v, 6) if isinstance(v, float) else v for v in t) for t in terms)
    return StructuredLight(level, _u(rng, *SL_BIAS_RMS_1M_M), terms)


# ------------------------------------------------------------------ time of flight


@dataclass(frozen=True)
class TimeOfFlight:
    """A continuous-wave time-of-flight sensor.

    Attributes
    ----------
    sigma_1m_m : float
        Depth noise on a 50 % reflectance surface facing the camera at 1 m, metres; it grows as
        1 / sqrt(amplitude), amplitude = reflectance * cos(incidence) / z**2 (z in metres).
    amplitude_min : float
        Below this amplitude a pixel returns nothing; between it and twice it, with a probability
        falling linearly to 0.
    multipath_gain, multipath_scale_m, multipath_max_m : float
        Concave corners read too far by ``gain`` times how far the pixel lies behind its
        neighbourhood (a Gaussian of ``scale_m`` on the surface), at most ``max_m``.
    wiggle_m, wiggle_period_m, wiggle_phase : float
        The periodic range error ``wiggle_m * sin(2 pi z / period + phase)``.
    flying_fraction, edge_drop_prob, random_drop_fraction : float
        Shares of edge pixels mixing two depths, of edge pixels lost, of all pixels lost.
    rgb_sigma : float
        Colour noise, 8-bit levels.
    min_range_m, max_range_m, depth_step_m : float
    """

    sigma_1m_m: float
    amplitude_min: float
    multipath_gain: float
    multipath_scale_m: float
    multipath_max_m: float
    wiggle_m: float
    wiggle_period_m: float
    wiggle_phase: float
    flying_fraction: float
    edge_drop_prob: float
    random_drop_fraction: float
    rgb_sigma: float
    min_range_m: float
    max_range_m: float
    depth_step_m: float = _DEPTH_STEP_M

    kind = "time_of_flight"

    def sigma_m(self, amplitude) -> np.ndarray:
        """Depth noise, metres, where the returned amplitude is ``amplitude``."""
        ref = _TOF_REFERENCE_ALBEDO
        return self.sigma_1m_m * np.sqrt(ref / np.maximum(np.asarray(amplitude, float), 1e-6))

    def record(self, intrinsics: Intrinsics) -> dict:
        """``truth.json`` ``sensor``: the observable pair truth's keys, with the axial noise of a 50 %
        reflectance surface facing the camera (sigma_1m * z) fitted as a + b (z - 0.4)**2 over
        0.4-1.6 m, then the draw."""
        z = np.linspace(0.4, 1.6, 25)
        A = np.column_stack([np.ones_like(z), (z - 0.4) ** 2])
        a, b = np.linalg.lstsq(A, self.sigma_1m_m * z, rcond=None)[0]
        out = {
            **sensor_header(
                fx_px=intrinsics.fx_px,
                axial_a_m=float(a),
                axial_b_per_m=float(b),
                depth_step_m=self.depth_step_m,
            ),
            "kind": self.kind,
        }
        out.update({k: v for k, v in asdict(self).items() if k not in out})
        return _rounded(out, 8)


def _draw_time_of_flight(rng: np.random.Generator) -> TimeOfFlight:
    return TimeOfFlight(
        sigma_1m_m=_u(rng, 0.001, 0.003),
        amplitude_min=_u(rng, 0.02, 0.06),
        multipath_gain=_u(rng, 0.3, 1.0),
        multipath_scale_m=_u(rng, 0.03, 0.08),
        multipath_max_m=0.03,
        wiggle_m=_u(rng, 0.001, 0.004),
        wiggle_period_m=_u(rng, 0.6, 2.0),
        wiggle_phase=_u(rng, 0.0, 2 * math.pi),
        flying_fraction=_u(rng, 0.4, 0.9),
        edge_drop_prob=_u(rng, 0.1, 0.4),
        random_drop_fraction=_u(rng, 0.001, 0.01),
        rgb_sigma=_u(rng, 0.4, 3.0),
        min_range_m=_u(rng, 0.2, 0.5),
        max_range_m=_u(rng, 3.0, 5.0),
    )


def draw_sensor(kind: str, rng: np.random.Generator, *, intrinsics: Intrinsics):
    """A ``StructuredLight`` or ``TimeOfFlight`` sensor with parameters drawn from their ranges.

    Parameters
    ----------
    kind : {"structured_light", "time_of_flight"}
    rng : numpy.random.Generator
    intrinsics : Intrinsics
        The rendered camera; a structured-light sensor's disparity is measured at its focal length
        scaled to 640 px wide.
    """
    if kind == "structured_light":
        return _draw_structured_light(rng, intrinsics.fx_px * _REFERENCE_WIDTH_PX / intrinsics.width_px)
    if kind == "time_of_flight":
        return _draw_time_of_flight(rng)
    raise ValueError(f"sensor kind={kind!r} is not one of {SENSOR_KINDS}")


def multipath_bias_m(
    depth_m: np.ndarray,
    *,
    fx_px: float,
    scale_m: float,
    gain: float,
    max_m: float,
    edges: np.ndarray | None = None,
) -> np.ndarray:
    """How much farther a time-of-flight sensor reads each pixel because of light scattered into it
    from its neighbourhood, metres, shape (H, W).

    A pixel that lies behind the mean of its surface neighbourhood (a Gaussian of ``scale_m`` at the
    median depth) sits in a concave corner, which neighbouring surfaces light: it reads ``gain`` times
    that depth difference farther, at most ``max_m``. Flat and convex surfaces (a pixel at or in
    front of its neighbourhood) read true. A neighbourhood that crosses a depth edge counts the less
    the nearer the edge, nothing at it and in full two Gaussian sigmas away: the background behind an
    object's silhouette is not a corner it lights, and scattered light fades with distance, so a hand
    coming near a corner changes its bias a little for each pixel it moves, never switching it off.
    ``edges`` is ``_depth_edges(depth_m)`` when the caller has it already.
    """
    valid = depth_m > 0
    if not valid.any():
        return np.zeros_like(depth_m)
    h, w = depth_m.shape
    sigma_px = max(1.0, fx_px * scale_m / float(np.median(depth_m[valid])))
    # The neighbourhood mean is smooth: take it at a quarter of the resolution when that is much
    # smaller than the neighbourhood, then interpolate it back.
    k = 4 if sigma_px >= 8 and min(h, w) >= 64 else 1
    z = np.where(valid, depth_m, 0.0).astype(np.float32)
    small = (max(w // k, 1), max(h // k, 1))
    zs = cv2.resize(z, small, interpolation=cv2.INTER_AREA)
    ws = cv2.resize(valid.astype(np.float32), small, interpolation=cv2.INTER_AREA)
    mean = cv2.GaussianBlur(zs, (0, 0), sigma_px / k) / np.maximum(
        cv2.GaussianBlur(ws, (0, 0), sigma_px / k), 1e-6
    )
    mean = cv2.resize(mean, (w, h), interpolation=cv2.INTER_LINEAR)
    behind = np.clip(z - mean, 0.0, None)
    edges = (_depth_edges(depth_m) if edges is None else edges).astype(np.uint8)
    lit = np.clip(cv2.distanceTransform(1 - edges, cv2.DIST_L2, 3) / (2 * sigma_px), 0.0, 1.0)
    return np.where(valid, lit * np.minimum(gain * behind, max_m), 0.0)


def add_tof_noise(
    frame: CleanFrame, *, sensor: TimeOfFlight, fx_px: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """What a time-of-flight RGB-D sensor delivers for a clean rendering.

    Steps, in order: the multipath bias at concave corners and the wiggling error, flying pixels
    (a depth between the foreground's and the background's) and dropouts at depth edges, noise that
    grows as the amplitude falls (reflectance ``frame.albedo`` times the cosine of incidence over
    z**2), dropouts where the amplitude is too low (dark, grazing or far surfaces), random dropouts,
    range limits and 1 mm steps; colour gets Gaussian noise.

    Returns
    -------
    depth_m : ndarray, shape (H, W), float32, 0 = no reading
    rgb : ndarray, shape (H, W, 3), uint8
    """
    z = frame.depth_m.astype(np.float64).copy()
    h, w = z.shape
    valid = z > 0
    rgb8 = _noisy_colour(frame.rgb, sensor.rgb_sigma, rng)
    albedo = frame.albedo if frame.albedo is not None else frame.rgb.mean(axis=2)
    amplitude = albedo * frame.cos_incidence / np.maximum(z, 0.05) ** 2
    edges = _depth_edges(z)  # of the clean depth: the multipath bias and the edge effects both use it

    z = z + multipath_bias_m(
        z,
        fx_px=fx_px,
        scale_m=sensor.multipath_scale_m,
        gain=sensor.multipath_gain,
        max_m=sensor.multipath_max_m,
        edges=edges,
    )
    z = np.where(
        valid, z + sensor.wiggle_m * np.sin(2 * math.pi * z / sensor.wiggle_period_m + sensor.wiggle_phase), 0
    )

    z = _flying_pixels(z, edges, fraction=sensor.flying_fraction, rng=rng)
    keep = valid & ~(edges & (rng.random((h, w)) < sensor.edge_drop_prob))

    z = z + rng.normal(0.0, 1.0, size=(h, w)) * sensor.sigma_m(amplitude)
    weak = np.clip((2.0 * sensor.amplitude_min - amplitude) / sensor.amplitude_min, 0.0, 1.0)
    keep &= ~(rng.random((h, w)) < weak)
    keep &= ~(rng.random((h, w)) < sensor.random_drop_fraction)
    keep &= (z >= sensor.min_range_m) & (z <= sensor.max_range_m)
    z = np.rint(z / sensor.depth_step_m) * sensor.depth_step_m
    return np.where(keep, z, 0.0).astype(np.float32), rgb8
