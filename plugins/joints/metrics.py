"""How close a joint estimate is to the truth: type, axis direction and position, state, part masks.

Every function takes plain arrays in the parent's frame (metres, radians), so the evaluation can
compare any estimator with any ground truth.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment

from artclass_plugins.segmenters.selection import mask_iou


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


def axis_position_error_m(true_point_m, true_direction, estimated_point_m, estimated_direction, *, at_m) -> float:
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
    at_on_true = np.asarray(true_point_m, float) + d_true * float((np.asarray(at_m, float) - true_point_m) @ d_true)
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


def part_iou(true_labels: np.ndarray, estimated_labels: np.ndarray, *, background: int = 0) -> dict[int, float]:
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
