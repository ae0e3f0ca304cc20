"""The data that flows through the pipeline. Units: metres, radians, seconds."""

from __future__ import annotations

import functools
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from .errors import InputError

Label = Literal["articulated", "rigid", "static"]
Decision = Literal["AM", "RM", "NM", "undecided", "skipped"]
LABELS: tuple[str, ...] = ("articulated", "rigid", "static")
#: What a pair can show: articulated motion, rigid motion, no motion. A pair no model explains is
#: ``undecided`` (shown, never counted as one of these); one that cannot be judged is ``skipped``.
DECISIONS: tuple[str, ...] = ("AM", "RM", "NM")


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of the depth camera, in pixels (depth registered to the colour image)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self):
        if not all(np.isfinite([self.fx, self.fy, self.cx, self.cy])) or self.fx <= 0 or self.fy <= 0:
            raise InputError(f"invalid intrinsics fx={self.fx} fy={self.fy} cx={self.cx} cy={self.cy}")

    def backproject(self, depth_m: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
        """Points of the valid (and masked) depth pixels.

        Parameters
        ----------
        depth_m : ndarray, shape (H, W), metres; 0 or NaN = no reading
        mask : ndarray of bool, shape (H, W), optional

        Returns
        -------
        points : ndarray, shape (N, 3), metres, camera frame (x right, y down, z forward)
        """
        valid = np.isfinite(depth_m) & (depth_m > 0)
        if mask is not None:
            valid &= mask
        v, u = np.nonzero(valid)
        return self.points(u, v, depth_m[v, u].astype(np.float64))

    def points(self, u: np.ndarray, v: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Points (N, 3) at pixel columns ``u``, rows ``v`` and depths ``z`` (m)."""
        return np.column_stack(((u - self.cx) * z / self.fx, (v - self.cy) * z / self.fy, z))

    def pixels(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel columns and rows (not rounded) where ``points`` (..., 3) project; inf or NaN where z <= 0."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return (
                self.fx * points[..., 0] / points[..., 2] + self.cx,
                self.fy * points[..., 1] / points[..., 2] + self.cy,
            )


@dataclass
class Frame:
    """One RGB-D frame. ``mask`` is the sequence's own object mask (ground truth or precomputed), if any."""

    index: int
    name: str
    rgb: np.ndarray  # (H, W, 3) uint8, RGB order
    depth_m: np.ndarray  # (H, W) float32, metres, 0 = no reading
    mask: np.ndarray | None = None  # (H, W) bool
    time_s: float | None = None


_reading = threading.local()


def reading_seconds() -> float:
    """Seconds this thread has spent reading frames from disk (:meth:`Sequence.load`), so far: a
    stage that reads frames (a segmenter comparing a frame with a later one) can tell reading apart
    from its own work."""
    return getattr(_reading, "seconds", 0.0)


class Sequence:
    """A lazily read RGB-D sequence. Readers subclass it and implement :meth:`load`.

    Frames are read on demand and only the last few are kept (``cache_frames``), so a long sequence
    is never held in memory at once.
    """

    cache_frames = 8
    #: The reader that opened the sequence and the reader parameters it was given (name, value pairs),
    #: so that a worker elsewhere opens it the same way; set by :func:`~artclass_core.open_sequences`.
    opened_with: tuple[str | None, tuple[tuple[str, str], ...]] = (None, ())

    def __init__(
        self,
        *,
        name: str,
        path: str | Path,
        intrinsics: Intrinsics,
        n_frames: int,
        label: str | None = None,
        object_name: str | None = None,
        has_masks: bool = False,
        accepted_labels: tuple[str, ...] | None = None,
        meta: dict[str, Any] | None = None,
    ):
        self.name = name
        self.path = Path(path)
        self.intrinsics = intrinsics
        self.n_frames = n_frames
        self.label = label
        self.object_name = object_name or name
        self.has_masks = has_masks
        # Labels counted as correct in evaluation (e.g. a rigid object the camera barely moves around
        # may rightly be called static); the first is the ground-truth label.
        self.accepted_labels = accepted_labels or ((label,) if label else ())
        self.meta = dict(meta or {})
        self.frame = functools.lru_cache(maxsize=self.cache_frames)(self._checked_load)

    def __len__(self) -> int:
        return self.n_frames

    def __getitem__(self, i: int) -> Frame:
        return self.frame(i)

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.name!r}: {self.n_frames} frames from {self.path}>"

    def forget_frames(self) -> None:
        """Drop the frames kept in memory; they are read again when next asked for. Call it when done
        with a sequence that stays open, as an evaluation of many sequences does with each."""
        self.frame.cache_clear()

    def load(self, i: int) -> Frame:
        """Read frame ``i`` from disk. Raise :class:`InputError` naming the file on bad data."""
        raise NotImplementedError

    def pair_truth(self, i: int, j: int) -> Decision | None:
        """Ground-truth motion between frames i and j (``AM``, ``RM``, ``NM``), or None if unknown."""
        return None

    def pair_truth_legacy(self, i: int, j: int) -> Decision | None:
        """The earlier joint-state definition of the pair truth, where a reader still has it (reported
        beside ``pair_truth`` for comparison), or None."""
        return None

    def _checked_load(self, i: int) -> Frame:
        if not 0 <= i < self.n_frames:
            raise IndexError(f"frame {i} out of range 0..{self.n_frames - 1}")
        t0 = time.perf_counter()
        frame = self.load(i)
        _reading.seconds = reading_seconds() + time.perf_counter() - t0
        shape = (self.intrinsics.height, self.intrinsics.width)
        for what, image in (("depth", frame.depth_m), ("colour", frame.rgb), ("mask", frame.mask)):
            if image is not None and image.shape[:2] != shape:
                raise InputError(
                    f"{what} image of frame {frame.name} is {image.shape[1]}x{image.shape[0]}, "
                    f"expected {shape[1]}x{shape[0]} (depth and RGB must have the same size)",
                    path=self.path,
                )
        return frame


@dataclass
class View:
    """The image a cloud was measured in, for image-space evidence (optical flow) between two frames."""

    gray: np.ndarray  # (H, W) uint8 intensity of the whole frame
    depth_m: np.ndarray  # (H, W) float32, metres, 0 outside the object's (eroded) mask
    intrinsics: Intrinsics
    scene_depth_m: np.ndarray | None = None  # (H, W) float32, metres: the whole frame's depth (0 = none)
    mask: np.ndarray | None = None  # (H, W) bool: the segmenter's object mask, before any erosion
    normals: np.ndarray | None = None  # (H, W, 3) float32 unit normals of depth_m's pixels (0 = none)
    covered: np.ndarray | None = None  # (H, W) bool: pixels a hand may cover (Segmenter.covered)


@dataclass
class Cloud:
    """A preprocessed object point cloud of one frame."""

    frame_index: int
    points: np.ndarray  # (N, 3) float64, metres, camera frame
    normals: np.ndarray | None = None  # (N, 3) unit vectors towards the camera
    info: dict[str, Any] = field(default_factory=dict)  # resolved v, r, diameter, counts ...
    colors: np.ndarray | None = None  # (N, 3) float RGB in [0, 1], if the preprocessor keeps colour
    view: View | None = None  # the frame's image, if the preprocessor keeps it
    pixels: np.ndarray | None = None  # (N, 2) int (column, row) of each point, for an image-space cloud

    def __len__(self) -> int:
        return len(self.points)


@dataclass
class Registration:
    """Result of registering one cell: ``T_target_from_source`` maps source points onto the target."""

    T_target_from_source: np.ndarray  # (4, 4)
    fitness: float  # fraction of source points with a correspondence
    rmse_m: float  # RMS distance of the correspondences
    n_correspondences: int


@dataclass
class CellMotion:
    """One grid cell of a frame pair and what happened to it."""

    cell: tuple[int, int, int]
    centre_m: np.ndarray  # (3,) cell centre
    source_idx: np.ndarray  # indices into the source cloud
    target_idx: np.ndarray  # indices into the target cloud
    registration: Registration | None = None
    skipped: str | None = None  # why the cell does not take part, or None
    cluster: int | None = None  # motion cluster / hash key index the rule put it in
    key: str | None = None  # the rule's readable key of that cluster

    @property
    def matched(self) -> bool:
        return self.registration is not None and self.skipped is None

    def to_dict(self) -> dict[str, Any]:
        from .geometry import quaternion_wxyz, rotation_angle_rad

        d: dict[str, Any] = dict(
            cell=list(self.cell),
            centre_m=_floats(self.centre_m),
            n_source=int(len(self.source_idx)),
            n_target=int(len(self.target_idx)),
            skipped=self.skipped,
            cluster=self.cluster,
            key=self.key,
        )
        reg = self.registration
        if reg is not None:
            T = reg.T_target_from_source
            d.update(
                fitness=float(reg.fitness),
                rmse_m=float(reg.rmse_m),
                n_correspondences=int(reg.n_correspondences),
                quaternion_wxyz=_floats(quaternion_wxyz(T[:3, :3])),
                translation_m=_floats(T[:3, 3]),
                rotation_deg=float(np.degrees(rotation_angle_rad(T[:3, :3]))),
                centre_displacement_m=_floats(T[:3, :3] @ self.centre_m + T[:3, 3] - self.centre_m),
            )
        return d


#: What a moved point finds at the target pixel it projects onto (:class:`MotionEvidence` ``status``).
SURFACE, OCCLUDED, FREE_SPACE, OFF_OBJECT, UNSEEN = range(5)
STATUS_NAMES = ("surface", "occluded", "free space", "off object", "unseen")


@dataclass
class MotionEvidence:
    """A pair's rigid-motion hypotheses and how well each explains every source point.

    Made by a pair registrar (:class:`~artclass_core.interfaces.PairRegistrar`) and read by a rule
    that decides from motions. Nothing in it depends on a decision threshold, so a rule can be run
    again under other thresholds from the same evidence.

    Attributes
    ----------
    motions : ndarray, shape (H, 4, 4)
        ``T_target_from_source`` of each hypothesis; the first is the identity.
    names : list of str, length H
        Where each hypothesis came from (``identity``, ``object``, ``cell 3``, ``refit 1`` ...).
    residual_m : ndarray, shape (H, N), float32, metres
        Distance of each moved source point to the target surface along its normal, where the point
        lands on the object's surface (``status == SURFACE``); NaN elsewhere.
    status : ndarray, shape (H, N), int8
        What the moved point finds at its target pixel: ``SURFACE`` (a surface within reach),
        ``OCCLUDED`` (something in front of it, or a hand the segmenter left out of the object's
        mask there: no evidence), ``FREE_SPACE`` (the camera sees past where the point should be:
        evidence against the motion), ``OFF_OBJECT`` (a surface at the right depth that is not the
        object), ``UNSEEN`` (out of the image or no depth).
    flow_px : ndarray, shape (H, N), float32, pixels
        Distance between where the motion puts a point in the target image and where optical flow
        says it went; NaN where the colour image has no texture to follow.
    noise_m : float
        The depth noise measured on the pair (robust spread of the best motion's residuals).
    points : ndarray, shape (N, 3), metres
        The source points the evidence is about.
    pixels : ndarray, shape (N, 2), int
        Their (column, row) in the source image.
    pixel_m : float
        The size of one pixel on the object (median depth / focal length), metres.
    n_source : int or None
        When set, only ``points[:n_source]`` are source points; the rest are target points judged the
        other way (moved by each motion's inverse onto the source image), so that a surface the
        motion says should have come from nowhere counts against it too. ``pixels`` of those are in
        the target image.
    landing_grey : ndarray, shape (H, N), float32, grey levels, or None
        Where a motion and the optical flow disagree by more than the default rule counts as a miss
        (``noise_factor`` times ``flow_sigma_px``), how unlike the source's texture the texture is
        where the motion lands the point (mean absolute difference of the two windows); NaN
        elsewhere. ``info["flow_grey"]`` holds the median and robust spread of the same difference at
        the flow's own matches. A motion that lands a point on texture as like the source's as the
        flow's matches are (stripes a period off, a stripe followed along itself) cannot be told from
        the flow's by that texture.
    scene_error_m : ndarray, shape (N,), float32, metres, or None
        How much the depth of the still scene about each point changed between the two frames: the
        sensor's own error there (a time-of-flight camera's multipath near a passing hand), which no
        motion need explain. None when nothing about the object was seen still (a moving camera).
    """

    motions: np.ndarray
    names: list[str]
    residual_m: np.ndarray
    status: np.ndarray
    flow_px: np.ndarray
    noise_m: float
    points: np.ndarray
    pixels: np.ndarray
    pixel_m: float
    info: dict[str, Any] = field(default_factory=dict)
    n_source: int | None = None
    landing_grey: np.ndarray | None = None
    scene_error_m: np.ndarray | None = None

    @property
    def forward(self) -> np.ndarray:
        """Which points are source points (judged from the source image onto the target's)."""
        out = np.zeros(len(self.points), bool)
        out[: len(self.points) if self.n_source is None else self.n_source] = True
        return out

    @property
    def stride_px(self) -> int:
        """The points' grid step, pixels (the registrar's ``info["stride_px"]``; 1 when not given)."""
        return int(self.info.get("stride_px", 1))


@dataclass(frozen=True)
class PairPoints:
    """A pair's labelled points without the evidence they were judged on (a few hundred kB a pair,
    against megabytes): what tracking parts over the whole video needs of each pair.

    Attributes
    ----------
    pixels : ndarray, shape (N, 2), int: each point's (column, row); the first ``n_source`` in frame i,
        the rest in frame j
    points : ndarray, shape (N, 3), metres, each in its own frame's camera coordinates
    n_source : int
    noise_m : float, the pair's depth noise
    pixel_m : float, one pixel on the object, metres
    stride_px : int, the points' grid step
    """

    pixels: np.ndarray
    points: np.ndarray
    n_source: int
    noise_m: float
    pixel_m: float
    stride_px: int

    @classmethod
    def of(cls, ev: MotionEvidence) -> PairPoints:
        return cls(ev.pixels, ev.points, int(ev.forward.sum()), ev.noise_m, ev.pixel_m, ev.stride_px)


@dataclass
class Motion:
    """One rigid motion a rule selected for a pair, and the source points it moves."""

    T_target_from_source: np.ndarray  # (4, 4)
    name: str
    n_points: int
    displacement_m: float  # median displacement of its points

    def to_dict(self) -> dict[str, Any]:
        from .geometry import rotation_angle_rad

        T = self.T_target_from_source
        return dict(
            name=self.name,
            n_points=self.n_points,
            displacement_m=round(float(self.displacement_m), 6),
            rotation_deg=round(float(np.degrees(rotation_angle_rad(T[:3, :3]))), 4),
            T_target_from_source=[_floats(row) for row in T],
        )


@dataclass
class PairResult:
    """The decision for the frame pair (i, j): j = i + k, or i + slow_factor k for a slow motion; and the
    cells or motions behind it."""

    i: int
    j: int
    decision: Decision
    reason: str = ""  # why a pair was skipped, or the rule's short explanation
    cells: list[CellMotion] = field(default_factory=list)
    cell_size_m: float | None = None
    info: dict[str, Any] = field(default_factory=dict)  # rule-specific evidence (JSON-ready)
    truth: Decision | None = None
    motions: list[Motion] = field(
        default_factory=list
    )  # the selected motions (rules that decide from motions)
    labels: np.ndarray | None = None  # (N,) int: each evidence point's motion (index into motions), -1 = none
    evidence: MotionEvidence | None = field(default=None, repr=False)  # what the motions were selected from
    # the points that ``labels`` label; kept when the evidence is dropped, for the parts over the video
    points: PairPoints | None = field(default=None, repr=False)
    # the rule's scratch space for this pair (DecisionRule.uses_scratch); not part of the result's JSON
    scratch: dict[Any, Any] = field(default_factory=dict, repr=False, compare=False)
    # The pair of the same frame i over the other baseline, when both were registered (the pipeline's
    # slow_factor): the pair (i, i + k) that showed no motion, when this longer pair replaced it because
    # it shows one; or, on a pair (i, i + k) without motion, the longer pair, which showed none either.
    other: PairResult | None = field(default=None, repr=False)

    def __post_init__(self):
        if self.points is None and self.evidence is not None:
            self.points = PairPoints.of(self.evidence)

    def release(self) -> None:
        """Let go of the motion evidence and the rule's scratch, of this pair and of :attr:`other` (the
        labelled points stay in :attr:`points`): a run that keeps no clouds cannot re-decide it."""
        for p in (self, self.other) if self.other is not None else (self,):
            p.evidence, p.scratch = None, {}

    def to_dict(self, *, cells: bool = True) -> dict[str, Any]:
        d = dict(
            i=self.i,
            j=self.j,
            decision=self.decision,
            reason=self.reason,
            truth=self.truth,
            cell_size_m=self.cell_size_m,
            n_cells=len(self.cells),
            n_matched=sum(c.matched for c in self.cells),
            info=self.info,
        )
        if self.motions:
            d["motions"] = [m.to_dict() for m in self.motions]
        if cells:
            d["cells"] = [c.to_dict() for c in self.cells]
        if self.other is not None:
            d["other"] = self.other.to_dict(cells=False)
        return d


@dataclass
class FrameResult:
    """What segmentation and preprocessing made of one frame."""

    index: int
    name: str
    cloud: Cloud | None  # dropped after use in a streaming run; ``info`` stays
    skipped: str | None = None
    mask_pixels: int = 0
    info: dict[str, Any] = field(default_factory=dict)  # the preprocessor's resolved values and counts

    def to_dict(self) -> dict[str, Any]:
        return dict(
            index=self.index, name=self.name, skipped=self.skipped, mask_pixels=self.mask_pixels, **self.info
        )


@dataclass
class RunResult:
    """Everything one run produced, with the parameters and plugins that produced it."""

    sequence: dict[str, Any]  # name, path, object, n_frames, truth label
    label: Label
    fractions: dict[str, float]  # share of decided pairs that are AM / RM / NM
    pairs: list[PairResult]
    filtered: list[Decision]  # decisions after the moving max-count filter (decided pairs only)
    frames: list[FrameResult]
    params: dict[str, dict[str, Any]]  # kind -> {name: value}
    plugins: dict[str, str]  # kind -> plugin name
    timing_s: dict[str, float]
    version: str = ""
    reason: str = ""  # why the video has its label

    def to_dict(self, *, cells: bool = True) -> dict[str, Any]:
        return dict(
            version=self.version,
            sequence=self.sequence,
            label=self.label,
            reason=self.reason,
            fractions=self.fractions,
            filtered=self.filtered,
            params=self.params,
            plugins=self.plugins,
            timing_s=self.timing_s,
            frames=[f.to_dict() for f in self.frames],
            pairs=[p.to_dict(cells=cells) for p in self.pairs],
        )


def _floats(a) -> list[float]:
    return [float(v) for v in np.asarray(a).ravel()]
