"""The stage cache: frame clouds and pair registrations kept between runs, keyed on what they depend on.

Incremental re-runs
-------------------
A :class:`StageCache` keeps each frame's cloud and each pair's registrations, keyed on exactly what
they depend on; pass the same cache to successive runs, and a change of a decision setting (rule,
``alpha``, ``min_fitness``, ``w``) only re-decides::

    cache = StageCache()
    result = Pipeline(registry, config).run(sequence, cache=cache)            # reads, segments, registers
    config2 = dataclasses.replace(config, rule_params=RuleParams(q_bar=0.2))
    result2 = Pipeline(registry, config2).run(sequence, cache=cache)          # decides only
"""

from __future__ import annotations

import threading
import weakref
from collections import OrderedDict
from typing import Any

from .types import Sequence

TABLES = ("frame", "register", "hands")


class StageCache:
    """Frame clouds and pair registrations kept between runs, keyed on everything they depend on; and
    the scores of a sequence's hand masks, which depend on its segmenter only.

    Used by :meth:`Pipeline.run` (``cache=``) and :meth:`Pipeline.redecide`; the keys are
    :meth:`Pipeline.frame_key` and :meth:`Pipeline.pair_key`, built from
    :data:`~artclass_core.config.STAGE_DEPENDENCIES`. Both tables are LRU-bounded (``max_frames``
    clouds, ``max_pairs`` registered pairs), so a cache can stay alive in a long-lived app. Each
    registered pair also owns a scratch dict (:meth:`scratch`) that a decision rule keeps its
    threshold-independent evidence in; it goes when the pair's entry goes. Sequences are told apart by
    identity (the same :class:`Sequence` object), never by path, so two in-memory sequences can never
    share entries. Thread-safe.

    Parameters
    ----------
    max_frames : int
        Frames (clouds) kept; each is a preprocessed cloud, typically 50-500 kB.
    max_pairs : int
        Registered pairs kept; each holds its cells' transforms and point indices, or its motion evidence.
    """

    def __init__(self, *, max_frames: int = 512, max_pairs: int = 1024):
        self.max_frames, self.max_pairs = max_frames, max_pairs
        self._tables: dict[str, OrderedDict[tuple, Any]] = {t: OrderedDict() for t in TABLES}
        self._limits = {"frame": max_frames, "register": max_pairs, "hands": max_frames}
        self._scratch: dict[tuple, dict] = {}
        self._lock = threading.Lock()
        self._tokens: dict[int, int] = {}  # id(sequence) -> token, dropped when the sequence dies
        self._next_token = 0
        self.hits = {t: 0 for t in TABLES}
        self.misses = {t: 0 for t in TABLES}

    def sequence_token(self, sequence: Sequence) -> int:
        """A number that stands for ``sequence`` (this very object) in the keys."""
        with self._lock:
            key = id(sequence)
            if key not in self._tokens:
                self._tokens[key] = self._next_token
                self._next_token += 1
                # The finalizer holds the cache weakly: a cache dropped by its user is freed at once,
                # not kept (with every cloud in it) for as long as the sequence lives.
                weakref.finalize(sequence, _forget_in, weakref.ref(self), key)
            return self._tokens[key]

    def get(self, stage: str, key: tuple) -> Any | None:
        """The entry of ``stage`` (``"frame"``, ``"register"`` or ``"hands"``) under ``key``, or None
        (counted as a miss)."""
        with self._lock:
            table = self._tables[stage]
            value = table.get(key)
            if value is None:
                self.misses[stage] += 1
            else:
                table.move_to_end(key)
                self.hits[stage] += 1
            return value

    def put(self, stage: str, key: tuple, value: Any) -> None:
        """Keep ``value`` under ``key``; the least recently used entries beyond the limit are dropped."""
        with self._lock:
            table = self._tables[stage]
            table[key] = value
            table.move_to_end(key)
            while len(table) > self._limits[stage]:
                self._drop(stage, table.popitem(last=False)[0])

    def scratch(self, pair_key: tuple) -> dict:
        """The scratch dict of the registered pair under ``pair_key``: it lives as long as the pair's
        entry, so a rule finds its evidence again when the pair is re-decided."""
        with self._lock:
            return self._scratch.setdefault(pair_key, {})

    def _drop(self, stage: str, key: tuple) -> None:
        if stage == "register":
            self._scratch.pop(key, None)

    def _forget(self, sequence_id: int) -> None:
        with self._lock:
            token = self._tokens.pop(sequence_id, None)
            if token is None:
                return
            for stage, table in self._tables.items():
                for k in [k for k in table if k[0] == token]:
                    del table[k]
                    self._drop(stage, k)

    def clear(self) -> None:
        with self._lock:
            for table in self._tables.values():
                table.clear()
            self._scratch.clear()

    def stats(self) -> dict[str, Any]:
        """Entries held and hits/misses per stage."""
        with self._lock:
            return dict(
                frames=len(self._tables["frame"]),
                pairs=len(self._tables["register"]),
                hits=dict(self.hits),
                misses=dict(self.misses),
            )


def _forget_in(cache: weakref.ref[StageCache], sequence_id: int) -> None:
    alive = cache()
    if alive is not None:
        alive._forget(sequence_id)
