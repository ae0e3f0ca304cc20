"""The YCB-Video layout, exactly as the dataset ships it.

::

    NNNN/                         one scene (a video)
        NNNNNN-color.png          8-bit colour
        NNNNNN-depth.png          16-bit depth; metres = value / factor_depth
        NNNNNN-label.png          8-bit per-pixel object id (0 = background, 1..21, see CLASSES)
        NNNNNN-meta.mat           MATLAB file: intrinsic_matrix (3x3), factor_depth, cls_indexes (ids
                                  present), poses (3x4xN, camera_from_object of each id in cls_indexes)
        NNNNNN-box.txt            2-D boxes (not used)

One scene holds several objects; the reader gives one sequence per object, named
``NNNN/<class>`` (e.g. ``0000/025_mug``), with mask ``label == id``.

Ground truth. The YCB-Video objects stand still on a table while the camera moves, so every
sequence is labelled ``rigid`` with ``static`` accepted too (the data README: a correct classifier
never calls them articulated). The per-pair truth is taken honestly from the annotated poses: the
object's motion *relative to the camera* between frames i and j, which is the motion a camera-frame
classifier sees. A camera that moves a few millimetres therefore makes pairs ``RM`` once the object
moved more than ``move_eps_m`` (or turned more than ``turn_eps_rad``) in the camera frame, and
``NM`` below that; never ``AM``.

Object ids are collected from the ``cls_indexes`` of the first, middle and last frame's meta.mat
(a YCB-Video scene keeps its objects throughout; reading every meta.mat of a 2000-frame scene up
front would take seconds). A frame in which an object is absent has an empty mask and is skipped.
"""

from __future__ import annotations

import os
import re
import zlib
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from artclass_core import Frame, InputError, Intrinsics, Params, Reader, Sequence, param
from artclass_core.io import read_depth, read_label, read_rgb

from .folder import pair_truth_from_states

# Class order of YCB-Video (ids 1..21), as in the dataset's classes.txt.
CLASSES: tuple[str, ...] = (
    "002_master_chef_can",
    "003_cracker_box",
    "004_sugar_box",
    "005_tomato_soup_can",
    "006_mustard_bottle",
    "007_tuna_fish_can",
    "008_pudding_box",
    "009_gelatin_box",
    "010_potted_meat_can",
    "011_banana",
    "019_pitcher_base",
    "021_bleach_cleanser",
    "024_bowl",
    "025_mug",
    "035_power_drill",
    "036_wood_block",
    "037_scissors",
    "040_large_marker",
    "051_large_clamp",
    "052_extra_large_clamp",
    "061_foam_brick",
)
FRAME_RE = re.compile(r"^(\d{6})-meta\.mat$")
PARTS = ("color", "depth", "label", "meta")


def class_name(object_id: int) -> str:
    """YCB-Video class name of an object id (1..21); ``obj_<id>`` for an id outside the table."""
    return CLASSES[object_id - 1] if 1 <= object_id <= len(CLASSES) else f"obj_{object_id}"


def read_meta(path: Path, names: tuple[str, ...]) -> dict[str, np.ndarray]:
    """Variables ``names`` of a YCB-Video ``meta.mat`` (only those are decoded).

    Raises :class:`InputError` naming the file when it is missing, unreadable or lacks one of them.
    """
    import scipy.io

    path = Path(path)
    if not path.is_file():
        raise InputError("file not found", path=path)
    try:
        data = scipy.io.loadmat(str(path), variable_names=list(names))
    except (ValueError, TypeError, OSError, NotImplementedError, zlib.error) as exc:
        raise InputError(f"unreadable MATLAB file ({exc})", path=path) from None
    missing = [n for n in names if n not in data]
    if missing:
        raise InputError(f"missing {', '.join(map(repr, missing))} in meta.mat", path=path)
    return data


def intrinsics_from_meta(meta: dict, *, path: Path, width: int, height: int) -> tuple[Intrinsics, float]:
    """:class:`Intrinsics` and depth units per metre from a meta.mat's ``intrinsic_matrix`` and ``factor_depth``."""
    K = np.asarray(meta["intrinsic_matrix"], dtype=float)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise InputError(f"'intrinsic_matrix' must be a finite 3x3 matrix, got shape {K.shape}", path=path)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if fx <= 0 or fy <= 0:
        raise InputError(
            f"'intrinsic_matrix' has fx={fx:g}, fy={fy:g}; focal lengths must be positive", path=path
        )
    factor = np.asarray(meta["factor_depth"], dtype=float).ravel()
    if factor.size != 1 or not np.isfinite(factor[0]) or factor[0] <= 0:
        raise InputError(f"'factor_depth' must be one positive number, got {factor.tolist()}", path=path)
    return Intrinsics(float(fx), float(fy), float(cx), float(cy), width=width, height=height), float(
        factor[0]
    )


@dataclass(frozen=True)
class YcbvParams(Params):
    move_eps_m: float = param(
        0.002,
        unit="m",
        bounds=(0.0, 1.0),
        help="Pair truth: the object moved (RM) when a point 10 cm from its origin moved "
        "more than this relative to the camera between the two frames.",
    )
    turn_eps_rad: float = param(
        float(np.radians(0.5)),
        unit="rad",
        bounds=(0.0, np.pi),
        help="Pair truth: the object moved (RM) when it turned more than this relative "
        "to the camera between the two frames.",
    )


class YcbvScene:
    """The frames of one scene folder, shared by the per-object sequences (meta.mat read lazily, cached)."""

    def __init__(self, path: Path, stems: list[str]):
        self.path = path
        self.stems = stems
        self.meta = lru_cache(maxsize=64)(self._meta)

    def file(self, i: int, part: str) -> Path:
        return self.path / f"{self.stems[i]}-{part}.{'mat' if part == 'meta' else 'png'}"

    def _meta(self, i: int) -> dict:
        return read_meta(self.file(i, "meta"), ("intrinsic_matrix", "factor_depth", "cls_indexes", "poses"))

    def ids(self, i: int) -> list[int]:
        return [int(v) for v in np.asarray(self.meta(i)["cls_indexes"]).ravel()]

    def pose(self, i: int, object_id: int) -> np.ndarray | None:
        """4x4 camera_from_object of ``object_id`` in frame i, or None when it is not annotated there."""
        meta = self.meta(i)
        ids = self.ids(i)
        if object_id not in ids:
            return None
        poses = np.asarray(meta["poses"], dtype=float)
        if poses.ndim == 2:  # a single object: MATLAB drops the trailing dimension
            poses = poses[:, :, None]
        k = ids.index(object_id)
        if poses.shape[:2] != (3, 4) or k >= poses.shape[2]:
            raise InputError(
                f"'poses' has shape {poses.shape}, expected 3x4x{len(ids)}", path=self.file(i, "meta")
            )
        T = np.eye(4)
        T[:3] = poses[:, :, k]
        return T


class YcbvSequence(Sequence):
    """One object of a YCB-Video scene."""

    def __init__(
        self,
        scene: YcbvScene,
        object_id: int,
        *,
        intrinsics: Intrinsics,
        factor_depth: float,
        params: YcbvParams,
    ):
        name = class_name(object_id)
        super().__init__(
            name=f"{scene.path.name}/{name}",
            path=scene.path,
            intrinsics=intrinsics,
            n_frames=len(scene.stems),
            label="rigid",
            object_name=name,
            has_masks=True,
            accepted_labels=("rigid", "static"),
            meta=dict(
                dataset="ycbv",
                object_id=object_id,
                depth_units_per_metre=factor_depth,
                truth="object pose relative to the camera (meta.mat poses)",
            ),
        )
        self.scene, self.object_id, self.params = scene, object_id, params

    def load(self, i: int) -> Frame:
        scene = self.scene
        meta = scene.meta(i)
        intr, factor = intrinsics_from_meta(
            meta, path=scene.file(i, "meta"), width=self.intrinsics.width, height=self.intrinsics.height
        )
        if not np.allclose(
            [intr.fx, intr.fy, intr.cx, intr.cy],
            [self.intrinsics.fx, self.intrinsics.fy, self.intrinsics.cx, self.intrinsics.cy],
            rtol=1e-6,
            atol=1e-6,
        ):
            raise InputError(
                "intrinsic_matrix differs from the first frame's; one sequence needs one camera",
                path=scene.file(i, "meta"),
            )
        rgb = read_rgb(scene.file(i, "color"))
        depth = read_depth(scene.file(i, "depth"), units_per_metre=factor)
        label = read_label(scene.file(i, "label"))
        for part, what, image in (("color", "colour", rgb), ("label", "label", label)):
            if image.shape[:2] != depth.shape:
                raise InputError(
                    f"{what} image is {image.shape[1]}x{image.shape[0]} but the depth image is "
                    f"{depth.shape[1]}x{depth.shape[0]}",
                    path=scene.file(i, part),
                )
        return Frame(i, scene.stems[i], rgb, depth, label == self.object_id)

    def pair_truth(self, i: int, j: int) -> str | None:
        pose_i, pose_j = self.scene.pose(i, self.object_id), self.scene.pose(j, self.object_id)
        if pose_i is None or pose_j is None:
            return None
        return pair_truth_from_states(
            None,
            None,
            pose_i,
            pose_j,
            joint_eps=np.inf,
            move_eps_m=self.params.move_eps_m,
            turn_eps_rad=self.params.turn_eps_rad,
        )


class YcbvReader(Reader):
    """Reads a YCB-Video scene folder (see module docstring): one sequence per object."""

    name = "ycbv"
    description = (
        "YCB-Video scene folder NNNN/ with NNNNNN-{color,depth,label}.png + meta.mat; one sequence per object"
    )
    Params = YcbvParams

    def sequences(self, path: Path) -> list[Sequence]:
        path = Path(path)
        if not path.is_dir():
            return []
        try:
            names = [e.name for e in os.scandir(path)]
        except OSError:
            return []
        stems = sorted(m.group(1) for m in map(FRAME_RE.match, names) if m)
        if not stems or not any(n.endswith("-color.png") for n in names):
            return []
        present = set(names)
        for stem in stems:
            for part in PARTS:
                fname = f"{stem}-{part}.{'mat' if part == 'meta' else 'png'}"
                if fname not in present:
                    raise InputError(f"frame {stem} has no {fname}", path=path / fname)
        scene = YcbvScene(path, stems)
        depth0 = read_depth(scene.file(0, "depth"), units_per_metre=1.0)
        intr, factor = intrinsics_from_meta(
            scene.meta(0), path=scene.file(0, "meta"), width=depth0.shape[1], height=depth0.shape[0]
        )
        ids: set[int] = set()
        for i in sorted({0, len(stems) // 2, len(stems) - 1}):
            ids.update(scene.ids(i))
        return [
            YcbvSequence(scene, oid, intrinsics=intr, factor_depth=factor, params=self.params)
            for oid in sorted(ids)
        ]
