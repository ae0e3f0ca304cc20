"""Joints: which way a moving part moves relative to its parent, and how far.

The built-in joint estimator fits the fixed, prismatic, revolute and screw models to the part's poses
and chooses one by BIC (:func:`fit_joint`). :mod:`artclass_core.joint_metrics` compares an estimate with the truth and
:mod:`.urdf` writes a model of parts and joints as a URDF.
"""

from artclass_core import hookimpl
from artclass_core.interfaces import JointEstimate, JointEstimator

from .models import MODELS, BICJointParams, fit_joint


class BICJointEstimator(JointEstimator):
    """Fixed, prismatic, revolute or screw joint, chosen by BIC (Sturm, Stachniss & Burgard 2011)."""

    name = "bic"
    description = (
        "fits fixed, prismatic, revolute and screw joints to the part's poses and keeps the best by BIC"
    )
    Params = BICJointParams

    def estimate(self, poses, *, n_independent=None, reach_m=None) -> JointEstimate:
        return fit_joint(poses, n_independent=n_independent, reach_m=reach_m, params=self.params)


@hookimpl
def register_joint_estimators(register):
    register(BICJointEstimator)


@hookimpl
def register_commands(subparsers):
    from .export import register_commands as add_export  # imports the command line only when it is built

    add_export(subparsers)


__all__ = ["BICJointEstimator", "BICJointParams", "MODELS", "fit_joint"]
