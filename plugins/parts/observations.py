"""What a finished run gives the part finder: each pair's labelled points on its two frames, and
the frames' clouds, masks and noise."""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from artclass_core import ArtclassError, RunResult


@dataclass
class _Observation:
    """One pair's labelling of one frame: pixels (N, 2), points (N, 3, camera frame) and motion labels."""

    pair: int
    frame: int
    pixels: np.ndarray
    points: np.ndarray
    labels: np.ndarray
    forward: bool

    @functools.cached_property
    def counts(self) -> np.ndarray:
        """How many points each motion (by number) labels."""
        return np.bincount(self.labels[self.labels >= 0])

    @property
    def motions(self) -> np.ndarray:
        """The motions (numbers) that label some of the points."""
        return np.flatnonzero(self.counts)

    @functools.cached_property
    def keys(self) -> tuple[np.ndarray, np.ndarray]:
        """Each point's pixel as one number, and the order that sorts them (to find shared pixels)."""
        keys = self.pixels[:, 1].astype(np.int64) * 1_000_000 + self.pixels[:, 0]
        return keys, np.argsort(keys)


def _observations(result: RunResult) -> list[_Observation]:
    """Each labelled pair's labelling of its source frame and of its target frame."""
    clouds = {f.index: f.cloud for f in result.frames if f.cloud is not None}
    out = []
    for n, p in enumerate(result.pairs):
        if p.labels is None or not p.motions or p.decision == "skipped":
            continue
        seen = p.points
        if seen is not None:
            cut = seen.n_source
            sides = ((p.i, slice(0, cut), True), (p.j, slice(cut, len(seen.points)), False))
            for frame, part, forward in sides:
                out.append(
                    _Observation(n, frame, seen.pixels[part], seen.points[part], p.labels[part], forward)
                )
        elif p.i in clouds and clouds[p.i].pixels is not None:
            c = clouds[p.i]
            out.append(_Observation(n, p.i, c.pixels, c.points, p.labels[: len(c.points)], True))
        else:
            raise ArtclassError("finding parts needs each pair's labelled points: run with keep_clouds=True")
    return out


def _frame_clouds(
    result: RunResult, observations: list[_Observation]
) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Each frame's object pixels (N, 2) and points (N, 3, camera frame): the ones a pair labelled (a
    pair's source side first), else the frame's cloud."""
    out = {}
    for o in sorted(observations, key=lambda o: (o.frame, not o.forward)):
        out.setdefault(o.frame, (o.pixels, o.points))
    for f in result.frames:
        if f.index not in out and f.cloud is not None and f.cloud.pixels is not None:
            out[f.index] = (f.cloud.pixels, f.cloud.points)
    return out


def _mask(result: RunResult, frame: int) -> np.ndarray | None:
    """The frame's object mask; None for a frame whose cloud is not kept (no part image is made for it:
    a run without ``keep_clouds``, or the frames a live run has let go)."""
    cloud = result.frames[frame].cloud if frame < len(result.frames) else None
    if cloud is None:
        return None
    view = getattr(cloud, "view", None)
    if view is not None and view.mask is not None:
        return view.mask
    if view is not None:
        return np.zeros(view.gray.shape, bool)
    raise ArtclassError(f"frame {frame} has no image to segment: run with keep_clouds=True")


def _stride(result: RunResult, frame: int) -> int:
    return int(result.frames[frame].info.get("stride_px", 1) or 1)


def _has_depth(result: RunResult, frame: int) -> bool:
    cloud = result.frames[frame].cloud if frame < len(result.frames) else None
    view = getattr(cloud, "view", None)
    return view is not None and view.depth_m is not None


def _noise(result: RunResult) -> float:
    """The pairs' median depth noise, metres."""
    values = [p.points.noise_m for p in result.pairs if p.points is not None]
    return float(np.median(values)) if values else 0.0


def _spacing(result: RunResult) -> float:
    """The pairs' median spacing of the sampled points on the object (pixel size times the stride), metres."""
    values = [p.points.pixel_m * p.points.stride_px for p in result.pairs if p.points is not None]
    return float(np.median(values)) if values else 0.0
