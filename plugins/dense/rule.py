"""The ``dense`` rule: how many rigid motions does the pair need? Model selection on dense evidence.

Evidence: for every source point and every motion hypothesis of the pair registrar, what the moved
point finds in the target image (:class:`~artclass_core.types.MotionEvidence`). A point costs its
squared residual in noise units (``(r / sigma)^2``, at most ``noise_factor^2``); a point the motion
sends into free space, or onto something that is not the object, costs the most; a point it hides
behind something (a hand) or out of view costs half of that, since it is no evidence either way.
Where the colour image has texture, the distance between where the motion and where optical flow
put the point adds a cost of the same kind. Sigma is measured on the pair: the spread of the second
differences of the best single motion's residuals at ``noise_lag_rad`` (:func:`field_noise`), which
holds the error a real sensor correlates over many pixels; and so many points make one independent
observation (A: 1 for an uncorrelated field), in which every count below is made.

Selection: motions are added one at a time, the one that lowers the total cost most first, while
the saving pays for the motion's six parameters (BIC: ``A 6 ln (N / A)``), the points it explains
better than the motions already chosen are at least ``min_part_share`` of the seen points (staying
still, which is no fit, needs only ``min_part_points``), and those points form one region of the image
rather than a scatter; then each selected motion in turn is swapped for the hypothesis that
explains the points best with the others. Each point then takes the selected motion that explains
it best: that labelling is the pair's part segmentation, and a part whose points are mixed with
another's (two fits that each explain half of a rigid object) is not a part.

Decision: two or more motions that really differ (their relative motion moves the median point of
each side by more than ``noise_factor`` sigma plus one pixel, the part fails in depth points that the
base explains, and the base fails points the part explains, in depth or, unless the part's motion is
a fit of the whole object, in optical flow where it lands them on texture unlike theirs: on stripes a
motion a period off lands on the same texture) are AM; one motion is RM when it moves the median point
by as much and explains in depth points that staying still fails, else NM. A motion fails a point in
depth when it misses it by more than ``noise_factor`` times sigma, or times the depth change of the
still scene about the point where that is larger (the sensor's own error there, such as a
time-of-flight camera's multipath near a passing hand: :mod:`.scene`), plus half a pixel (the look-up
rounds to the nearest pixel, up to half a pixel off the surface where the surface is steep: a still
object on a shaking camera, half hidden by a moving hand, misses a slide along itself by less), plus
``calibration_error`` times how far the motion's rotation moves it about the object's centre (a
calibration a few percent off bends a rigid motion by that much). Too few points seen in both
frames: skipped. A pair whose kept motions fail most of its points, or whose parts none of the
optical flow follows (its spread beyond ``noise_factor`` times ``flow_sigma_px``), is undecided: no
model explains it.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from artclass_core import DecisionRule, Motion, MotionEvidence, Params, RuleDecision, param
from artclass_core.geometry import transform
from artclass_core.types import FREE_SPACE, OFF_OBJECT, SURFACE

from .projective import hypothesis_costs, kernels

# The registrar's hypotheses fitted to all of the object's points are named with this first.
WHOLE_OBJECT = "object"


@dataclass(frozen=True)
class DenseRuleParams(Params):
    noise_factor: float = param(
        3.0,
        unit="sigma",
        bounds=(0.5, 20.0),
        help="A residual beyond this many noise sigmas (measured on the pair) is a misfit; "
        "a motion must move points by this much, plus a pixel, to count as one.",
    )
    flow_sigma_px: float = param(
        2.5,
        unit="px",
        bounds=(0.1, 20.0),
        help="Typical error of the optical flow on texture, in pixels (the flow noise "
        "measured on a pair is never taken below this).",
    )
    bic_factor: float = param(
        1.0,
        unit="1",
        bounds=(0.0, 100.0),
        help="A further motion must lower the total cost by this many times its BIC "
        "penalty, 6 ln N (6 parameters, N points).",
    )
    min_part_share: float = param(
        0.03,
        unit="fraction",
        bounds=(0.0, 0.5),
        help="A further motion must explain at least this share of the seen points "
        "better than the motions already chosen.",
    )
    min_part_points: int = param(
        20,
        unit="points",
        bounds=(1, 100000),
        help="... and at least this many points (staying still needs only these: it is no fit).",
    )
    min_coherence: float = param(
        0.6,
        unit="fraction",
        bounds=(0.0, 1.0),
        help="A part is a region, not a scatter: its points' image neighbours must be "
        "its own for at least this share on average (and so must those of the "
        "points it explains that no chosen motion does).",
    )
    calibration_error: float = param(
        0.03,
        unit="fraction",
        bounds=(0.0, 0.5),
        help="Relative error of the camera's calibration (focal length, principal point, depth "
        "scale): a rigid motion that turns the object by R misplaces a point r from its centre by "
        "up to this times |(R - I) r|, which a part must exceed to fail its base.",
    )
    noise_lag_rad: float = param(
        0.05,
        unit="rad",
        bounds=(0.0, 1.0),
        help="The depth noise of a pair is the spread of residual differences between points this "
        "far apart (seen from the camera): beyond the few pixels over which a sensor's depth error "
        "is correlated, within a part (32 px at 640x480).",
    )
    min_seen_share: float = param(
        0.3,
        unit="fraction",
        bounds=(0.0, 1.0),
        help="A pair is skipped when fewer of its points land on a surface of the target "
        "under the best motion.",
    )


def point_costs(
    ev: MotionEvidence, *, noise_factor: float, flow_sigma_px: float, noise_m: float | None = None
) -> np.ndarray:
    """Cost (H, N) of explaining each point by each hypothesis, in squared noise units (depth noise
    ``noise_m``, default the evidence's own; flow noise ``flow_sigma_px``)."""
    return hypothesis_costs(
        ev.residual_m,
        ev.status,
        ev.flow_px,
        noise_m=noise_m or ev.noise_m,
        flow_sigma_px=flow_sigma_px,
        worst=noise_factor**2,
    )


def _grid(pixels: np.ndarray, stride: int, *, pad: int) -> tuple[np.ndarray, tuple[int, int]]:
    """Each point's (column, row) cell on the ``stride`` grid, offset so that ``pad`` empty cells
    surround the points, and the grid's shape (rows, columns)."""
    g = pixels // max(stride, 1)
    g -= np.array([g[:, 0].min(), g[:, 1].min()]) - pad  # a column at a time: (N, 2) reduces slowly
    return g, (int(g[:, 1].max()) + 1 + pad, int(g[:, 0].max()) + 1 + pad)


def _coherence(members: np.ndarray, pixels: np.ndarray, stride: int) -> float:
    """Share of ``members`` (a boolean mask of points) with a member among their 8 image neighbours."""
    if members.sum() == 0:
        return 0.0
    same = label_coherence(members.astype(np.int64), pixels, stride)[members]
    return float((np.nan_to_num(same) > 0).mean())


def label_coherence(labels: np.ndarray, pixels: np.ndarray, stride: int) -> np.ndarray:
    """For each point, the share of its 8 image neighbours (points on the ``stride`` grid) that carry
    its label, among those labelled -1 or more (a label below -1 marks a point to leave out); NaN for
    a point without such neighbours."""
    g, (rows, columns) = _grid(pixels, stride, pad=1)
    cell = g[:, 1] * columns + g[:, 0]
    image = np.full(rows * columns, -2, np.int64)
    image[cell] = labels
    steps = [dv * columns + du for dv in (-1, 0, 1) for du in (-1, 0, 1) if dv or du]
    neighbour = image[cell + np.array(steps)[:, None]]  # (8, N)
    with np.errstate(invalid="ignore", divide="ignore"):
        return (neighbour == labels).sum(axis=0) / (neighbour >= -1).sum(axis=0)


def regions(
    members: np.ndarray, pixels: np.ndarray, stride: int, *, min_points: int, most: int
) -> list[np.ndarray]:
    """The ``most`` largest 8-connected image regions (indices of points) of the ``members`` points,
    each of at least ``min_points``."""
    if members.sum() < min_points:
        return []
    g, shape = _grid(pixels, stride, pad=0)
    image = np.zeros(shape, np.uint8)
    image[g[members, 1], g[members, 0]] = 1
    _, labels, stats, _ = cv2.connectedComponentsWithStats(image, connectivity=8)
    label = np.where(members, labels[g[:, 1], g[:, 0]], 0)
    big = [
        c
        for c in np.argsort(-stats[:, cv2.CC_STAT_AREA], kind="stable")
        if c and stats[c, cv2.CC_STAT_AREA] >= min_points
    ]
    return [np.flatnonzero(label == c) for c in big[:most]]


def select(
    costs: np.ndarray,
    pixels: np.ndarray,
    *,
    penalty: float,
    misfit: float,
    min_points: int,
    min_coherence: float,
    stride: int,
    min_still_points: int | None = None,
) -> list[int]:
    """Greedy model selection: the hypotheses (indices into ``costs``) the points need.

    Starts from the single hypothesis of least total cost and adds the one that saves most, while the
    saving exceeds ``penalty`` and the points it explains (cost below ``misfit / 2``) that the chosen
    ones do not (cost at least ``misfit``) number ``min_points`` and are a coherent image region. A
    motion that merely fits some points a little better (two fits of a symmetric object) adds nothing.
    Staying still (hypothesis 0, the identity) is no fit, so it needs only ``min_still_points``: a
    still base seen as a thin strip, sliding in itself under its part's motion, fails that motion at
    its edges only.
    Finally each chosen motion is swapped for the best one given the others (:func:`_swapped`).
    """
    compiled = kernels()
    total, saving = np.empty((2, len(costs)), costs.dtype)
    compiled.totals_kernel(costs, total)
    chosen = [int(np.argmin(total))]
    best = costs[chosen[0]].copy()
    while True:
        compiled.savings_kernel(costs, best, saving)
        saving[chosen] = 0
        order = np.argsort(-saving, kind="stable")
        unexplained = best >= misfit
        for h in order[:5]:
            if saving[h] <= penalty:
                return _swapped(costs, chosen)
            members = (costs[h] < misfit / 2) & unexplained
            enough = min_points if h or min_still_points is None else min_still_points
            if members.sum() >= enough and _coherence(members, pixels, stride) >= min_coherence:
                chosen.append(int(h))
                best = np.minimum(best, costs[h])
                break
        else:
            return _swapped(costs, chosen)


def _swapped(costs: np.ndarray, chosen: list[int]) -> list[int]:
    """``chosen`` with each motion in turn replaced by the hypothesis that, with the others, explains
    the points at least cost. A motion chosen first, alone, may be a compromise between a part and its
    base (a whole-object fit pulled by the part); once the part has its own motion, the base's own is
    better."""
    chosen = list(chosen)
    if len(chosen) < 2:
        return chosen
    for i in range(len(chosen)):
        others = np.min(costs[[h for j, h in enumerate(chosen) if j != i]], axis=0)
        total = np.minimum(others[None], costs).sum(axis=1)
        total[[h for j, h in enumerate(chosen) if j != i]] = np.inf
        chosen[i] = int(np.argmin(total))
    return chosen


def field_noise(
    residual_m: np.ndarray, pixels: np.ndarray, stride: int, *, lag_px: float, floor_m: float
) -> tuple[float, float]:
    """The noise of a residual field from second differences of points ``lag_px`` apart, and how
    many points it correlates.

    Real depth error is correlated over the image (a stereo matcher's windows, a projector's pattern,
    the preprocessor's smoothing), so the spread of a residual about its neighbours' understates it.
    The second difference ``r(p - L) - 2 r(p) + r(p + L)`` of points ``L`` apart along a row or a
    column holds the error of all three, correlated or not, once ``L`` exceeds the correlation length;
    but not a misfit that varies linearly over a region (a part turning away from the motion fitted
    to the whole object), which shows only at the region's edges.

    Parameters
    ----------
    residual_m : (N,) residuals, NaN where a point has none
    pixels : (N, 2) their (column, row)
    stride : the points' grid step, pixels
    lag_px : L, pixels
    floor_m : the noise of one pixel (the sensor's), metres: the sigmas are not taken below it

    Returns
    -------
    sigma : the robust sigma (1.4826 MAD of the second differences over sqrt 6) at lag L, metres;
        NaN for too few points
    area : the points that make one independent observation: the square of that sigma over the
        same at lag one grid step (1 for an uncorrelated field), at most L^2
    """
    g, shape = _grid(pixels, stride, pad=0)
    value = np.full(shape, np.nan)
    value[g[:, 1], g[:, 0]] = residual_m

    def sigma(lag: int) -> float:
        """At ``lag`` grid steps, or an eighth of the field's extent along a row or a column if
        that is less: a part's edges must stay a small share of the differences."""
        across, down = (min(lag, max(1, n // 8)) if n >= 3 else 0 for n in shape[::-1])
        d = np.empty(2 * value.size)
        d = d[: kernels().second_differences_kernel(value, across, down, d)]
        return _spread(d, centred=False) / np.sqrt(6) if len(d) >= 20 else np.nan

    lag = max(1, int(round(lag_px / max(stride, 1))))
    near, far = sigma(1), sigma(lag)
    area = max(1.0, max(far, floor_m) / max(near, floor_m)) ** 2 if np.isfinite(far + near) else 1.0
    return far, min(area, lag**2)


def _spread(values: np.ndarray, *, centred: bool = True) -> float:
    """Robust standard deviation (1.4826 MAD) of ``values``; about zero when not ``centred``."""
    centre = _median(values) if centred else 0.0
    return float(1.4826 * _median(np.abs(values - centre)))


def _median(values: np.ndarray) -> float:
    """``np.median`` of a 1-D array of finite values, to the bit, without the generality that takes
    most of its time on a few thousand values."""
    half = len(values) // 2
    if len(values) % 2:
        return np.partition(values, half)[half]
    low, high = np.partition(values, (half - 1, half))[half - 1 : half + 1]
    return (low + high) / 2


def _layout(ev: MotionEvidence) -> np.ndarray:
    """The points' pixels on one canvas: the target's points (judged the other way) to the right of
    the source's, so that image neighbours are always points of the same image."""
    pixels = ev.pixels.copy()
    forward = ev.forward
    if not forward.all():
        pixels[:, 0] += np.where(forward, 0, pixels[:, 0].max() + 8 * ev.stride_px)
    return pixels


def _displacement(points: np.ndarray, A: np.ndarray, B: np.ndarray) -> float:
    """Median distance between the points moved by A and by B (metres)."""
    return (
        float(_median(np.linalg.norm(transform(points, A) - transform(points, B), axis=1)))
        if len(points)
        else 0.0
    )


class DenseRule(DecisionRule):
    """Counts the rigid motions the pair's dense evidence needs, by model selection (see module docstring)."""

    name = "dense"
    description = "model selection over dense motion hypotheses: AM when two distinct motions pay for themselves (default)"
    Params = DenseRuleParams
    needs = "motions"

    def costs(
        self, ev: MotionEvidence, noise_m: float | None = None, flow_px: float | None = None
    ) -> np.ndarray:
        return point_costs(
            ev,
            noise_factor=self.params.noise_factor,
            noise_m=noise_m,
            flow_sigma_px=flow_px or self.params.flow_sigma_px,
        )

    def noise(
        self, ev: MotionEvidence, seen: np.ndarray, layout: np.ndarray
    ) -> tuple[float, float, np.ndarray, int]:
        """The depth and flow noise of the pair, the costs under them, and the points that make one
        independent observation (``layout``: the points' pixels, :func:`_layout`).

        The depth noise is that of the residual field of the single motion that explains the pair
        best (:func:`field_noise`, never below the frames' own noise), and so is the number of
        points its error correlates. The flow noise is the robust spread of each seen point's flow
        misfit under the motion the selection gives it (never below ``flow_sigma_px``)."""
        costs = self.costs(ev)
        best = int(np.argmin(costs.sum(axis=1)))
        forward = ev.forward
        residual = np.where(seen & (ev.status[best] == SURFACE), ev.residual_m[best], np.nan)[forward]
        fx = float(_median(ev.points[:, 2][forward])) / ev.pixel_m
        field, area = field_noise(
            residual,
            np.compress(forward, ev.pixels, axis=0),
            ev.stride_px,
            lag_px=self.params.noise_lag_rad * fx,
            floor_m=ev.noise_m,
        )
        sigma, area = float(np.fmax(field, ev.noise_m)), int(round(area))
        chosen = self.choose(ev, costs, seen, layout, area=area)
        owner = np.asarray(chosen)[np.argmin(costs[chosen], axis=0)]
        point = np.arange(len(owner))
        f = ev.flow_px[owner, point][seen & np.isfinite(ev.flow_px[owner, point])]
        flow = (
            max(_spread(f, centred=False), self.params.flow_sigma_px)
            if len(f) >= 10
            else self.params.flow_sigma_px
        )
        return sigma, flow, self.costs(ev, sigma, flow), area

    def choose(
        self, ev: MotionEvidence, costs: np.ndarray, seen: np.ndarray, layout: np.ndarray, *, area: int = 1
    ) -> list[int]:
        """The hypotheses selected for the seen points (indices into ``ev.motions``; ``layout``: the
        points' pixels, :func:`_layout`), ``area`` points making one independent observation."""
        p = self.params
        n = int(seen.sum())
        return select(
            costs[:, seen],
            np.compress(seen, layout, axis=0),  # layout[seen], ten times faster
            penalty=p.bic_factor * area * 6 * np.log(max(n / area, 2)),
            misfit=p.noise_factor**2,
            min_points=max(p.min_part_points * area, int(p.min_part_share * n)),
            min_coherence=p.min_coherence,
            stride=ev.stride_px,
            min_still_points=p.min_part_points * area,
        )

    def decide(self, ev: MotionEvidence, *, source=None, target=None) -> RuleDecision:
        p = self.params
        seen = (ev.status == SURFACE).any(axis=0)
        forward = ev.forward
        if not seen.any():
            return RuleDecision("skipped", [], reason="no point lands on the target surface under any motion")
        layout, stride = _layout(ev), ev.stride_px
        noise, flow_noise, costs, area = self.noise(ev, seen, layout)
        first = int(np.argmin(costs.sum(axis=1)))
        share = float((ev.status[first, forward] == SURFACE).mean()) if forward.any() else 0.0
        if share < p.min_seen_share:
            return RuleDecision(
                "skipped",
                [],
                reason=f"only {share:.0%} of the points seen on the target surface "
                f"(alpha = {p.min_seen_share:g})",
                info=dict(seen_share=share),
            )
        chosen = self.choose(ev, costs, seen, layout, area=area)
        labels = np.where(seen, np.asarray(chosen)[np.argmin(costs[chosen], axis=0)], -1)
        threshold = p.noise_factor * noise + ev.pixel_m
        base = chosen[0]
        parts = []
        # Coherence counts the decisive points only: where one selected motion explains a point clearly
        # better than the others (a surface both explain, sliding in itself, belongs to neither).
        ranked = np.sort(costs[chosen], axis=0)
        decisive = (
            np.where(seen & (ranked[1] - ranked[0] >= p.noise_factor**2 / 2), labels, -3)
            if len(chosen) > 1
            else labels
        )
        coherence = label_coherence(decisive, layout, stride)
        misfit = p.noise_factor**2

        def least(h: int, area: int = area) -> int:
            """The points motion ``h`` must explain on its own (``area`` points to an independent
            observation): staying still is no fit."""
            few = p.min_part_points * area
            return few if h == 0 else max(few, int(p.min_part_share * seen.sum()))

        # A miss counts beyond noise_factor sigma (or the still scene's change about the point) plus
        # the look-up's half pixel, plus what the calibration's error makes of the motion's rotation.
        scene = 0.0 if ev.scene_error_m is None else ev.scene_error_m
        limit = p.noise_factor * np.maximum(noise, scene) + ev.pixel_m / 2
        centre = np.array([_median(x) for x in ev.points.T])

        def repeats(b: int) -> np.ndarray:
            """The points motion ``b`` lands on texture as like the source's as the flow's own matches
            are (within ``noise_factor`` robust sigmas): there the flow cannot tell ``b`` from its own."""
            if ev.landing_grey is None:
                return np.zeros(len(ev.points), bool)
            median, spread = ev.info.get("flow_grey", (np.nan, np.nan))
            return ev.landing_grey[b] <= median + p.noise_factor * spread

        def fails(b: int, *, texture: bool) -> np.ndarray:
            """The points motion ``b`` misses in depth (or, with ``texture``, in optical flow)."""
            status, residual = ev.status[b], np.abs(np.nan_to_num(ev.residual_m[b], nan=np.inf))
            turned = np.linalg.norm((ev.points - centre) @ (ev.motions[b][:3, :3] - np.eye(3)).T, axis=1)
            out = (status == FREE_SPACE) | (status == OFF_OBJECT)
            out |= (status == SURFACE) & (residual >= limit + p.calibration_error * turned)
            if texture:
                out |= (np.nan_to_num(ev.flow_px[b]) >= p.noise_factor * flow_noise) & ~repeats(b)
            return out

        def needed(a: int, b: int, *, texture: bool = False, part: bool = True) -> bool:
            """Whether motion ``a`` explains enough points that ``b`` fails in depth (or, with
            ``texture``, in depth or optical flow); staying still needs only ``min_part_points``.
            A ``part`` counts them in independent observations."""
            members = seen & (costs[a] < misfit / 2) & fails(b, texture=texture)
            return int(members.sum()) >= least(a, area if part else 1)

        tests = []
        for h in chosen[1:]:
            own = np.compress(forward & (labels == h), ev.points, axis=0)
            rest = np.compress(forward & (labels >= 0) & (labels != h), ev.points, axis=0)
            apart = min(
                _displacement(own, ev.motions[h], ev.motions[base]),
                _displacement(rest, ev.motions[h], ev.motions[base]),
            )
            # Each motion must fail points the other explains: two fits of one rigid body explain
            # nearly the same points, a part and its base do not. The part must fail the base's
            # points in depth, since texture alone misleads (stripes that repeat, shading that moves
            # over a turning surface); the base may fail the part's in texture (a drawer sliding
            # along its own surface), unless the part's motion is a fit of the whole object, which
            # flow on stripes can pull off the object's motion everywhere (a turning striped can).
            texture = not ev.names[h].startswith(WHOLE_OBJECT)
            both_needed = needed(h, base, texture=texture) and needed(base, h)
            # ... and a part is one region of the image where its motion is clearly the better one.
            region = regions(decisive == h, layout, stride, min_points=least(h) // 2, most=1)
            coherent = float(np.nanmean(coherence[decisive == h])) if region else 0.0
            tests.append(
                dict(
                    motion=ev.names[h],
                    apart_m=round(apart, 5),
                    needed=both_needed,
                    region=bool(region),
                    coherence=round(coherent, 3),
                )
            )
            if apart > threshold and both_needed and region and coherent >= p.min_coherence:
                parts.append(h)
        kept = [base, *parts]
        labels = np.where(seen, np.asarray(kept)[np.argmin(costs[kept], axis=0)], -1)
        motions = [
            Motion(
                ev.motions[h],
                ev.names[h],
                int((forward & (labels == h)).sum()),
                _displacement(
                    np.compress(forward & (labels == h), ev.points, axis=0), ev.motions[h], np.eye(4)
                ),
            )
            for h in kept
        ]
        index = np.full(len(ev.motions), -1)
        index[kept] = np.arange(len(kept))
        labels = np.where(labels >= 0, index[labels], -1)
        info = dict(
            noise_m=round(noise, 6),
            frame_noise_m=round(ev.noise_m, 6),
            correlated_points=area,
            flow_noise_px=round(flow_noise, 3),
            threshold_m=round(threshold, 6),
            seen_share=round(share, 4),
            n_hypotheses=len(ev.motions),
            selected=[ev.names[h] for h in chosen],
            part_shares=[round(m.n_points / max(int((seen & forward).sum()), 1), 4) for m in motions],
            candidates=tests,
        )
        # No model explains the pair when the kept motions fail most of its points, or, for parts, when
        # the optical flow follows none of them: a motion beyond what registration reaches.
        unexplained = float((costs[kept].min(axis=0)[seen] >= misfit).mean())
        info["unexplained_share"] = round(unexplained, 4)
        lost = flow_noise > p.noise_factor * p.flow_sigma_px
        if unexplained > 0.5 or (parts and lost):
            why = (
                f"the kept motions fail {unexplained:.0%} of the points"
                if unexplained > 0.5
                else f"the optical flow follows none of the {len(kept)} motions (misfit {flow_noise:.0f} px)"
            )
            return RuleDecision("undecided", [], reason=f"no model explains the pair: {why}", info=info)
        if parts:
            shares = ", ".join(f"{s:.0%}" for s in info["part_shares"][1:])
            return RuleDecision(
                "AM",
                [],
                reason=f"{len(kept)} distinct motions (parts of {shares} of the points)",
                info=info,
                motions=motions,
                labels=labels,
            )
        moved = motions[0].displacement_m
        reason = f"one motion, moving points by {moved * 1000:.1f} mm (threshold {threshold * 1000:.1f} mm)"
        # ... and, as a part must, it must be needed in depth: staying still (the evidence's first
        # hypothesis, the identity) fails points it explains. A fit that slides along a surface depth
        # cannot fix (a sliver of a still mug beside a moving hand) moves points, but shows no motion.
        if moved > threshold and not needed(base, 0, part=False):
            moved, reason = 0.0, reason + ", but staying still explains the depth as well"
        decision = "RM" if moved > threshold else "NM"
        return RuleDecision(
            decision,
            [],
            reason=reason,
            info=info,
            motions=motions,
            labels=labels,
        )
