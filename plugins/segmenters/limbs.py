"""Limbs: the forearm that enters the picture, found by its shape alone, whatever its colour.

A forearm, bare or sleeved, gloved or a robot's, is a straight cylinder a few centimetres across
(:data:`FOREARM_RADIUS_M`) that enters the picture at its border and is held above the table. Its
readings may start farther in: a sleeve nearer than the sensor's range, or black under time of
flight, leaves a gap in them that reaches the border. So, in each region standing out of the
background that reaches the image border, or such a gap:

1. the *stub*: its points within :data:`STUB_M` of where it enters (the middle of a run of its
   pixels along the border, or the gap, at least a forearm wide at the run's own depth, since a
   forearm reaching in from far away looks slim there; each run is tried);
2. the *cylinder* through them: its axis runs along the direction their surface normals (of the
   readings averaged over :data:`NORMAL_M`, which the sensor's noise tilts little) are all square
   to, pointing into the picture; across the axis, a circle fitted to the points gives the
   axis's place and the radius. A stretch of points elongated along one direction
   (:data:`ELONGATED`) gives the axis by its length instead. The stub must be a cylinder: its
   points scatter about the circle by no more than :data:`RADIUS_SLACK_M`, and its arc bulges off
   its chord by a good part of the radius (:data:`RELIEF`; a flat strip does not bulge);
3. the *trace*: slab after slab of :data:`SLAB_M` along the axis, each added while most of its points
   near the axis (:data:`INSIDE_SHARE`) lie within the radius of it, give or take the stub's own
   scatter about the radius (the sensor's noise; :data:`RADIUS_SLACK_M` at least), the cylinder
   refitted to all the points taken so far. It stops where the slab is empty (the arm ends) or
   where its points spread wider than a forearm (the hand, or the object it holds or rests on).

The trace is a forearm when it reaches at least :data:`FOREARM_MIN_M` into the picture, its radius
is a forearm's, and it does not rest on the support plane. Its hand is taken with it: the points
beyond the trace's end, up to :data:`HAND_REACH_M` along the axis and within :data:`HAND_RADIUS_M`
of it (a hand continues its forearm; the wrist bends a little). An object the hand holds or passes
over loses what of it lies inside that reach, never more.

A large object that enters the picture is no cylinder; one lying on the table rests on it. A
cylinder held above the table and cut by the picture's border (a carried bottle seen in part) cannot
be told from a forearm by shape, and is taken for one.
"""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np

from artclass_core import Intrinsics

from ._compiled import border_reach
from .support import as_uint8, border_band, label_box, region_mask

__all__ = ["limbs"]

#: A forearm's radius, from a robot's slim link (3 cm across) to a loose sleeve, metres.
FOREARM_RADIUS_M = (0.015, 0.06)
#: The shortest stretch of forearm that counts, metres (a hand alone is shorter).
FOREARM_MIN_M = 0.10
#: The stub that gives the first axis: the points within this distance of where the region enters.
STUB_M = 0.12
#: Points that spread this many times farther along their first direction than across it lie along
#: the axis; a shorter stub's axis is read from its normals.
ELONGATED = 3.0
#: A cylinder's points lie off the chord of its seen arc by at least this share of its radius
#: (between their 10th and 90th percentiles: 0.56 of it where half the cylinder is seen).
RELIEF = 0.3
#: A slab holds the points this near the axis (a loose sleeve's width): farther ones are other parts of
#: the region, not what the forearm meets.
NEAR_M = 2 * FOREARM_RADIUS_M[1]
#: The trace grows by slabs this thick along the axis.
SLAB_M = 0.02
#: A slab continues the cylinder when this share of its points lies within its radius.
INSIDE_SHARE = 0.7
#: The surface's roughness: a slab's points may lie this much beyond the radius, or three times the
#: stub's scatter about it (the sensor's noise), if more. A stub scattered more is no cylinder.
RADIUS_SLACK_M = 0.01
#: The hand beyond the forearm: this far along the axis (wrist to fingertips), within this radius.
HAND_REACH_M = 0.19
HAND_RADIUS_M = 0.05
#: The trace follows pixels this far apart on the surface, in x and y (at the region's median depth).
SAMPLE_M = 0.005
#: Normals from the points this far to either side (a forearm's surface turns little over it), each
#: the readings averaged over as many pixels: the sensor's noise (a dark sleeve under time of flight
#: reads centimetres off) would tilt normals from single readings by tens of degrees.
NORMAL_M = 0.01
#: The steepest surface averaged over: its depth changes by at most this many times the width it
#: spans (72 degrees from facing the camera); more is a step between two surfaces.
STEEPEST = 3.0
#: A region rests on the support plane when at least this many of its pixels come down to it (a line
#: of contact, not a stray reading).
CONTACT_PX = 3


def limbs(
    foreground: np.ndarray,
    depth_m: np.ndarray,
    intrinsics: Intrinsics,
    *,
    contact: np.ndarray,
) -> np.ndarray:
    """The forearms (and the hands beyond them) among the regions of ``foreground`` that reach the
    image border (see the module docstring).

    Parameters
    ----------
    foreground : ndarray of bool, shape (H, W) -- pixels standing out of the background, with a
        reading (depth steps included: a sleeve's cuff is a step between the sleeve and the wrist;
        the few readings that mix two surfaces lie off the cylinder)
    depth_m : ndarray, shape (H, W), metres, 0 = no reading
    intrinsics : pinhole intrinsics of the image
    contact : ndarray of bool, shape (H, W) -- the pixels on the support plane

    Returns
    -------
    ndarray of bool, shape (H, W)
    """
    out = np.zeros(foreground.shape, bool)
    n, labels, stats, box = label_box(foreground)
    if n < 2:
        return out
    runs, across, widest = _ways_in(
        foreground, depth_m, intrinsics.fx / float(np.median(depth_m[foreground]))
    )
    entering = np.flatnonzero(np.bincount(labels[runs[box] > 0], minlength=n)[1:]) + 1
    # the fewest pixels a forearm's least stretch covers, at the farthest reading
    least_px = (
        FOREARM_MIN_M * 2 * FOREARM_RADIUS_M[0] * (intrinsics.fx / max(float(depth_m.max()), 1e-3)) ** 2
    )
    for k in entering[stats[entering, cv2.CC_STAT_AREA] >= least_px]:
        region = region_mask(k, labels, stats, box, foreground.shape)
        v, u = np.nonzero(region)
        z = depth_m[v, u].astype(np.float64)
        px_per_m = intrinsics.fx / float(np.median(z))
        stride = max(int(SAMPLE_M * px_per_m), 1)
        sample = (u % stride == 0) & (v % stride == 0)
        traced = intrinsics.points(u[sample], v[sample], z[sample])
        apart = max(round(NORMAL_M * px_per_m), 1)
        smooth = _smoothed(region, depth_m, apart, intrinsics.fx)
        normals = _normals(region, smooth, intrinsics, v[sample], u[sample], apart)
        entries, points = runs[v, u], None
        for r in np.unique(entries[entries > 0]):  # each as wide as a forearm, at its own depth
            at = entries == r
            width_m = across[r] * float(np.median(z[at])) / intrinsics.fx
            if not 2 * FOREARM_RADIUS_M[0] <= width_m <= widest[r]:
                continue
            limb = _trace(traced, normals, intrinsics.points(u[at], v[at], z[at]).mean(axis=0))
            if limb is None:
                continue
            points = intrinsics.points(u, v, z) if points is None else points
            arm, hand = limb.split(points)
            if np.count_nonzero(contact[v[arm], u[arm]]) < CONTACT_PX:
                out[v[arm | hand], u[arm | hand]] = True
    return out


def _ways_in(
    foreground: np.ndarray, depth_m: np.ndarray, px_per_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where the regions of ``foreground`` come into view: the runs of their pixels along the picture's
    border, and along the gaps in the readings that reach it and are a forearm across
    (:data:`FOREARM_RADIUS_M`, at ``px_per_m``). An arm nearer than the sensor's range, or a black
    sleeve under time of flight, comes into view at its cuff, where its readings start; the readings
    along a gap are ragged, so a run there is the region's pixels within a forearm's radius of it.

    Returns the runs, each labelled apart (int32 (H, W), 0 = none); each run's width across, pixels
    (its bounding box's larger side); and the widest each may be, metres: a cuff at most twice a
    forearm across, while a forearm seen at a slant may cross the picture's border anywhere."""
    border = border_band(depth_m.shape)
    gap = as_uint8(depth_m <= 0)
    side = 2 * round(FOREARM_RADIUS_M[0] * px_per_m) + 1  # the slimmest forearm's diameter
    cuffs = np.zeros(gap.shape, bool)
    border_reach(cv2.erode(gap, np.ones((side, side), np.uint8)) > 0, cuffs)
    if cuffs.any():
        # the gap's own outline again, and a forearm's radius beyond it
        cuffs = cv2.dilate(as_uint8(cuffs), np.ones((2 * side - 1, 2 * side - 1), np.uint8)) > 0
    runs, across, widest = np.zeros(depth_m.shape, np.int32), [0], [0.0]
    for band, most in ((border, np.inf), (cuffs & ~border, 4 * FOREARM_RADIUS_M[1])):
        count, found, stats, box = label_box(foreground & band)
        runs[box][found > 0] = found[found > 0] + len(across) - 1
        across += list(stats[1:, 2:4].max(axis=1))
        widest += [most] * (count - 1)
    return runs, np.array(across), np.array(widest)


class _Limb(NamedTuple):
    """A traced forearm: its axis (a point and a unit direction into the picture), its radius, how far
    off it its points may lie (the surface's roughness and the sensor's noise), and where along the
    axis it starts and ends (metres)."""

    centre: np.ndarray
    direction: np.ndarray
    radius: float
    slack: float
    start: float
    end: float

    def split(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Which of ``points`` (N, 3) are the forearm, and which the hand beyond it: bool (N,) each."""
        along = (points - self.centre) @ self.direction
        across = np.linalg.norm(points - self.centre - along[:, None] * self.direction, axis=1)
        arm = (along >= self.start) & (along <= self.end) & (across <= self.radius + self.slack)
        hand = ~arm & (along > self.end - SLAB_M / 2) & (along <= self.end + HAND_REACH_M)
        return arm, hand & (across <= HAND_RADIUS_M)


def _normals(
    region: np.ndarray, depth_m: np.ndarray, intrinsics: Intrinsics, v: np.ndarray, u: np.ndarray, d: int
) -> np.ndarray:
    """The surface's unit normal at the pixels (``v``, ``u``) of ``region`` (bool (H, W)): the cross
    product of the differences between the points ``d`` pixels to either side, across and down; NaN
    where a neighbour is outside the region or the image. float (N, 3)."""
    h, w = region.shape

    def point(dv: int, du: int) -> np.ndarray:
        vv, uu = np.clip(v + dv, 0, h - 1), np.clip(u + du, 0, w - 1)
        z = np.where(region[vv, uu] & (vv == v + dv) & (uu == u + du), depth_m[vv, uu], np.nan)
        return intrinsics.points(uu, vv, z.astype(np.float64))

    normals = np.cross(point(0, d) - point(0, -d), point(d, 0) - point(-d, 0))
    return normals / np.linalg.norm(normals, axis=1, keepdims=True)


def _smoothed(region: np.ndarray, depth_m: np.ndarray, size: int, fx: float) -> np.ndarray:
    """The readings of ``region`` averaged over ``size`` x ``size`` pixels of it, where they span no
    depth step (at most :data:`STEEPEST` times the window's width on the surface); elsewhere, and
    off the region, the readings as they are. The sensor's noise, which tilts normals taken from
    single readings, shrinks by ``size``; a forearm in front of the object it passes keeps its own
    depth at its edge. ``fx``: the focal length, pixels."""
    out = np.array(depth_m, np.float32)
    x, y, w, h = cv2.boundingRect(as_uint8(region))
    inside, crop = region[y : y + h, x : x + w], out[y : y + h, x : x + w]
    readings = np.where(inside, crop, 0).astype(np.float32)
    kernel = np.ones((size, size), np.uint8)
    steady = cv2.medianBlur(readings, 5)  # the span of single readings is mostly the noise's
    far = cv2.dilate(np.where(inside, steady, 0), kernel)
    near = cv2.erode(np.where(inside, steady, np.inf).astype(np.float32), kernel)
    total = cv2.boxFilter(readings, -1, (size, size), normalize=False)
    count = cv2.boxFilter(inside.astype(np.float32), -1, (size, size), normalize=False)
    flat = inside & (far - near <= STEEPEST * size * crop / fx)
    crop[flat] = (total / np.maximum(count, 1))[flat]
    return out


def _trace(points: np.ndarray, normals: np.ndarray, start: np.ndarray) -> _Limb | None:
    """The forearm among ``points`` (N, 3), with surface ``normals`` (N, 3), that enters the picture
    at ``start`` (3,), or None."""
    taken = np.linalg.norm(points - start, axis=1) <= STUB_M
    slack = None
    while True:
        fit = _cylinder(points[taken], normals[taken], start)
        if fit is None:
            return None
        centre, direction, radius = fit
        along = (points - centre) @ direction
        across = np.linalg.norm(points - centre - along[:, None] * direction, axis=1)
        if slack is None:  # the stub lies on the cylinder's surface, give or take the sensor's noise
            scatter = 1.4826 * float(np.median(np.abs(across[taken] - radius)))
            if scatter > RADIUS_SLACK_M:
                return None
            slack = max(RADIUS_SLACK_M, 3 * scatter)
        end = float(along[taken].max())
        slab = ~taken & (along > end - SLAB_M / 2) & (along <= end + SLAB_M) & (across <= NEAR_M)
        inside = slab & (across <= radius + slack)
        if not slab.any() or np.count_nonzero(inside) < INSIDE_SHARE * np.count_nonzero(slab):
            break
        taken |= inside
    limb = _Limb(centre, direction, radius, slack, float(along[taken].min()), end)
    long = end - float((start - centre) @ direction) >= FOREARM_MIN_M
    return limb if long and FOREARM_RADIUS_M[0] <= radius <= FOREARM_RADIUS_M[1] else None


def _cylinder(
    points: np.ndarray, normals: np.ndarray, start: np.ndarray
) -> tuple[np.ndarray, np.ndarray, float] | None:
    """The cylinder through ``points`` (N, 3) with surface ``normals`` (N, 3): a point on its axis, the
    axis's direction (unit, pointing away from ``start``) and its radius; None when the points are
    too few, or lie on no cylinder. A cylinder's normals are all square to its axis: the axis is the
    direction in which they vary least (points spread :data:`ELONGATED` times farther along one
    direction than across it give the axis by their length instead). Across it, a circle is fitted
    to the points (Kasa's algebraic fit); the arc it shows must bulge off its chord (:data:`RELIEF`)."""
    if len(points) < 10:
        return None
    mean = points.mean(axis=0)
    spread, along = np.linalg.svd(points - mean, full_matrices=False)[1:]
    if spread[0] >= ELONGATED * spread[1]:  # a long stretch: the axis runs along it
        basis = along
    else:
        known = normals[np.isfinite(normals[:, 0])]
        basis = np.linalg.eigh(known.T @ known)[1].T  # smallest first: the axis, then across it
    direction = basis[0] if (mean - start) @ basis[0] >= 0 else -basis[0]
    a, b = ((points - mean) @ basis[1:].T).T
    (x, y, c), *_ = np.linalg.lstsq(
        np.column_stack([2 * a, 2 * b, np.ones_like(a)]), a * a + b * b, rcond=None
    )
    radius = float(np.sqrt(max(c + x * x + y * y, 0.0)))
    # a cylinder's cross-section is an arc that bulges off its chord by most of its radius; a flat
    # strip's is a line, off which only the sensor's noise takes it
    chord = np.linalg.svd(np.column_stack([a, b]), full_matrices=False)[2][1]
    if np.subtract(*np.quantile(a * chord[0] + b * chord[1], [0.9, 0.1])) < RELIEF * radius:
        return None
    return mean + x * basis[1] + y * basis[2], direction, radius
