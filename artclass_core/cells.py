"""Per-cell registration, the paper's step 3: one grid of cells of size x over a pair of clouds, and a
registration of each cell (after an optional whole-cloud pre-alignment)."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable

import numpy as np

from .errors import ArtclassError
from .geometry import diameter_of_vertices, grid_cells, hull_vertices, transform
from .interfaces import DecisionRule, Registrar
from .params import PipelineParams
from .types import CellMotion, Cloud, PairResult

CELLS_PER_DIAMETER = 5.0  # the paper's x = D / 5
MIN_CELL_SIZE_M = 1e-4


def cell_size(source: Cloud, target: Cloud, *, cell_size_m: float | None) -> float:
    """The cell size x (m): ``cell_size_m``, or 1/5 of the largest distance between points of the pair.

    The largest distance is taken over the two clouds' hull vertices, which gives exactly the diameter
    of the two clouds together.
    """
    if cell_size_m is not None:
        return cell_size_m
    vertices = np.concatenate([hull_vertices(source.points), hull_vertices(target.points)])
    return max(diameter_of_vertices(vertices) / CELLS_PER_DIAMETER, MIN_CELL_SIZE_M)


def prealign(source: Cloud, target: Cloud, registrar: Registrar) -> np.ndarray:
    """Whole-cloud motion ``T_target_from_source`` (4x4) found with ``registrar``, coarse to fine (cells
    of 1/2.5, 1/5 and 1/10 of the pair's extent), from the identity and from the centroid shift; the
    better fit (fitness, then RMSE) wins."""
    extent = float(np.linalg.norm(np.ptp(np.concatenate([source.points, target.points]), axis=0)))
    shift = np.eye(4)
    shift[:3, 3] = target.points.mean(0) - source.points.mean(0)
    best, best_key = np.eye(4), (-1.0, 0.0)
    for T in (np.eye(4), shift):
        for scale in (extent / 2.5, extent / 5, extent / 10):
            reg = registrar.register(
                transform(source.points, T),
                target.points,
                source_normals=None if source.normals is None else source.normals @ T[:3, :3].T,
                target_normals=target.normals,
                cell_size_m=scale,
            )
            T = reg.T_target_from_source @ T
        if (reg.fitness, -reg.rmse_m) > best_key:
            best, best_key = T, (reg.fitness, -reg.rmse_m)
    return best


def register_cells(
    source: Cloud, target: Cloud, registrar: Registrar, *, params: PipelineParams
) -> tuple[tuple[CellMotion, ...], float]:
    """Register each cell of the pair's grid; returns the cells (no fitness check) and x (m).

    With ``params.prealign`` the source is first moved by the whole-cloud motion (:func:`prealign`), so
    each cell's registration, which starts from the identity, only has to find the residual; a cell's
    transform is the composition, and its centre is given in the source frame. Cells with fewer than
    ``params.min_cell_points`` points in either cloud are not registered.
    """
    x = cell_size(source, target, cell_size_m=params.cell_size_m)
    T0 = prealign(source, target, registrar) if params.prealign else np.eye(4)
    moved = transform(source.points, T0)
    normals = None if source.normals is None else source.normals @ T0[:3, :3].T
    T0_inv = np.linalg.inv(T0)
    cells = []
    for key, centre, si, ti in grid_cells(moved, target.points, cell_size_m=x):
        cell = CellMotion(key, transform(centre[None], T0_inv)[0], si, ti)
        if min(len(si), len(ti)) < params.min_cell_points:
            cell.skipped = f"too few points ({len(si)} source, {len(ti)} target)"
        else:
            reg = registrar.register(
                moved[si],
                target.points[ti],
                source_normals=None if normals is None else normals[si],
                target_normals=None if target.normals is None else target.normals[ti],
                cell_size_m=x,
            )
            reg.T_target_from_source = reg.T_target_from_source @ T0
            cell.registration = reg
        cells.append(cell)
    return tuple(cells), x


def checked_cells(cells: Iterable[CellMotion], *, min_fitness: float) -> list[CellMotion]:
    """Copies of registered ``cells`` with the skip reasons of ``min_fitness``, and no cluster (a cell
    that was not registered keeps its reason)."""
    out = []
    for c in cells:
        reg, skipped = c.registration, c.skipped
        if reg is not None:
            skipped = (
                "no correspondence"
                if reg.n_correspondences == 0
                else f"low fitness {reg.fitness:.2f}"
                if reg.fitness < min_fitness
                else None
            )
        out.append(dataclasses.replace(c, skipped=skipped, cluster=None, key=None))
    return out


def scratch_kwargs(rule: DecisionRule, scratch: dict) -> dict[str, dict]:
    """The keyword that hands a rule the pair's scratch dict, for a rule that keeps evidence in it
    (:attr:`DecisionRule.uses_scratch`); none for the others."""
    return {"scratch": scratch} if getattr(rule, "uses_scratch", False) else {}


def decide_cells(
    rule: DecisionRule,
    i: int,
    j: int,
    cells: list[CellMotion],
    source: Cloud,
    target: Cloud,
    cell_size_m: float,
    between: tuple[Cloud | None, ...],
    *,
    alpha: float,
    scratch: dict,
) -> PairResult:
    """The alpha check and ``rule`` on copies of a registered pair's cells (see
    :meth:`artclass_core.pipeline.Pipeline.decide`)."""
    cells = [dataclasses.replace(c, cluster=None, key=None) for c in cells]
    pair = PairResult(i, j, "skipped", cells=cells, cell_size_m=cell_size_m, scratch=scratch)
    n_matched = sum(c.matched for c in cells)
    if not cells or n_matched == 0 or n_matched < alpha * len(cells):
        pair.reason = f"only {n_matched} of {len(cells)} cells matched (alpha = {alpha:g})"
        return pair
    extra = {"between": between} if rule.uses_frames_between and None not in between else {}
    out = rule.decide(cells, source=source, target=target, **extra, **scratch_kwargs(rule, scratch))
    if len(out.clusters) != len(cells):
        raise ArtclassError(
            f"rule {rule.name!r} returned {len(out.clusters)} clusters for {len(cells)} cells"
        )
    for c, k in zip(cells, out.clusters):
        c.cluster = k
        c.key = out.keys[k] if k is not None and k < len(out.keys) else None
    pair.decision, pair.reason, pair.info = out.decision, out.reason, out.info
    return pair
