"""How far the robust rule's optical flow lands from the truth, on synthetic rigid carries.

    .venv/bin/python benchmarks/flow_accuracy.py [ROOT] [--k 5]

ROOT is a benchmark folder written by ``artclass sample ROOT --preset benchmark-vga`` (default
``benchmark_data/vga``). For every pair (i, i + k) of every rigid carry, each cloud point's flow
(:func:`artclass_plugins.rules.flow.flow_targets`, chained through the frames between as the rule
does) is compared with where the recorded object poses put the point, where the camera still sees
it there. Prints, per noise level and for 2-D texture (the flow in full) and edges (across the edge
only): error percentiles in full-resolution pixels, by how far the point moved, and the share of
points beyond the tolerance the rule allows (``FLOW_ERROR_PX``, ``FLOW_ERROR_SHARE``). Prints numbers;
never fails.
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from artclass_core import Config, Pipeline, find_sequences, load_registry
from artclass_core.geometry import transform
from artclass_plugins.rules.flow import flow_targets, offset_px


def errors(pipe: Pipeline, seq, poses: list[np.ndarray], k: int):
    """(error px, shift px, tolerance px, is edge) of every point with flow whose truth is visible."""
    clouds = [pipe.frame(seq, i).cloud for i in range(len(seq))]
    for i in range(len(seq) - k):
        src, tgt = clouds[i], clouds[i + k]
        if src is None or tgt is None or None in clouds[i + 1 : i + k]:
            continue
        ev = flow_targets(src, tgt, src.points, between=tuple(clouds[i + 1 : i + k]))
        K, depth = src.view.intrinsics, tgt.view.depth_m
        true = transform(src.points, poses[i + k] @ np.linalg.inv(poses[i]))
        ut, vt = K.pixels(true)
        u0, v0 = K.pixels(src.points)
        ui, vi = np.round(ut).astype(int), np.round(vt).astype(int)
        inside = (ui >= 0) & (ui < depth.shape[1]) & (vi >= 0) & (vi < depth.shape[0])
        seen = np.zeros(len(true), bool)
        seen[inside] = np.abs(depth[vi[inside], ui[inside]] - true[inside, 2]) < 0.01
        err = offset_px(ev.pixel[:, 0] - ut, ev.pixel[:, 1] - vt, ev.normal)
        use = seen & np.isfinite(ev.pixel[:, 0])
        yield (
            err[use],
            np.hypot(ut - u0, vt - v0)[use],
            (ev.tol * K.fx / src.points[:, 2])[use],
            ev.edge[use],
        )


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("root", nargs="?", default="benchmark_data/vga")
    p.add_argument("--k", type=int, default=5)
    args = p.parse_args()
    registry = load_registry()
    pipe = Pipeline(registry, Config())
    seqs, _ = find_sequences(registry, args.root)
    rows: dict[str, list] = {}
    for seq in seqs:
        meta = json.loads((seq.path / "meta.json").read_text())
        if meta.get("label") != "rigid" or meta.get("motion") != "carry":
            continue
        poses = [np.array(T) for T in json.loads((seq.path / "truth.json").read_text())["object_poses"]]
        rows.setdefault(meta["noise"], []).extend(errors(pipe, seq, poses, args.k))
    for noise, parts in rows.items():
        err, shift, tol, edge = (np.concatenate(x) for x in zip(*parts))
        for name, kind in (("2-D texture", ~edge), ("edge, across", edge)):
            e, s, t = err[kind], shift[kind], tol[kind]
            pct = " / ".join(f"{x:.2f}" for x in np.percentile(e, [50, 90, 95, 99]))
            print(
                f"{noise} noise, {name}: {len(e)} points, error px p50/p90/p95/p99 {pct}, "
                f"beyond tolerance {np.mean(e > t):.1%}"
            )
            for lo, hi in ((0, 5), (5, 15), (15, 40), (40, np.inf)):
                sel = (s >= lo) & (s < hi)
                if sel.sum() >= 20:
                    print(
                        f"    moved {lo}-{hi} px: {sel.sum()} points, error p90 {np.percentile(e[sel], 90):.2f} px, "
                        f"tolerance median {np.median(t[sel]):.2f} px, beyond it {np.mean(e[sel] > t[sel]):.1%}"
                    )


if __name__ == "__main__":
    main()
