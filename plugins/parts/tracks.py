"""Step 1, tracks: which motions of which pairs are one part."""

from __future__ import annotations

from typing import Any

import numpy as np

from artclass_core import RunResult

from .observations import _Observation


def _overlaps(a: _Observation, b: _Observation) -> list[tuple[float, tuple, tuple]]:
    """(IoU, node a, node b) of every pair of motions of two labellings of one or neighbouring frames,
    over the pixels both label."""
    from ._compiled import contingency  # Numba, loaded on first use

    if not len(a.labels) or not len(b.labels):
        return []
    table = contingency(*a.keys, np.asarray(a.labels, np.int64), *b.keys, np.asarray(b.labels, np.int64))
    in_a, in_b = table.sum(axis=1)[1:], table.sum(axis=0)[1:]  # row and column 0: no motion
    table = table[1:, 1:]
    m, n = np.nonzero(table)
    iou = table[m, n] / (in_a[m] + in_b[n] - table[m, n])
    return [(float(x), (a.pair, int(i)), (b.pair, int(j))) for x, i, j in zip(iou, m, n)]


class _Groups:
    """Disjoint groups of nodes (union-find), each holding a set of pairs: two groups are joined only
    when they hold no pair in common (one part has at most one motion in a pair)."""

    def __init__(self, pairs: dict[Any, set[int]]):
        self.parent = {n: n for n in pairs}
        self.pairs = {n: set(p) for n, p in pairs.items()}  # by root

    def root(self, n):
        while self.parent[n] != n:
            self.parent[n] = self.parent[self.parent[n]]
            n = self.parent[n]
        return n

    def join(self, a, b) -> None:
        ra, rb = self.root(a), self.root(b)
        if ra != rb and not self.pairs[ra] & self.pairs[rb]:
            self.parent[rb] = ra
            self.pairs[ra] |= self.pairs.pop(rb)


def _tracks(observations: list[_Observation], *, min_overlap: float) -> dict[tuple, int]:
    """Track number of every node (pair, motion): greedy merging by overlap, largest first, never two
    motions of one pair in one track."""
    nodes = {(o.pair, int(m)) for o in observations for m in o.motions}
    by_frame: dict[int, list[_Observation]] = {}
    for o in observations:
        by_frame.setdefault(o.frame, []).append(o)
    edges = []
    for f, here in by_frame.items():
        for x in range(len(here)):
            for y in range(x + 1, len(here)):
                if here[x].pair != here[y].pair:
                    edges += _overlaps(here[x], here[y])
        for other in by_frame.get(f + 1, []):
            for o in here:
                if o.pair != other.pair:
                    edges += _overlaps(o, other)
    groups = _Groups({n: {n[0]} for n in nodes})
    root = groups.root

    def merge(edges):
        for iou, a, b in sorted(edges, key=lambda e: -e[0]):
            if iou < min_overlap:
                break
            groups.join(a, b)

    merge(edges)
    # a part hidden for a while: the track that ends before another begins, on the frames either side
    frames: dict[tuple, set] = {}
    for o in observations:
        for m in o.motions:
            frames.setdefault(root((o.pair, int(m))), set()).add(o.frame)
    gaps = []
    for ra, fa in frames.items():
        for rb, fb in frames.items():
            if ra != rb and max(fa) < min(fb) and not groups.pairs[ra] & groups.pairs[rb]:
                gaps += [
                    e
                    for x in by_frame[max(fa)]
                    for y in by_frame[min(fb)]
                    for e in _overlaps(x, y)
                    if root(e[1]) == ra and root(e[2]) == rb
                ]
    merge(gaps)
    roots = sorted({root(n) for n in nodes})
    return {n: roots.index(root(n)) for n in nodes}


def _track_sizes(observations: list[_Observation], track: dict[tuple, int]) -> dict[int, int]:
    """Labelled points of each track over all frames."""
    size: dict[int, int] = {}
    for o in observations:
        for m in o.motions:
            t = track[(o.pair, int(m))]
            size[t] = size.get(t, 0) + int(o.counts[m])
    return size


def _seen_tracks(result: RunResult, track: dict[tuple, int], *, min_pairs: int) -> set[int]:
    """The parts of an articulated object: the tracks found in at least ``min_pairs`` AM pairs."""
    count: dict[int, int] = {}
    for (pair, _), t in track.items():
        count[t] = count.get(t, 0) + (result.pairs[pair].decision == "AM")
    return {t for t, n in count.items() if n >= min_pairs}
