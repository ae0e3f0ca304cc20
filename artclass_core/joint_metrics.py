"""How close a joint estimate is to the truth: type, axis direction and position, state, part masks.

Every function takes plain arrays in the parent's frame (metres, radians), so the evaluation can
compare any estimator with any ground truth.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment


def joint_type_accuracy(true_types, estimated_types) -> float:
    """Share of joints whose estimated type is the true one (0 to 1; NaN for no joint)."""
    true_types, estimated_types = list(true_types), list(estimated_types)
    if len(true_types) != len(estimated_types):
        raise ValueError(f"{len(true_types)} true joint types but {len(estimated_types)} estimated")
    if not true_types:
        return float("nan")
    return sum(t == e for t, e in zip(true_types, estimated_types)) / len(true_types)


def _unit(v) -> np.ndarray:
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


def axis_direction_error_rad(true_direction, estimated_direction, *, sign_invariant: bool = True) -> float:
    """Angle between two axis directions (3,), radians.

    With ``sign_invariant`` (a revolute axis: u and -u are the same hinge, with the state's sign
    flipped) the angle is at most pi / 2.
    """
    cos = float(_unit(true_direction) @ _unit(estimated_direction))
    return float(np.arccos(np.clip(abs(cos) if sign_invariant else cos, -1.0, 1.0)))


def axis_position_error_m(
    true_point_m, true_direction, estimated_point_m, estimated_direction, *, at_m
) -> float:
    """Distance between the true and the estimated axis lines, measured at the part, metres.

    Parameters
    ----------
    true_point_m, estimated_point_m : ndarray, shape (3,), metres: a point on each axis
    true_direction, estimated_direction : ndarray, shape (3,)
    at_m : ndarray, shape (3,), metres: a point of the part (e.g. its centroid); it is projected on the
        true axis and the distance from there to the estimated axis is returned. Two lines that cross
        at an angle are far apart away from the crossing, so the place matters.
    """
    d_true, d_est = _unit(true_direction), _unit(estimated_direction)
    at_on_true = np.asarray(true_point_m, float) + d_true * float(
        (np.asarray(at_m, float) - true_point_m) @ d_true
    )
    offset = at_on_true - np.asarray(estimated_point_m, float)
    return float(np.linalg.norm(offset - d_est * float(offset @ d_est)))


def state_error(true_states, estimated_states, *, same_direction: bool = True) -> float:
    """Median absolute difference of two state series (N,) after aligning their zeros (radians or metres).

    The zero of a state is arbitrary (the first frame seen), so the estimate is shifted by the median
    difference over the frames where both are known. ``same_direction=False`` when the estimated axis
    points the other way from the true one (the estimate's states are then negated first).
    NaN when no frame has both.
    """
    true_states = np.asarray(true_states, float)
    estimated_states = np.asarray(estimated_states, float) * (1.0 if same_direction else -1.0)
    both = np.isfinite(true_states) & np.isfinite(estimated_states)
    if not both.any():
        return float("nan")
    difference = estimated_states[both] - true_states[both]
    return float(np.median(np.abs(difference - np.median(difference))))


def mask_iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two boolean masks (0 when both are empty)."""
    union = np.count_nonzero(a | b)
    return np.count_nonzero(a & b) / union if union else 0.0


def part_iou(
    true_labels: np.ndarray, estimated_labels: np.ndarray, *, background: int = 0
) -> dict[int, float]:
    """IoU of each true part with the estimated part matched to it, from two label images (H, W).

    Estimated labels are arbitrary numbers: each true part is matched one-to-one to the estimated part
    that maximises the total IoU (Hungarian assignment). A true part left unmatched scores 0. Pixels
    labelled ``background`` in either image belong to no part.
    """
    true_labels, estimated_labels = np.asarray(true_labels), np.asarray(estimated_labels)
    if true_labels.shape != estimated_labels.shape:
        raise ValueError(f"label images differ in shape: {true_labels.shape} and {estimated_labels.shape}")
    true_ids = [int(k) for k in np.unique(true_labels) if k != background]
    est_ids = [int(k) for k in np.unique(estimated_labels) if k != background]
    iou = np.array([[mask_iou(true_labels == t, estimated_labels == e) for e in est_ids] for t in true_ids])
    scores = {t: 0.0 for t in true_ids}
    if iou.size:
        rows, cols = linear_sum_assignment(iou, maximize=True)
        scores.update({true_ids[r]: float(iou[r, c]) for r, c in zip(rows, cols)})
    return scores


def _matched_parts(
    articulation, true_labels: dict[int, np.ndarray]
) -> tuple[dict[int, int], list[list[float]], list[list[float]]]:
    """Estimated part -> true part (both numbered from 0), matched once for the whole video by the
    total intersection over union (Hungarian) over the frames with a part image, and the IoU of every
    true part shown in a frame (the matched estimate's, 0 for an unmatched true part), per frame: over
    the frames whose part image shows a moving part, and over every frame of ``true_labels`` (a frame
    without a part image scores 0)."""
    images = {f: (np.asarray(t), articulation.label_image(f)) for f, t in sorted(true_labels.items())}
    estimated = {f: pair for f, pair in images.items() if pair[1] is not None}
    n_est = len(articulation.parts)
    n_true = 1 + max((int(t.max()) for t, _ in images.values()), default=0)
    inter, union = np.zeros((n_true, n_est)), np.zeros((n_true, n_est))
    for truth, est in estimated.values():
        for t in range(n_true):
            for e in range(n_est):
                a, b = truth == t + 1, est == e + 1
                inter[t, e] += np.count_nonzero(a & b)
                union[t, e] += np.count_nonzero(a | b)
    with np.errstate(invalid="ignore", divide="ignore"):
        iou = np.nan_to_num(inter / union)
    rows, cols = linear_sum_assignment(iou, maximize=True)
    match = {int(e): int(t) for t, e in zip(rows, cols)}
    with_moving_part, every_frame = [], []
    for truth, est in images.values():
        shown = [t for t in range(n_true) if (truth == t + 1).any()]
        if est is None:
            every_frame.append([0.0] * len(shown))
            continue
        scores = [
            mask_iou(truth == t + 1, np.isin(est, [e + 1 for e, tt in match.items() if tt == t]))
            for t in shown
        ]
        every_frame.append(scores)
        if (est > 1).any():
            with_moving_part.append(scores)
    return match, with_moving_part, every_frame


def _mean_over(frames: list[list[float]]) -> float | None:
    scores = [s for frame in frames for s in frame]
    return float(np.mean(scores)) if scores else None


def score_articulation(articulation, truth: dict, true_labels: dict[int, np.ndarray]) -> dict:
    """How close the parts and joints found in a video are to the generator's truth.

    Parameters
    ----------
    articulation : :class:`artclass_core.articulation.Articulation`
    truth : dict
        The sequence's ``truth.json`` (``parts``, ``joints`` with per-frame ``state``,
        ``axis_camera0``, ``origin_camera0_m``, ``part_poses`` and ``part_points_m``).
    true_labels : dict of frame -> ndarray (H, W)
        The true part images (``parts/*.png``: 0 = not the object, 1 + part index), of every frame
        that has one.

    Returns
    -------
    dict: ``part_iou`` (mean IoU over the true parts and the frames whose estimated part image shows
    a moving part, or None), ``part_iou_all_frames`` (the same over every frame of ``true_labels``, a
    frame without an estimated part image scoring 0 for each of its true parts: an estimate that gives
    up on hard frames scores lower here, not higher; None without any true part image),
    and per estimated joint, matched to the true joint between the true parts its two parts match
    (or, failing that, the true joint of its child's part): ``type``, ``true_type``,
    ``axis_direction_error_deg``, ``axis_position_error_mm`` (at the true moving part in frame 0),
    ``state_error`` and its ``state_unit`` (``deg`` or ``mm``).
    """
    match, with_moving_part, every_frame = _matched_parts(articulation, true_labels)
    true_joints, true_parts = truth.get("joints") or [], truth.get("parts") or []
    out = dict(part_iou=_mean_over(with_moving_part), part_iou_all_frames=_mean_over(every_frame), joints=[])
    for joint in articulation.joints:
        parent, child = match.get(joint.parent), match.get(joint.child)
        found = [n for n, j in enumerate(true_joints) if {j["parent"], j["child"]} == {parent, child}]
        if (
            not found
            and child is not None
            and child < len(true_parts)
            and true_parts[child].get("joint") is not None
        ):
            found = [true_parts[child]["joint"]]
        if not found:
            out["joints"].append(dict(type=joint.estimate.type, true_type=None))
            continue
        j = true_joints[found[0]]
        swapped = j["parent"] == child
        out["joints"].append(_joint_errors(joint.estimate, j, truth, swapped=swapped))
    return out


def _joint_errors(est, true: dict, truth: dict, *, swapped: bool) -> dict:
    scores = dict(type=est.type, true_type=true["type"])
    if est.axis_direction is None or est.axis_point_m is None:
        return scores
    direction, point = (
        np.asarray(true["axis_camera0"][0], float),
        np.asarray(true["origin_camera0_m"][0], float),
    )
    moving = true["child"]
    local = np.asarray(truth["part_points_m"][0][moving], float).reshape(-1, 3)
    P = np.asarray(truth["part_poses"][0][moving], float)
    at = (P[:3, :3] @ local.mean(axis=0) + P[:3, 3]) if len(local) else point
    prismatic = true["type"] == "prismatic"
    same = (float(direction @ est.axis_direction) > 0) != swapped
    error = state_error(true["state"], est.states, same_direction=same)
    scores.update(
        axis_direction_error_deg=float(
            np.degrees(axis_direction_error_rad(direction, est.axis_direction, sign_invariant=True))
        ),
        axis_position_error_mm=None
        if prismatic
        else 1000 * axis_position_error_m(point, direction, est.axis_point_m, est.axis_direction, at_m=at),
        state_error=float(error * (1000 if prismatic else np.degrees(1.0))),
        state_unit="mm" if prismatic else "deg",
    )
    return scores
