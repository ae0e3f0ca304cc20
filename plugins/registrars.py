"""Registrars: Open3D ICP of one cell, from the identity."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from artclass_core import Params, Registrar, Registration, hookimpl, param

from .dense.registrar import DenseRegistrar
from .preprocessors import camera_facing_normals, to_o3d

reg = o3d.pipelines.registration

# Reproducible only with Open3D on one thread of its own: the pipeline sets that before it runs
# (artclass_core.scheduler.single_threaded_open3d); importing this module changes nothing.


@dataclass(frozen=True)
class ICPParams(Params):
    max_correspondence_cells: float = param(
        0.5,
        unit="x",
        bounds=(0.01, 5.0),
        help="ICP's maximum correspondence distance, as a fraction of the "
        "cell size x: the largest motion a cell can register.",
    )
    max_iterations: int = param(30, unit="iterations", bounds=(1, 1000), help="ICP iteration limit.")
    tolerance: float = param(
        1e-6,
        unit="1",
        bounds=(0.0, 1.0),
        help="ICP stops when fitness and RMSE change by less than this between iterations.",
    )


class _Open3DICP(Registrar):
    Params = ICPParams
    estimation: reg.TransformationEstimation

    centred = False  # solve about the source centroid (see PointToPlaneICP)

    def register(self, source, target, *, source_normals, target_normals, cell_size_m) -> Registration:
        p = self.params
        c = source.mean(axis=0) if self.centred and len(source) else np.zeros(3)
        src, tgt = to_o3d(source - c), to_o3d(target - c, target_normals)
        result = reg.registration_icp(
            src,
            tgt,
            p.max_correspondence_cells * cell_size_m,
            np.eye(4),
            self.estimation(),
            reg.ICPConvergenceCriteria(
                relative_fitness=p.tolerance, relative_rmse=p.tolerance, max_iteration=p.max_iterations
            ),
        )
        T = np.array(result.transformation)
        T[:3, 3] += c - T[:3, :3] @ c  # back to the camera frame: x -> R (x - c) + t + c
        return Registration(
            T, float(result.fitness), float(result.inlier_rmse), len(result.correspondence_set)
        )


class PointToPointICP(_Open3DICP):
    """Open3D point-to-point ICP (the paper's choice)."""

    name = "icp_point_to_point"
    description = "Open3D point-to-point ICP from the identity (the paper's registration)"
    estimation = reg.TransformationEstimationPointToPoint


class PointToPlaneICP(_Open3DICP):
    """Open3D point-to-plane ICP; uses the target normals computed by the preprocessor.

    Solved about the cell's source centroid: the point-to-plane step linearises the rotation about
    the origin, and about a camera a metre away a 3 degree turn of a 4 cm cell becomes centimetres of
    coupled translation that the step gets wrong, until no correspondence is left.
    """

    centred = True

    name = "icp_point_to_plane"
    description = "Open3D point-to-plane ICP from the identity (needs target normals)"
    estimation = reg.TransformationEstimationPointToPlane

    def register(self, source, target, *, source_normals, target_normals, cell_size_m) -> Registration:
        if target_normals is None:
            target_normals = camera_facing_normals(target, radius_m=cell_size_m / 2)
        return super().register(
            source,
            target,
            source_normals=source_normals,
            target_normals=target_normals,
            cell_size_m=cell_size_m,
        )


@hookimpl
def register_registrars(register):
    register(DenseRegistrar)
    register(PointToPointICP)
    register(PointToPlaneICP)
