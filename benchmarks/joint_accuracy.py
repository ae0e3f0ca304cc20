"""Accuracy and cost of the built-in joint estimator against pose noise, on synthetic joints.

    python benchmarks/joint_accuracy.py [--seeds 5] [--frames 60] [--outliers 3] [--turn-deg 74] [--slide-mm 300]

For each noise level and joint type (a turn 20 cm from the axis, a slide, no motion)
prints the share of right joint types and the median errors over the seeds: axis direction
(degrees), axis position at the part (mm), state (degrees or mm), and the CPU time of one fit (ms).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from artclass_core.joint_metrics import axis_direction_error_rad, axis_position_error_m, state_error
from artclass_plugins.joints import fit_joint
from artclass_plugins.joints.synthetic import synthetic_joint

NOISE = [(0.0005, 0.25), (0.001, 0.5), (0.002, 1.0), (0.005, 2.0)]  # (metres, degrees) per axis


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--outliers", type=int, default=3, help="wrong poses per sequence")
    parser.add_argument("--turn-deg", type=float, default=74.0, help="the revolute joint's turn")
    parser.add_argument("--slide-mm", type=float, default=300.0, help="the prismatic joint's travel")
    args = parser.parse_args()
    travels = {"revolute": np.radians(args.turn_deg), "prismatic": args.slide_mm / 1000, "fixed": 0.0}
    print(
        f"{args.frames} frames, {args.outliers} wrong poses, {args.seeds} seeds per row; "
        f"a {args.turn_deg:g} deg turn, a {args.slide_mm:g} mm slide\n"
    )
    print(
        "| noise (mm / deg) | joint | type right | axis direction (deg) | axis position (mm) | state "
        "| CPU per fit (ms) |"
    )
    print("|---|---|---|---|---|---|---|")
    for noise_m, noise_deg in NOISE:
        for kind, travel in travels.items():
            right, direction, position, state, cpu = [], [], [], [], []
            for seed in range(args.seeds):
                truth = synthetic_joint(
                    kind,
                    n_frames=args.frames,
                    travel=travel,
                    noise_m=noise_m,
                    noise_rad=np.radians(noise_deg),
                    n_outliers=args.outliers,
                    seed=seed,
                )
                start = time.process_time()
                est = fit_joint(truth.poses)
                cpu.append(1000 * (time.process_time() - start))
                right.append(est.type == kind)
                if kind == "fixed" or est.axis_direction is None:
                    continue
                direction.append(np.degrees(axis_direction_error_rad(truth.direction, est.axis_direction)))
                same = bool(truth.direction @ est.axis_direction > 0)
                error = state_error(truth.states, est.states, same_direction=same)
                state.append(np.degrees(error) if kind == "revolute" else 1000 * error)
                if kind == "revolute":
                    position.append(
                        1000
                        * axis_position_error_m(
                            truth.point_m,
                            truth.direction,
                            est.axis_point_m,
                            est.axis_direction,
                            at_m=truth.poses[0, :3, 3],
                        )
                    )
            unit = {"revolute": "deg", "prismatic": "mm"}.get(kind, "")

            def cell(v, u=""):
                return f"{np.median(v):.2f}{' ' + u if u else ''}" if v else "-"

            print(
                f"| {1000 * noise_m:g} / {noise_deg:g} | {kind} | {np.mean(right):.0%} | {cell(direction)} | "
                f"{cell(position)} | {cell(state, unit)} | {np.median(cpu):.0f} |"
            )


if __name__ == "__main__":
    main()
