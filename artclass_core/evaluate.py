"""Evaluation over labelled sequences, reported in the layout of the paper's Tables 1-4."""

from __future__ import annotations

import platform
import time
from collections import defaultdict
from dataclasses import dataclass, field
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from .articulation import Articulation, forget_clouds
from .config import JOINT_ESTIMATOR, PART_FINDER
from .errors import ArtclassError
from .io import read_mask
from .joint_metrics import score_articulation
from .pipeline import Config, Pipeline, StageCache
from .plugins import Registry
from .types import DECISIONS, LABELS, RunResult, Sequence
from .video import JOINT_MODELS


@dataclass
class SequenceOutcome:
    name: str
    object: str
    truth: str
    accepted: tuple[str, ...]
    predicted: str | None  # None when the run failed
    error: str | None = None
    fractions: dict[str, float] = field(default_factory=dict)
    pair_correct: int = 0
    pair_total: int = 0
    pair_correct_legacy: int = 0  # against the reader's earlier pair truth, where it has one
    pair_total_legacy: int = 0
    n_pairs: int = 0
    n_undecided: int = 0  # pairs no model explained (counted as wrong in the pair accuracy)
    seconds: float = 0.0
    joints: dict[str, Any] | None = None  # parts and joints against the truth (sequences with joint truth)
    observable: bool | None = (
        None  # some pair's truth is AM: the articulation can show at this k (None: no pair truth)
    )
    n_frames: int = 0
    segment_s: float = 0.0  # the run's time segmenting its frames
    hands: dict[str, int] | None = None  # hand masks against the sequence's hand truth (score_hands)
    moved_against: str | None = None  # what a rigid or static object called articulated moved against

    @property
    def correct(self) -> bool:
        return self.predicted in self.accepted

    @property
    def effective_truth(self) -> str:
        """The truth this prediction is scored against: the prediction itself when it is accepted."""
        return self.predicted if self.correct else self.truth


@dataclass
class Evaluation:
    rule: str
    outcomes: list[SequenceOutcome]
    config: dict[str, Any]

    def metrics(self) -> dict[str, Any]:
        outs = self.outcomes
        n = len(outs)
        per_object: dict[str, list[SequenceOutcome]] = defaultdict(list)
        for o in outs:
            per_object[o.object].append(o)
        classes = [c for c in LABELS if any(o.truth == c for o in outs)]
        confusion = {t: {p: 0 for p in (*LABELS, "error")} for t in LABELS}
        for o in outs:
            confusion[o.effective_truth][o.predicted or "error"] += 1
        f1s, per_class = {}, {}
        for c in classes:
            tp = confusion[c][c]
            fp = sum(confusion[t][c] for t in LABELS if t != c)
            fn = sum(confusion[c].values()) - tp
            f1s[c] = 2 * tp / (2 * tp + fp + fn) if tp + fp + fn else 0.0
            members = [o for o in outs if o.truth == c]
            per_class[c] = sum(o.correct for o in members) / len(members)
        pair_total = sum(o.pair_total for o in outs)
        frames = sum(o.n_frames for o in outs)
        legacy_total = sum(o.pair_total_legacy for o in outs)
        shown = [o for o in outs if o.truth == "articulated" and o.observable]
        return dict(
            n_sequences=n,
            accuracy=sum(o.correct for o in outs) / n if n else 0.0,
            per_class_accuracy=per_class,
            # Articulated sequences whose articulation some pair (i, i + k or slow_factor k) can show.
            articulated_observable=dict(
                n=len(shown),
                of=sum(o.truth == "articulated" for o in outs),
                accuracy=sum(o.correct for o in shown) / len(shown) if shown else None,
            ),
            macro_f1=sum(f1s.values()) / len(f1s) if f1s else 0.0,
            f1=f1s,
            pair_accuracy=(sum(o.pair_correct for o in outs) / pair_total) if pair_total else None,
            pair_total=pair_total,
            pairs_undecided=sum(o.n_undecided for o in outs),
            pair_accuracy_legacy=(sum(o.pair_correct_legacy for o in outs) / legacy_total)
            if legacy_total
            else None,
            confusion=confusion,
            false_articulated=[
                o.name
                for o in outs
                if o.predicted == "articulated" and o.truth != "articulated" and not o.correct
            ],
            # what each of them moved against, where the object and hand truth tell
            false_articulated_against={o.name: o.moved_against for o in outs if o.moved_against},
            segment_ms_per_frame=1000 * sum(o.segment_s for o in outs) / frames if frames else None,
            hands=hand_summary([o.hands for o in outs if o.hands]),
            per_object={
                obj: dict(
                    truth=os_[0].truth,
                    n=len(os_),
                    accuracy=sum(o.correct for o in os_) / len(os_),
                    fractions={
                        d: _mean([o.fractions.get(d, 0.0) for o in os_ if o.fractions]) for d in DECISIONS
                    },
                )
                for obj, os_ in sorted(per_object.items(), key=lambda kv: (kv[1][0].truth, kv[0]))
            },
            errors=sum(o.predicted is None for o in outs),
            joints=joint_summary(outs),
        )

    def to_dict(self) -> dict[str, Any]:
        return dict(
            rule=self.rule,
            config=self.config,
            metrics=self.metrics(),
            sequences=[dict(o.__dict__, correct=o.correct) for o in self.outcomes],
        )


def hand_summary(counts: list[dict[str, int]]) -> dict[str, Any] | None:
    """The hand-mask IoU pooled over the frames with a hand, the share of those frames with the arm in
    the object's mask, and the frames without a hand where one was found (None without counts)."""
    if not counts:
        return None
    total = {k: sum(c[k] for c in counts) for k in counts[0]}
    with_hand = total["frames_with_hand"]
    return dict(
        hand_iou=total["intersection"] / total["union"] if total["union"] else None,
        arm_in_mask=total["arm_in_mask"] / with_hand if with_hand else None,
        frames_with_hand=with_hand,
        found_without_hand=total["found_without_hand"],
        frames_without_hand=total["frames_without_hand"],
    )


def _mean(values: list[float]) -> float:
    return sum(values) / len(values) if values else 0.0


def _median(values: list[float]) -> float | None:
    values = [v for v in values if v is not None and np.isfinite(v)]
    return float(np.median(values)) if values else None


def _joint_figures(outs: list[SequenceOutcome]) -> dict[str, Any]:
    """Joint-type accuracy and median errors over the joints found in ``outs``."""
    joints = [j for o in outs for j in o.joints["joints"] if j.get("true_type")]
    states = {
        unit: _median([j.get("state_error") for j in joints if j.get("state_unit") == unit])
        for unit in ("deg", "mm")
    }
    return dict(
        n_joints=len(joints),
        joint_type_accuracy=sum(j["type"] == j["true_type"] for j in joints) / len(joints)
        if joints
        else None,
        axis_direction_error_deg=_median([j.get("axis_direction_error_deg") for j in joints]),
        axis_position_error_mm=_median([j.get("axis_position_error_mm") for j in joints]),
        state_error_deg=states["deg"],
        state_error_mm=states["mm"],
        part_iou=_median([o.joints["part_iou"] for o in outs]),
        part_iou_all_frames=_median([o.joints.get("part_iou_all_frames") for o in outs]),
    )


def joint_summary(outs: list[SequenceOutcome]) -> dict[str, Any] | None:
    """Parts and joints over the sequences with joint truth: how many articulated ones got a moving
    part, the figures over those (overall and per object), and how many others wrongly got a joint."""
    scored = [o for o in outs if o.joints is not None]
    if not scored:
        return None
    articulated = [o for o in scored if o.truth == "articulated"]
    found = [o for o in articulated if o.joints["joints"]]
    by_object: dict[str, list[SequenceOutcome]] = defaultdict(list)
    for o in found:
        by_object[o.object].append(o)
    return dict(
        n_articulated=len(articulated),
        n_with_part=len(found),
        n_not_articulated=len(scored) - len(articulated),
        not_articulated_with_joint=sum(bool(o.joints["joints"]) for o in scored if o.truth != "articulated"),
        **_joint_figures(found),
        per_object={obj: _joint_figures(os_) for obj, os_ in sorted(by_object.items())},
    )


def evaluate(
    registry: Registry, sequences: list[Sequence], config: Config, *, progress=None, workers: int = 1
) -> Evaluation:
    """Run every sequence (on ``workers`` threads); a sequence that fails is recorded with its error, not fatal."""
    pipeline = Pipeline(registry, config)
    outcomes = []
    for n, seq in enumerate(sequences):
        outcomes.append(run_outcome(pipeline, seq, workers=workers)[0])
        seq.forget_frames()
        if progress:
            progress("sequences", n + 1, len(sequences))
    return evaluation(config, outcomes)


def run_outcome(
    pipeline: Pipeline, seq: Sequence, *, workers: int = 1, cache: StageCache | None = None
) -> tuple[SequenceOutcome, RunResult | None]:
    """Run one sequence and score it against its truth. Any failure is caught and recorded as the
    outcome's one-line ``error`` (the result is then None), so that the sequences after it still run."""
    o = outcome_of(seq)
    t0 = time.perf_counter()
    result = None
    truth = getattr(seq, "truth", None)
    finder = pipeline.registry.create("part_finder", PART_FINDER)
    with_joints = isinstance(truth, dict) and "joints" in truth and finder.works_on(pipeline.rule)
    # a rigid or static object called articulated is told what it moved against from its parts
    with_parts = (
        seq.label != "articulated" and (Path(seq.path) / "mask").is_dir() and finder.works_on(pipeline.rule)
    )
    try:
        result = pipeline.run(seq, workers=workers, cache=cache, keep_clouds=with_joints or with_parts)
    except Exception as exc:  # bad data, or a plugin's bug: one line here, and the next sequence runs
        o.error = one_line(exc)
    else:
        score_labels(o, pipeline, seq, result)
        wrongly = with_parts and o.predicted == "articulated" and not o.correct
        if with_joints or wrongly:
            try:
                estimator = pipeline.registry.create("joint_estimator", JOINT_ESTIMATOR)
                articulation = finder.find(result, estimator=estimator)
                if wrongly:
                    o.moved_against = _moved_against(articulation, seq, result)
                if with_joints:
                    o.joints = _score_joints(articulation, seq, result, truth)
            except Exception as exc:  # the label stands; the parts are reported as failed
                if with_joints:
                    o.joints = dict(part_iou=None, part_iou_all_frames=None, joints=[], error=one_line(exc))
        if with_joints or with_parts:
            forget_clouds(result)  # the run's clouds and evidence were kept for the parts only
        o.hands = _hands_of(pipeline, seq, cache)
    o.seconds = time.perf_counter() - t0
    return o, result


def outcome_of(seq: Sequence) -> SequenceOutcome:
    """A sequence's outcome before it is run: its name, object and truth."""
    return SequenceOutcome(seq.name, seq.object_name, seq.label, tuple(seq.accepted_labels), None)


def score_labels(o: SequenceOutcome, pipeline: Pipeline, seq: Sequence, result: RunResult) -> None:
    """Fill ``o`` with ``result``'s label, class fractions and pair accuracy against ``seq``'s truth."""
    o.predicted, o.fractions = result.label, result.fractions
    truthful = [p for p in result.pairs if p.truth and p.decision != "skipped"]
    o.pair_total = len(truthful)
    o.observable = _observable(seq, pipeline.params)
    o.pair_correct = sum(p.decision == p.truth for p in truthful)
    legacy = [(p, seq.pair_truth_legacy(p.i, p.j)) for p in result.pairs if p.decision != "skipped"]
    o.pair_total_legacy = sum(t is not None for _, t in legacy)
    o.pair_correct_legacy = sum(p.decision == t for p, t in legacy)
    o.n_pairs, o.n_frames = len(result.pairs), len(result.frames)
    o.segment_s = result.timing_s.get("segment", 0.0)
    o.n_undecided = sum(p.decision == "undecided" for p in result.pairs)


#: The arm is in the object's mask in a frame where it takes more than this share of the mask: a few
#: mixed pixels along the contact are not counted, a wrist or a sleeve is.
ARM_SHARE = 0.01
#: What :func:`score_hands` counts.
HAND_COUNTS = (
    "intersection",
    "union",
    "frames_with_hand",
    "arm_in_mask",
    "frames_without_hand",
    "found_without_hand",
)


def score_hands(
    segmenter, seq: Sequence, *, arm_share: float = ARM_SHARE, every: int = 1
) -> dict[str, int] | None:
    """A segmenter's hand masks (``hand_mask``: the hand or gripper with its arm) against the hand truth
    beside the sequence's frames (``hand/NAME.png``, non-zero on the hand and arm), as counts over the
    frames: pixels of their intersection and union where the truth has a hand, the frames with a hand
    and those where more than ``arm_share`` of the object's mask is the true hand, the frames without
    a hand and those where one was found (every ``every``-th frame). None when the segmenter does not
    look for hands or the sequence has no hand truth."""
    folder = Path(seq.path) / "hand"
    if not hasattr(segmenter, "hand_mask") or not folder.is_dir():
        return None
    out = dict.fromkeys(HAND_COUNTS, 0)
    for i in range(0, len(seq), every):
        frame = seq[i]
        path = folder / f"{frame.name}.png"
        if not path.is_file():
            continue
        found = segmenter.hand_mask(frame, sequence=seq)
        if found is None:  # this segmenter does not look for hands
            return None
        truth = read_mask(path)
        if not truth.any():
            out["frames_without_hand"] += 1
            out["found_without_hand"] += int(found.any())
            continue
        mask = segmenter.segment(frame, sequence=seq)
        out["frames_with_hand"] += 1
        out["intersection"] += int(np.count_nonzero(found & truth))
        out["union"] += int(np.count_nonzero(found | truth))
        out["arm_in_mask"] += int(
            mask is not None and np.count_nonzero(mask & truth) > arm_share * mask.sum()
        )
    return out


def _hands_of(pipeline: Pipeline, seq: Sequence, cache: StageCache | None) -> dict[str, int] | None:
    """:func:`score_hands` of the pipeline's segmenter, once per sequence and segmenter in ``cache``:
    settings that share the masks share the score (their segmenter never saw the frames)."""
    key = None if cache is None else (cache.sequence_token(seq), *pipeline.depends(seq, "segment"))
    if key is not None and (hit := cache.get("hands", key)) is not None:
        return hit or None
    try:
        counts = score_hands(pipeline.segmenter(seq), seq)
    except ArtclassError:  # unreadable hand truth: the labels stand
        counts = None
    if key is not None:
        cache.put("hands", key, counts or {})
    return counts


#: What a rigid or static object called articulated moved against, as the summary says it: the hand
#: or arm, something beside the object (a stand it was lifted from, the table), or itself (split in two).
AGAINST_TEXT = dict(hand="a hand or arm", beside="what it stood on or beside", itself="itself")
#: A part of the joint is the hand, or beside the object, when this share of its pixels is.
AGAINST_SHARE = 1 / 3


def moved_against(articulation: Articulation, object_masks: dict, hand_masks: dict) -> str | None:
    """What the joint seen over the most pairs moves: ``"hand"`` or ``"beside"`` when at least
    :data:`AGAINST_SHARE` of the pixels of one of its two parts lie on the true hand and arm
    (``hand_masks``, frame -> bool (H, W)) or on neither the hand nor the object (``object_masks``),
    the larger share when both do; else ``"itself"``. None without a joint or any frame with truth."""
    joints = [j for j in articulation.joints if j.estimate.type in JOINT_MODELS]
    if not joints:
        return None
    joint = max(joints, key=lambda j: j.n_pairs)
    counts = np.zeros((2, 3))  # the joint's parent and child: pixels on the hand, beside, the object
    for f in articulation.frames:
        if f not in object_masks:
            continue
        labels, obj = articulation.label_image(f), object_masks[f]
        hand = hand_masks.get(f, np.zeros_like(obj))
        for row, part in enumerate((joint.parent, joint.child)):
            on = labels == part + 1
            counts[row] += [
                np.count_nonzero(on & hand),
                np.count_nonzero(on & ~hand & ~obj),
                np.count_nonzero(on & obj & ~hand),
            ]
    if not counts.any():
        return None
    shares = counts[:, :2] / np.maximum(counts.sum(axis=1, keepdims=True), 1)
    worst = shares.max(axis=0)  # the largest share of either part on the hand, and beside
    return ("hand", "beside")[int(np.argmax(worst))] if worst.max() >= AGAINST_SHARE else "itself"


def _moved_against(articulation: Articulation, seq: Sequence, result: RunResult) -> str | None:
    """:func:`moved_against` of a run's parts against the object and hand truth beside the
    sequence's frames (``mask/``, ``hand/``); None when either cannot be read."""
    masks = {}
    try:
        for kind in ("mask", "hand"):
            paths = {f.index: Path(seq.path) / kind / f"{f.name}.png" for f in result.frames}
            masks[kind] = {i: read_mask(p) for i, p in paths.items() if p.is_file()}
    except ArtclassError:  # the label stands
        return None
    return moved_against(articulation, masks["mask"], masks["hand"])


def _observable(seq: Sequence, params) -> bool | None:
    """Whether some pair the pipeline may decide, (i, i + k) or (i, i + slow_factor k), has AM for its
    truth (None when the sequence has no pair truth): a judgement of the truth alone, not of which
    pairs the run decided."""
    truths = [
        seq.pair_truth(i, i + gap)
        for gap in {params.k, params.k * params.slow_factor}
        for i in range(len(seq) - gap)
    ]
    known = [t for t in truths if t]
    return ("AM" in known) if known else None


def _score_joints(
    articulation: Articulation, seq: Sequence, result: RunResult, truth: dict
) -> dict[str, Any]:
    """The parts and joints found in a run against the sequence's joint truth and part images
    (``parts/``)."""
    images = {}
    for frame in result.frames:
        path = Path(seq.path) / "parts" / f"{frame.name}.png"
        if path.is_file():
            images[frame.index] = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    return score_articulation(articulation, truth, images)


def one_line(exc: BaseException) -> str:
    """The first line of an error's message; prefixed with its type unless it is an :class:`ArtclassError`."""
    text = (str(exc).strip().splitlines() or [""])[0]
    return text if isinstance(exc, ArtclassError) else f"{type(exc).__name__}: {text}".rstrip(": ")


#: The packages whose versions an evaluation's numbers depend on: artclass, and those that render,
#: read and compute (two installs can render a few depth pixels apart, and the labels near a
#: decision's edge move with them).
PACKAGES = (
    "artclass",
    "numpy",
    "scipy",
    "opencv-python-headless",
    "open3d-cpu",
    "open3d",
    "numba",
    "onnxruntime",
)


def environment() -> dict[str, str]:
    """The installed versions of :data:`PACKAGES` (those installed), and Python's."""
    found = {"python": platform.python_version()}
    for name in PACKAGES:
        try:
            found[name] = version(name)
        except PackageNotFoundError:
            continue
    return found


def evaluation(config: Config, outcomes: list[SequenceOutcome]) -> Evaluation:
    """The :class:`Evaluation` of ``config`` made of these outcomes, with the :func:`environment`."""
    return Evaluation(
        config_label(config),
        outcomes,
        dict(
            plugins={k: getattr(config, k) for k in ("segmenter", "preprocessor", "registrar", "rule")},
            environment=environment(),
        ),
    )


def config_label(config: Config) -> str:
    """A short column name: the rule, and what else differs from the default pipeline."""
    default = Config()
    parts = [config.rule] + [
        f"{kind}={getattr(config, kind)}"
        for kind in ("segmenter", "preprocessor", "registrar")
        if getattr(config, kind) != getattr(default, kind)
    ]
    return ", ".join(parts + ([] if config.pipeline.prealign else ["no prealign"]))


def _pct(x: float | None) -> str:
    return "–" if x is None else f"{100 * x:.2f}"


def _number(x: float | None, digits: int = 1) -> str:
    return "–" if x is None else f"{x:.{digits}f}"


def _against(m: dict[str, Any], name: str) -> str:
    """A sequence named in the false-articulation row, with what it moved against where known."""
    against = m["false_articulated_against"].get(name)
    return f"{name}: {AGAINST_TEXT[against]}" if against else name


def _hand_lines(ms: list[dict[str, Any]]) -> list[str]:
    """Summary rows of the hand masks (segmenters that look for hands, on data with hand truth)."""
    if not any(m["hands"] for m in ms):
        return []
    rows = (
        ("hand-and-arm mask IoU, pooled over the frames with a hand", lambda h: _number(h["hand_iou"], 3)),
        ("frames with a hand where the arm is in the object's mask %", lambda h: _pct(h["arm_in_mask"])),
        ("frames with / without a hand", lambda h: f"{h['frames_with_hand']} / {h['frames_without_hand']}"),
        ("frames without a hand where one is found", lambda h: str(h["found_without_hand"])),
    )
    return [
        f"| {label} | " + " | ".join(cell(m["hands"]) if m["hands"] else "–" for m in ms) + " |"
        for label, cell in rows
    ]


def _joint_lines(rules: list[str], ms: list[dict[str, Any]]) -> list[str]:
    """The parts-and-joints section: overall, then per object (sequences with joint truth only)."""
    if all(m.get("joints") is None for m in ms):
        return []
    rows = [
        (
            "articulated sequences with a moving part found",
            lambda j: f"{j['n_with_part']} / {j['n_articulated']}",
        ),
        (
            "rigid or static sequences with a joint",
            lambda j: f"{j['not_articulated_with_joint']} / {j['n_not_articulated']}",
        ),
        ("joint type right %", lambda j: _pct(j["joint_type_accuracy"])),
        ("median axis direction error (deg)", lambda j: _number(j["axis_direction_error_deg"])),
        ("median axis position error at the part (mm)", lambda j: _number(j["axis_position_error_mm"])),
        ("median state error, revolute (deg)", lambda j: _number(j["state_error_deg"])),
        ("median state error, prismatic (mm)", lambda j: _number(j["state_error_mm"])),
        ("median part IoU, frames where a moving part was found", lambda j: _number(j["part_iou"], 2)),
        (
            "median part IoU, every frame (0 where none was found)",
            lambda j: _number(j.get("part_iou_all_frames"), 2),
        ),
    ]
    lines = [
        "",
        "## Parts and joints (over the articulated sequences where a moving part was found)",
        "",
        "| metric | " + " | ".join(rules) + " |",
        "|---|" + "---|" * len(rules),
    ]
    for label, cell in rows:
        lines.append(
            f"| {label} | " + " | ".join(cell(m["joints"]) if m.get("joints") else "–" for m in ms) + " |"
        )
    first = ms[0].get("joints")
    if first and first["per_object"]:
        lines += [
            "",
            f"Per object ({rules[0]}):",
            "",
            "| object | joints | type right % | axis direction (deg) | axis position (mm) | state (deg) "
            "| state (mm) | part IoU, frames with a part found | part IoU, every frame |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for obj, j in first["per_object"].items():
            lines.append(
                f"| {obj} | {j['n_joints']} | {_pct(j['joint_type_accuracy'])} | "
                f"{_number(j['axis_direction_error_deg'])} | {_number(j['axis_position_error_mm'])} | "
                f"{_number(j['state_error_deg'])} | {_number(j['state_error_mm'])} | {_number(j['part_iou'], 2)} | "
                f"{_number(j.get('part_iou_all_frames'), 2)} |"
            )
    return lines


def markdown(evals: list[Evaluation]) -> str:
    """A Markdown report; with several evaluations (e.g. the default rule and ``paper``) side by side."""
    ms = [e.metrics() for e in evals]
    rules = [e.rule for e in evals]
    versions = ", ".join(f"{k} {v}" for k, v in evals[0].config.get("environment", {}).items())
    lines = ["# artclass evaluation", ""] + ([f"Measured with {versions}.", ""] if versions else [])
    lines += [
        "## Sequences",
        "",
        "| sequence | object | truth | " + " | ".join(f"{r}" for r in rules) + " |",
        "|---|---|---|" + "---|" * len(rules),
    ]
    for row in zip(*(e.outcomes for e in evals)):
        o = row[0]
        cells = [(x.predicted or f"error: {x.error}") + ("" if x.correct else " ✗") for x in row]
        lines.append(f"| {o.name} | {o.object} | {o.truth} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "## Accuracy per object (Tables 1-2)",
        "",
        "| object | truth | n | " + " | ".join(f"{r} accuracy %" for r in rules) + " |",
        "|---|---|---|" + "---|" * len(rules),
    ]
    for obj, info in ms[0]["per_object"].items():
        lines.append(
            f"| {obj} | {info['truth']} | {info['n']} | "
            + " | ".join(_pct(m["per_object"][obj]["accuracy"]) for m in ms)
            + " |"
        )
    lines += [
        "",
        "## Pair fractions per object (Tables 3-4)",
        "",
        "| object | " + " | ".join(f"{r} {d}" for r in rules for d in DECISIONS) + " |",
        "|---|" + "---|" * (len(rules) * len(DECISIONS)),
    ]
    for obj in ms[0]["per_object"]:
        lines.append(
            f"| {obj} | "
            + " | ".join(f"{m['per_object'][obj]['fractions'][d]:.3f}" for m in ms for d in DECISIONS)
            + " |"
        )
    lines += ["", "## Summary", "", "| metric | " + " | ".join(rules) + " |", "|---|" + "---|" * len(rules)]
    rows = [
        ("accuracy", "sequence accuracy %"),
        ("macro_f1", "macro-F1 %"),
        ("pair_accuracy", "pair accuracy %"),
    ]
    if any(m["pair_accuracy_legacy"] is not None for m in ms):
        rows.append(("pair_accuracy_legacy", "pair accuracy % (earlier joint-state truth)"))
    for key, label in rows:
        lines.append(f"| {label} | " + " | ".join(_pct(m[key]) for m in ms) + " |")
    lines.append(
        "| pairs undecided (counted as wrong) | " + " | ".join(str(m["pairs_undecided"]) for m in ms) + " |"
    )
    for c in LABELS:
        if c in ms[0]["per_class_accuracy"]:
            lines.append(
                f"| {c} accuracy % | " + " | ".join(_pct(m["per_class_accuracy"].get(c)) for m in ms) + " |"
            )
    if any(m["articulated_observable"]["n"] for m in ms):
        lines.append(
            "| articulated accuracy % where some pair shows the articulation | "
            + " | ".join(
                f"{_pct(m['articulated_observable']['accuracy'])} "
                f"({m['articulated_observable']['n']} of {m['articulated_observable']['of']} sequences)"
                for m in ms
            )
            + " |"
        )
    lines.append(
        "| sequences / errors | " + " | ".join(f"{m['n_sequences']} / {m['errors']}" for m in ms) + " |"
    )
    lines.append(
        "| rigid or static called articulated | "
        + " | ".join(
            f"{len(m['false_articulated'])}"
            + (
                f" ({', '.join(_against(m, name) for name in m['false_articulated'])})"
                if m["false_articulated"]
                else ""
            )
            for m in ms
        )
        + " |"
    )
    lines.append(
        "| segmenting, ms a frame | " + " | ".join(_number(m["segment_ms_per_frame"]) for m in ms) + " |"
    )
    lines += _hand_lines(ms)
    lines += _joint_lines(rules, ms)
    for e, m in zip(evals, ms):
        lines += [
            "",
            f"## Confusion matrix ({e.rule}; rows truth, columns predicted)",
            "",
            "| truth \\ predicted | " + " | ".join((*LABELS, "error")) + " |",
            "|---|" + "---|" * 4,
        ]
        for t in LABELS:
            lines.append(
                f"| {t} | " + " | ".join(str(m["confusion"][t][p]) for p in (*LABELS, "error")) + " |"
            )
    return "\n".join(lines) + "\n"
