"""The ``u2net`` segmenter: U^2-Net (u2netp) salient regions joined with the objects depth finds.

Saliency says *which* object a region belongs to, depth says *where* its pixels are. Per frame:

1. the objects that depth finds, as the ``depth_threshold`` segmenter finds them (what stands out of
   the scene's large planes, objects lying flat, hands and the gripper left out);
2. the u2netp foreground probability (class-agnostic; onnxruntime on the CPU), thresholded, hands
   left out; of the salient pixels that depth shows to be background, only those on the support
   plane that stand a little above it (their height averaged over ``THIN_WINDOW_PX`` squared pixels
   more than ``grow_sigmas`` times the noise of that mean) and, as a region, above the table around
   them (:func:`lying_flat`) are kept: a thin object lying flat, not a salient patch of the table;
3. a depth object that two salient regions claim, through pixels that meet in the image though
   their surfaces do not, is split between them (:func:`split_bridges`): a box, the keyboard
   behind it and a mug beside it are three objects, not one;
4. each connected salient region joins the depth objects it overlaps into one instance and adds its
   pixels that lie flat or belong to a depth object (:func:`join_salient`): a lid or lever that
   depth cut off is joined to its object, and an object lying flat that saliency alone finds is an
   instance of its own. Other salient pixels (what depth left out as too small: the rim of a hand,
   speckle) only connect.

The shared selection (:mod:`.selection`) picks the instance being manipulated.

Pre/post-processing (the model's own): RGB resized to 320 x 320, / 255, ImageNet mean
(0.485, 0.456, 0.406) and std (0.229, 0.224, 0.225), NCHW float32 into ``input.1``; the output
``1959`` (1 x 1 x 320 x 320) is already a sigmoid probability, resized back to the frame and
thresholded as is (no min-max normalisation, which would turn an empty scene into a full mask).

Weights: ``artclass models fetch u2netp`` puts them in the model cache (:mod:`.onnx_models`);
``model_path`` points at another file with the same signature (e.g. the larger u2net.onnx).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from artclass_core import Frame, Sequence, param

from . import onnx_models
from .depth_threshold import THIN_WINDOW_PX, DepthThresholdParams, DepthThresholdSegmenter
from .onnx_models import TensorSpec
from .selection import depth_edges
from .support import DEPTH_STEP_M, above_planes, label_regions

__all__ = [
    "U2netParams",
    "U2netSegmenter",
    "saliency",
    "load_u2net",
    "join_salient",
    "split_bridges",
    "lying_flat",
    "INPUT_SIZE",
]

INPUT_SIZE = 320
MEAN = np.array([0.485, 0.456, 0.406], np.float32)
STD = np.array([0.229, 0.224, 0.225], np.float32)
INPUTS = [TensorSpec("input.1", "tensor(float)", 4, (1, 3, INPUT_SIZE, INPUT_SIZE))]
OUTPUTS = [TensorSpec("1959", "tensor(float)", 4, (1, 1, INPUT_SIZE, INPUT_SIZE))]
# An object lying flat is told from the table by the table's height in a ring this wide around it.
RING_PX = 3


@dataclass(frozen=True)
class U2netParams(DepthThresholdParams):
    model_path: str = param(
        "",
        help="U^2-Net ONNX file; empty = the u2netp fetched into the model cache by "
        "`artclass models fetch u2netp`.",
    )
    threshold: float = param(
        0.5,
        unit="probability",
        bounds=(0.01, 0.99),
        help="Pixels whose foreground probability exceeds this are salient.",
    )


def load_u2net(model_path: str = ""):
    """The (cached) onnxruntime session of the U^2-Net model, its signature checked.

    Raises :class:`~artclass_core.PluginError` when the model is missing (naming the fetch command),
    fails its checksum, or does not have U^2-Net's signature.
    """
    path = onnx_models.resolve("u2netp", model_path)
    sess = onnx_models.session(str(path))
    onnx_models.check_signature(
        sess, inputs=INPUTS, outputs=OUTPUTS, what="U^2-Net (input.1 -> 1959)", path=path
    )
    return sess


def saliency(rgb: np.ndarray, *, session) -> np.ndarray:
    """U^2-Net foreground probability of an image.

    Parameters
    ----------
    rgb : ndarray, shape (H, W, 3), uint8, RGB order
    session : onnxruntime session of a U^2-Net model (see :func:`load_u2net`)

    Returns
    -------
    probability : ndarray, shape (H, W), float32 in [0, 1]
    """
    h, w = rgb.shape[:2]
    small = cv2.resize(rgb, (INPUT_SIZE, INPUT_SIZE), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0
    x = ((small - MEAN) / STD).transpose(2, 0, 1)[None].astype(np.float32)
    prob = session.run(["1959"], {"input.1": x})[0][0, 0]
    return cv2.resize(prob, (w, h), interpolation=cv2.INTER_LINEAR)


def lying_flat(
    salient: np.ndarray, height_m: np.ndarray, table: np.ndarray, *, noise_m: float, sigmas: float
) -> np.ndarray:
    """The salient regions on a plane that stand out of the plane around them: objects lying flat.

    A connected region (8-connected) of ``salient`` is kept when it has at least ``THIN_WINDOW_PX``
    squared pixels (the area over which a thin object is told from the table; a single reading one
    depth step above the table is noise) and its mean height above the plane
    exceeds that of the ``table`` pixels in a ring ``RING_PX`` wide around it by more than the
    plane's noise and by more than ``sigmas`` times the noise of that difference
    (``noise_m * sqrt(1/n + 1/m)`` over n pixels in the region and m in the ring). An object a few
    millimetres thick stands out on average though none of its single readings does; a salient
    patch of the table itself (a wood grain, a highlight) is at the height of the table around it,
    even where the fitted plane is off by a millimetre or two.

    Parameters
    ----------
    salient : ndarray of bool, shape (H, W) -- salient pixels on the plane, with a depth reading
    height_m : ndarray, shape (H, W), metres -- height above the plane (:func:`.support.plane_height_m`)
    table : ndarray of bool, shape (H, W) -- the plane's pixels with a reading (``salient`` included)
    noise_m : metres -- a single reading's noise on the plane

    Returns
    -------
    ndarray of bool, shape (H, W)
    """
    n, labels, stats, _ = cv2.connectedComponentsWithStats(salient.astype(np.uint8), connectivity=8)
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * RING_PX + 1, 2 * RING_PX + 1))
    rows, cols = salient.shape
    out = np.zeros(salient.shape, bool)
    for k in range(1, n):
        if stats[k, cv2.CC_STAT_AREA] < THIN_WINDOW_PX**2:
            continue
        x, y, w, h = stats[k, :4]
        box = np.s_[
            max(y - RING_PX, 0) : min(y + h + RING_PX, rows), max(x - RING_PX, 0) : min(x + w + RING_PX, cols)
        ]
        region = labels[box] == k
        ring = (cv2.dilate(region.view(np.uint8), disc) > 0) & table[box] & ~salient[box]
        if not ring.any():
            continue
        inside, around = height_m[box][region], height_m[box][ring]
        rise = float(inside.mean() - around.mean())
        if rise > noise_m and rise > sigmas * noise_m * np.sqrt(1 / len(inside) + 1 / len(around)):
            out[box] |= region
    return out


def split_bridges(
    instances: list[np.ndarray],
    salient: np.ndarray,
    depth_m: np.ndarray,
    *,
    step_m: float,
    min_area_fraction: float,
) -> list[np.ndarray]:
    """The depth instances that join two salient objects, split between them.

    Depth alone joins objects whose pixels meet in the image though their surfaces do not (a box
    in front of a keyboard, the keyboard behind a mug). An instance is cut into pieces at its depth
    edges (neighbouring readings more than ``step_m`` apart) and each piece is claimed by the
    connected salient region (8-connected) that covers most of it; a region whose pieces are
    smaller than ``min_area_fraction`` of the image together claims none. An instance is split when
    two or more salient regions claim pieces of one of its connected parts (8-connected): each such
    region gets its pixels of the instance and the pieces it claims (without the pixels of the
    other regions), and what is left that no region covers (a keyboard) is an instance of its own
    where it is at least ``min_area_fraction`` of the image. Other instances are unchanged, among
    them those whose parts depth joined across a gap (an object that a hand in front of it cuts in
    two, which a salient region cut by the same hand does not tell apart). Largest first.

    Parameters
    ----------
    instances : list of ndarray of bool, shape (H, W) -- the objects that depth finds
    salient : ndarray of bool, shape (H, W) -- the salient pixels that may belong to an object
    depth_m : ndarray, shape (H, W), metres, 0 = no reading
    step_m : metres -- neighbouring readings further apart than this are on surfaces that do not touch

    Returns
    -------
    list of ndarray of bool, shape (H, W)
    """
    n, labels = cv2.connectedComponents(salient.astype(np.uint8), connectivity=8)
    if n < 3:  # fewer than two salient regions: nothing to split between
        return instances
    edges = depth_edges(depth_m, step_m)
    least = max(1, int(np.ceil(min_area_fraction * salient.size)))
    out = []
    for mask in instances:
        count, pieces, stats = label_regions(mask & ~edges)
        # each piece's pixels per salient region (0 = not salient)
        overlap = np.bincount(pieces[mask] * n + labels[mask], minlength=count * n).reshape(count, n)
        owner = overlap[:, 1:].argmax(axis=1) + 1
        claimed = (2 * overlap[np.arange(count), owner] > stats[:, cv2.CC_STAT_AREA]) & (np.arange(count) > 0)
        # a region claims an object only with at least an instance's least area (not a fingertip
        # that the hand mask left out)
        area = np.bincount(owner[claimed], weights=stats[claimed, cv2.CC_STAT_AREA], minlength=n)
        claimed &= area[owner] >= least
        _, parts, _ = label_regions(mask)
        part_of = np.zeros(count, np.int32)
        part_of[pieces[mask]] = parts[mask]
        claims = np.unique(np.stack([part_of[claimed], owner[claimed]]), axis=1)
        if len(np.unique(claims[0])) == claims.shape[1]:  # one region or none per connected part
            out.append(mask)
            continue
        regions = np.unique(owner[claimed])
        for r in regions:
            own = np.isin(pieces, np.flatnonzero(claimed & (owner == r)))
            out.append(mask & (labels == r) | own & (labels == 0))
        rest = mask & ~np.isin(pieces, np.flatnonzero(claimed)) & (labels == 0)
        m, parts, part_stats = label_regions(rest)
        out += [parts == k for k in range(1, m) if part_stats[k, cv2.CC_STAT_AREA] >= least]
    return sorted(out, key=lambda x: -int(np.count_nonzero(x)))


def join_salient(
    instances: list[np.ndarray],
    salient: np.ndarray,
    *,
    min_area_fraction: float,
    usable: np.ndarray | None = None,
) -> list[np.ndarray]:
    """The depth instances joined with the salient regions that overlap them.

    Each connected salient region (8-connected) is one object: it joins every depth instance it
    overlaps (those instances become one), and adds its ``usable`` pixels to them. A salient region
    that overlaps no depth instance is an instance of its own when its usable pixels cover at least
    ``min_area_fraction`` of the image. Depth instances that no salient region overlaps stay as they
    are. Largest first.

    Parameters
    ----------
    instances : list of ndarray of bool, shape (H, W) -- the objects that depth finds
    salient : ndarray of bool, shape (H, W) -- the salient pixels that may belong to an object
    usable : ndarray of bool, shape (H, W), optional -- the salient pixels that may be added to an
        object (default: all); the others only connect

    Returns
    -------
    list of ndarray of bool, shape (H, W)
    """
    n, labels = cv2.connectedComponents(salient.astype(np.uint8), connectivity=8)
    # a graph of the depth instances (nodes 0 .. m - 1) and the salient regions 1 .. n - 1 (nodes
    # m .. m + n - 2), an edge where a region overlaps an instance; each connected part is one object
    m = len(instances)
    edges = np.array(
        [(j, m + r - 1) for j, mask in enumerate(instances) for r in np.unique(labels[mask]) if r], np.int64
    ).reshape(-1, 2)
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(m + n - 1, m + n - 1))
    count, group = connected_components(graph, directed=False)
    least = max(1, int(np.ceil(min_area_fraction * salient.size)))
    out = []
    for g in range(count):
        members = np.flatnonzero(group == g)
        mask = np.isin(labels, members[members >= m] - m + 1)
        if usable is not None:
            mask &= usable
        for j in members[members < m]:
            mask |= instances[j]
        if members[0] < m or np.count_nonzero(mask) >= least:
            out.append(mask)
    return sorted(out, key=lambda x: -int(np.count_nonzero(x)))


class U2netSegmenter(DepthThresholdSegmenter):
    """Salient objects (U^2-Net) joined with the objects depth finds, chosen by how they move."""

    name = "u2net"
    description = (
        "U^2-Net (u2netp) salient regions joined with depth objects, hands removed, moving instance chosen"
    )
    Params = U2netParams

    def instances(self, frame: Frame, *, sequence: Sequence) -> list[np.ndarray]:
        p = self.params
        found = super().instances(frame, sequence=sequence)
        scene = self.scene(frame, sequence=sequence)
        prob = saliency(frame.rgb, session=load_u2net(p.model_path))
        covered = self.covered(frame, sequence=sequence)
        allowed = np.ones(prob.shape, bool) if covered is None else ~covered
        salient = (prob > p.threshold) & allowed
        if scene.planes:  # salient regions a little above the support plane lie flat on it
            table = scene.valid & scene.background & (np.abs(scene.heights_m[0]) < p.plane_distance_m)
            raised = above_planes(
                scene.depth_m,
                sequence.intrinsics,
                scene.planes,
                params=p,
                sigmas=p.grow_sigmas,
                window_px=THIN_WINDOW_PX,
                heights=scene.heights_m,
            )
            noise_m = max(scene.planes[0].noise_m, DEPTH_STEP_M)
            flat = lying_flat(
                salient & table & raised, scene.heights_m[0], table, noise_m=noise_m, sigmas=p.grow_sigmas
            )
        else:
            flat = np.zeros(prob.shape, bool)
        salient &= ~scene.background | flat
        # the salient pixels added to objects: those lying flat and those of depth's objects; the
        # other foreground pixels (what depth left out as too small: speckle, the rim of a hand)
        # only connect
        usable = flat | np.logical_or.reduce(found, initial=False)
        found = split_bridges(
            found, salient, scene.depth_m, step_m=p.join_m, min_area_fraction=p.min_area_fraction
        )
        return join_salient(
            found, salient, min_area_fraction=p.min_area_fraction, usable=usable & scene.valid
        )
