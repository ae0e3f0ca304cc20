"""Hook specifications: the only way plugins, built-in or third-party, extend artclass.

Every ``register_*`` hook receives a ``register`` callback and calls it once per class it provides.
A registered class has a unique lowercase ``name``, a one-line ``description``, a frozen ``Params``
dataclass (subclass of :class:`artclass_core.params.Params`) and the one method of its kind; it is
constructed as ``cls(params)``. Base classes with the exact method signatures are in
:mod:`artclass_core.interfaces`. Hooks are called with keyword arguments only.
"""

from __future__ import annotations

import pluggy

hookspec = pluggy.HookspecMarker("artclass")
hookimpl = pluggy.HookimplMarker("artclass")


@hookspec
def register_readers(register) -> None:
    """Register dataset readers: classes with ``sequences(path) -> list[Sequence]``.

    ``sequences`` returns an empty list when the path is not in the reader's layout, and raises
    :class:`~artclass_core.errors.InputError` (naming the file) when it is but the data is bad.
    """


@hookspec
def register_segmenters(register) -> None:
    """Register segmenters: classes with ``segment(frame, *, sequence) -> ndarray[bool] (H, W) | None``.

    The mask marks the pixels of the handled object in ``frame``; ``None`` (or an empty mask) means
    no object was found and the frame is skipped. ``sequence`` gives access to neighbouring frames,
    for choosing the instance that is being manipulated.
    """


@hookspec
def register_preprocessors(register) -> None:
    """Register preprocessors: classes with ``process(frame, mask, *, intrinsics) -> Cloud``.

    Turns the masked depth into the object's point cloud in metres (camera frame), filtered and
    downsampled; the resolved parameter values go in ``Cloud.info``.
    """


@hookspec
def register_registrars(register) -> None:
    """Register registrars: classes with ``register(source, target, *, source_normals, target_normals,
    cell_size_m) -> Registration``.

    ``source`` (N, 3) and ``target`` (M, 3) are the points of one cell in frames i and i + k (metres),
    with their unit normals (or ``None``). ICP starts from the identity; the result maps source onto
    target. No correspondence at all is reported as ``n_correspondences = 0``.
    """


@hookspec
def register_rules(register) -> None:
    """Register decision rules: classes with ``decide(cells, *, source, target) -> RuleDecision``.

    ``cells`` are the pair's :class:`~artclass_core.types.CellMotion` (skipped ones included, with
    their reason); ``source`` and ``target`` are the two frames' :class:`~artclass_core.types.Cloud`.
    The rule returns the pair decision (``AM``, ``RM``, ``NM`` or ``skipped``) and the cluster of each
    matched cell.
    """


@hookspec
def register_commands(subparsers) -> None:
    """Add sub-commands to the ``artclass`` command line.

    ``subparsers`` is an :mod:`argparse` sub-parsers object; call ``subparsers.add_parser(...)`` and
    ``set_defaults(func=handler)`` where ``handler(args) -> int`` returns the exit status.
    """


@hookspec
def register_joint_estimators(register) -> None:
    """Register joint estimators: classes with ``estimate(poses, *, n_independent=None) -> JointEstimate``.

    ``poses`` (N, 4, 4) are a moving part's poses in its parent's frame over the video (metres, NaN
    where unknown), of which ``n_independent`` carry independent errors (None: all; an ``estimate``
    without the argument is called without it); the estimator returns the joint type, its axis, the joint state per frame
    (radians or metres, relative to the first known frame) and their uncertainties, as an
    :class:`~artclass_core.interfaces.JointEstimate`.
    """


@hookspec
def register_part_finders(register) -> None:
    """Register part finders: classes with ``find(result, *, estimator) -> Articulation``.

    ``result`` is a finished :class:`~artclass_core.types.RunResult` made with ``keep_clouds=True``;
    ``estimator`` is the :class:`~artclass_core.interfaces.JointEstimator` to fit each joint with.
    The finder returns the parts (the base first), the joints between them (metres, radians, in the
    base's coordinates of the first frame) and each frame's part image, as an
    :class:`~artclass_core.articulation.Articulation`. Its class attribute ``needs`` names what the
    run's rule must decide from (``"motions"``, ``"cells"`` or ``"any"``).
    """
