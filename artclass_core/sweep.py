"""Parameter sweeps over whole datasets, on the local cores or on a Dask cluster.

A sweep runs every labelled sequence for every setting of a grid and writes one tidy table, one row
per (sequence, setting), as it goes::

    settings = grid_settings(registry, {"q_bar": ["0.05", "0.1", "0.2"]}, rule="paper")
    table = sweep(registry, sequences, settings, out="results.parquet")

Work is split into one task per sequence, which runs all of that sequence's settings with one
:class:`~artclass_core.pipeline.StageCache`: frames are read, segmented and preprocessed once for all
the settings that share those stages, and a setting that changes only the decision (the rule and its
parameters, ``alpha``, ``min_fitness``, ``w``) decides again from the cached registrations. Settings
are run in an order that keeps the settings sharing stages together, so the cache need hold only one
sequence's frames and pairs.

The table is rewritten atomically after every row, so an interrupted sweep loses no finished row,
and running the same sweep again skips the rows already in the table. Every row is computed by the
same deterministic function whatever runs it (the local cores, a ``LocalCluster``, a remote
cluster), so the table is identical but for the timing columns.
"""

from __future__ import annotations

import itertools
import json
import logging
import os
from collections.abc import Collection, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import pandas as pd

from .cache import StageCache
from .config import PLUGIN_KINDS, STAGES, Config, stage_config
from .errors import ArtclassError, InputError, ParamError
from .evaluate import SequenceOutcome, one_line, run_outcome
from .pipeline import Pipeline
from .plugins import Registry, load_registry
from .scheduler import Progress
from .sequences import open_sequences
from .types import DECISIONS, Sequence

DASK_HINT = "pip install 'artclass[dask]'"
KEY_COLUMNS = ("path", "sequence", "recipe")
TABLE_SUFFIXES = (".parquet", ".csv")
DECISION_LETTERS = {
    "AM": "A",
    "RM": "R",
    "NM": "N",
    "undecided": "?",
    "skipped": "-",
}  # the ``decisions`` column


@dataclass(frozen=True)
class Setting:
    """One point of a sweep: the plugins and the parameter values (as text, by name or paper symbol).

    ``grid`` holds the values of the swept names only (what the setting is called in tables and
    figures); ``plugins`` and ``params`` are everything needed to build the :class:`Config`.
    """

    plugins: tuple[tuple[str, str], ...]
    params: tuple[tuple[str, str], ...]
    grid: tuple[tuple[str, str], ...] = ()

    def config(self, registry: Registry) -> Config:
        """The pipeline configuration of this setting (raises :class:`ParamError` on a bad value)."""
        return Config(**dict(self.plugins)).with_overrides(registry, dict(self.params))

    @property
    def label(self) -> str:
        """``q_bar=0.1, k=3``: the swept values (``default`` when nothing is swept)."""
        return ", ".join(f"{k}={v}" for k, v in self.grid) or "default"

    @property
    def recipe(self) -> str:
        """Everything that defines the setting, as canonical JSON: the key a resumed sweep matches on."""
        return json.dumps(
            dict(plugins=dict(self.plugins), params=dict(self.params), grid=list(self.grid)), sort_keys=True
        )


def parse_grid(items: Iterable[str]) -> dict[str, list[str]]:
    """``["q_bar=0.05,0.1", "k=3,5"]`` -> ``{"q_bar": ["0.05", "0.1"], "k": ["3", "5"]}``.

    Raises :class:`ArtclassError` on an item that is not ``NAME=V1,V2,...`` or a name given twice.
    """
    grid: dict[str, list[str]] = {}
    for item in items:
        name, sep, values = item.partition("=")
        name = name.strip()
        vals = [v.strip() for v in values.split(",") if v.strip()]
        if not sep or not name or not vals:
            raise ArtclassError(f"--grid {item!r}: expected NAME=V1,V2,...")
        if name in grid:
            raise ArtclassError(f"--grid {name} is given twice")
        grid[name] = list(dict.fromkeys(vals))
    return grid


def grid_settings(
    registry: Registry, grid: dict[str, list[str]], *, params: dict[str, str] | None = None, **plugins: str
) -> list[Setting]:
    """Every combination of ``grid`` (the last name varies fastest), on top of ``plugins`` and ``params``.

    A grid name is a parameter (by name or paper symbol) or a plugin kind (``rule=dense,paper``).
    Every setting is checked here, so a bad name or value fails before anything runs.
    """
    base = {kind: plugins.get(kind, getattr(Config(), kind)) for kind in PLUGIN_KINDS}
    out = []
    for values in itertools.product(*grid.values()):
        chosen = dict(zip(grid, values))
        setting = Setting(
            plugins=tuple({**base, **{k: v for k, v in chosen.items() if k in PLUGIN_KINDS}}.items()),
            params=tuple(
                {**(params or {}), **{k: v for k, v in chosen.items() if k not in PLUGIN_KINDS}}.items()
            ),
            grid=tuple(chosen.items()),
        )
        for kind, name in setting.plugins:
            if not (kind == "segmenter" and name == "auto"):
                registry.get(kind, name)  # an unknown plugin: PluginError naming the registered ones
        try:
            setting.config(registry)
        except ArtclassError as exc:
            raise type(exc)(f"setting {setting.label}: {exc}" if grid else str(exc)) from None
        out.append(setting)
    return out


# -- one sequence, all its settings: the unit of work ------------------------------------------------


@dataclass(frozen=True)
class SequenceSource:
    """Where a worker finds a sequence: a path it can see, the sequence's name there, the reader and the
    reader parameters it was opened with."""

    path: str
    name: str
    reader: str | None = None
    reader_values: tuple[tuple[str, str], ...] = ()

    @classmethod
    def of(cls, sequence: Sequence, *, reader: str | None = None) -> SequenceSource:
        opened_by, values = sequence.opened_with
        return cls(*_where(sequence), opened_by or reader, values)

    def open(self, registry: Registry) -> Sequence:
        values = dict(self.reader_values)
        found = [
            s
            for s in open_sequences(registry, self.path, reader=self.reader, reader_values=values)
            if s.name == self.name
        ]
        if not found:
            raise InputError(f"no sequence named {self.name!r} here", path=self.path)
        return found[0]


def sequence_rows(
    registry: Registry, sequence: Sequence | SequenceSource, settings: list[Setting], *, workers: int = 1
) -> Iterator[tuple[int, dict[str, Any], SequenceOutcome]]:
    """Run one sequence under every setting, sharing its stage cache; yields ``(setting index, row,
    outcome)`` as each setting finishes. A failure is recorded in the row's ``error``, never raised."""
    source = sequence if isinstance(sequence, SequenceSource) else SequenceSource.of(sequence)
    try:
        seq = sequence.open(registry) if isinstance(sequence, SequenceSource) else sequence
        plan = _plan(registry, seq, [s.config(registry) for s in settings])
    except Exception as exc:  # an unreadable sequence: every setting of it is a failed row
        for n, setting in enumerate(settings):
            outcome = SequenceOutcome(source.name, source.name, "", (), None, error=one_line(exc))
            yield n, _row(source, setting, outcome, None), outcome
        return
    try:
        for n, pipeline, cache in plan:
            outcome, result = run_outcome(pipeline, seq, workers=workers, cache=cache)
            yield n, _row(source, settings[n], outcome, result), outcome
    finally:
        seq.forget_frames()  # the caller may keep the sequence open (evaluating a whole folder does)


def _plan(
    registry: Registry, sequence: Sequence, configs: list[Config]
) -> list[tuple[int, Pipeline, StageCache]]:
    """The order to run ``configs`` in, each with its pipeline and the stage cache it uses.

    Settings with the same frame stages run one after another, and within them those with the same
    registrations, so a cache of one sequence's frames and pairs suffices. Two settings whose
    registrations differ but whose pair cache keys are equal never share a cache.
    """
    probe = StageCache()
    pipelines = [Pipeline(registry, c) for c in configs]
    frame_keys = [p.frame_key(sequence, 0, probe)[2:] for p in pipelines]
    registrations = [
        stage_config(p.config, "register") for p in pipelines
    ]  # what the registrations depend on
    order = sorted(
        range(len(configs)),
        key=lambda n: (frame_keys.index(frame_keys[n]), registrations.index(registrations[n])),
    )
    size = len(sequence) + 1
    caches: list[tuple[dict[tuple, Config], StageCache]] = []
    plan = []
    for n in order:
        p = pipelines[n]
        key = p.pair_key(sequence, 0, p.params.k, probe)
        cache = next(
            (c for seen, c in caches if seen.setdefault(key, registrations[n]) == registrations[n]), None
        )
        if cache is None:
            cache = StageCache(max_frames=size, max_pairs=size)
            caches.append(({key: registrations[n]}, cache))
        plan.append((n, p, cache))
    return plan


def _row(source: SequenceSource, setting: Setting, o: SequenceOutcome, result) -> dict[str, Any]:
    plugins = dict(result.plugins) if result is not None else dict(setting.plugins)
    timing = result.timing_s if result is not None else {}
    grid = {k: v for k, v in setting.grid if k not in PLUGIN_KINDS}  # a swept plugin has its own column
    return dict(
        sequence=o.name,
        object=o.object,
        path=source.path,
        setting=setting.label,
        **grid,
        **{kind: plugins[kind] for kind in PLUGIN_KINDS},
        label=o.predicted,
        truth=o.truth,
        accepted=",".join(o.accepted),
        correct=o.correct,
        **{d: o.fractions.get(d, float("nan")) if o.fractions else float("nan") for d in DECISIONS},
        pair_correct=o.pair_correct,
        pair_total=o.pair_total,
        pair_accuracy=o.pair_correct / o.pair_total if o.pair_total else float("nan"),
        n_pairs=o.n_pairs,
        skipped_pairs=sum(p.decision == "skipped" for p in result.pairs) if result is not None else 0,
        decisions="".join(DECISION_LETTERS[p.decision] for p in result.pairs) if result is not None else None,
        **{f"time_{s}_s": float(timing.get(s, float("nan"))) for s in (*STAGES, "total")},
        seconds=o.seconds,
        error=o.error,
        params=json.dumps(result.params, sort_keys=True, default=str) if result is not None else None,
        recipe=setting.recipe,
    )


def _task(
    source: SequenceSource, settings: list[Setting], workers: int
) -> list[tuple[int, dict, SequenceOutcome]]:
    """What a Dask worker runs: one sequence, all its settings."""
    return list(sequence_rows(_worker_registry(), source, settings, workers=workers))


@lru_cache(maxsize=1)
def _worker_registry() -> Registry:
    return load_registry()


# -- running the tasks: here, or on a Dask cluster ----------------------------------------------------

Task = tuple[int, Sequence, list[int]]  # (sequence index, sequence, indices of the settings to run)


def plan_tasks(
    registry: Registry,
    sequences: list[Sequence],
    settings: list[Setting],
    *,
    done: Collection[tuple[str, str, str]] = (),
) -> list[Task]:
    """The tasks of a sweep: one per sequence and frame stages (segmenter, preprocessor and their
    params), since settings with other frame stages share nothing; the settings of a row in ``done``
    (``(path, sequence, recipe)``) are left out."""
    stages = [_frame_stages(st.config(registry)) for st in settings]
    tasks = []
    for i, seq in enumerate(sequences):
        groups: dict[tuple, list[int]] = {}
        for m, st in enumerate(settings):
            if (*_where(seq), st.recipe) not in done:
                groups.setdefault(stages[m], []).append(m)
        tasks += [(i, seq, chosen) for chosen in groups.values()]
    return tasks


def _frame_stages(config: Config) -> tuple:
    return config.segmenter, config.segmenter_params, config.preprocessor, config.preprocessor_params


def _where(sequence: Sequence) -> tuple[str, str]:
    """``(path, name)``: the sequence in the table's ``path`` and ``sequence`` columns."""
    return str(Path(sequence.path).resolve()), sequence.name


def run_tasks(
    registry: Registry,
    tasks: list[Task],
    settings: list[Setting],
    *,
    scheduler=None,
    workers: int = 1,
    reader: str | None = None,
    lost: list[str] | None = None,
) -> Iterator[tuple[int, int, dict[str, Any], SequenceOutcome]]:
    """Run every task, yielding ``(sequence index, setting index, row, outcome)`` as rows finish.

    Without ``scheduler`` the tasks run here, one after another, each on ``workers`` threads. With a
    scheduler address, ``"local"`` (a ``LocalCluster`` with one single-threaded worker per CPU) or a
    ``distributed.Client``, each task is one Dask task. A task lost to the cluster (a worker died, the
    scheduler went away) is not raised: its sequence's name and the error are appended to ``lost``.
    """
    if not (isinstance(workers, int) and workers >= 1):  # here, not as a failed row in every task
        raise ParamError(f"workers = {workers!r} must be a positive integer")
    if scheduler is None:
        for i, seq, chosen in tasks:
            for n, row, outcome in sequence_rows(
                registry, seq, [settings[m] for m in chosen], workers=workers
            ):
                yield i, chosen[n], row, outcome
        return
    with dask_client(scheduler) as client:
        from distributed import as_completed

        futures = {
            client.submit(
                _task,
                SequenceSource.of(seq, reader=reader),
                [settings[m] for m in chosen],
                workers,
                pure=False,
            ): (i, seq, chosen)
            for i, seq, chosen in tasks
        }
        for future in as_completed(futures):
            i, seq, chosen = futures[future]
            try:
                done = future.result()
            except Exception as exc:
                if lost is None:
                    raise
                lost.append(f"{seq.name}: {one_line(exc)}")
                continue
            for n, row, outcome in done:
                yield i, chosen[n], row, outcome


@contextmanager
def dask_client(scheduler):
    """A ``distributed.Client`` for ``scheduler``: ``"local"`` starts a ``LocalCluster`` (closed on exit),
    an address connects to a running scheduler, and a ``Client`` is used as it is."""
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise ArtclassError(f"--scheduler needs Dask, which is not installed: {DASK_HINT}") from None
    if isinstance(scheduler, Client):
        yield scheduler
    elif scheduler == "local":
        with (
            LocalCluster(
                n_workers=os.cpu_count() or 1,
                threads_per_worker=1,
                dashboard_address=None,
                silence_logs=logging.ERROR,
            ) as cluster,
            Client(cluster) as client,
        ):
            yield client
    else:
        try:
            client = Client(scheduler, timeout="20s")
        except (OSError, TimeoutError, ValueError) as exc:
            raise ArtclassError(f"cannot reach the Dask scheduler at {scheduler}: {one_line(exc)}") from None
        with client:
            yield client


# -- the sweep and its table ------------------------------------------------------------------------


def sweep(
    registry: Registry,
    sequences: list[Sequence],
    settings: list[Setting],
    *,
    out: str | Path,
    scheduler=None,
    workers: int = 1,
    force: bool = False,
    reader: str | None = None,
    progress: Progress | None = None,
    lost: list[str] | None = None,
) -> pd.DataFrame:
    """Run every sequence under every setting, writing the table to ``out`` (``.parquet`` or ``.csv``)
    after each row; rows already in ``out`` are kept and not run again unless ``force``.

    Returns the table: the rows of ``out`` (rows of other settings or sequences included), this
    sweep's rows first, in sequence order and then grid order. ``progress("rows", done, total)`` is
    called as rows finish; ``scheduler`` and ``lost`` are as in :func:`run_tasks`.
    """
    out = Path(out)
    if out.suffix not in TABLE_SUFFIXES:
        raise ArtclassError(f"{out}: the table is written as {' or '.join(TABLE_SUFFIXES)}")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ArtclassError(
            f"{out.parent}: cannot create the folder of the table ({one_line(exc)})"
        ) from None
    table = read_table(out) if out.exists() else pd.DataFrame()
    wanted = {
        (*_where(s), st.recipe): (i, m) for i, s in enumerate(sequences) for m, st in enumerate(settings)
    }
    rows = table.to_dict("records") if len(table) else []
    if force:
        rows = [r for r in rows if _key(r) not in wanted]
    tasks = plan_tasks(registry, sequences, settings, done={_key(r) for r in rows})
    total = sum(len(c) for _, _, c in tasks)
    if progress:
        progress("rows", 0, total)
    for n, (_, _, row, _) in enumerate(
        run_tasks(registry, tasks, settings, scheduler=scheduler, workers=workers, reader=reader, lost=lost),
        1,
    ):
        rows.append(row)
        write_table(_ordered(rows, wanted), out)
        if progress:
            progress("rows", n, total)
    table = _ordered(rows, wanted)
    write_table(table, out)
    return table


def _key(row: dict[str, Any]) -> tuple[str, str, str]:
    return tuple(row[c] for c in KEY_COLUMNS)


def _ordered(rows: list[dict[str, Any]], wanted: dict[tuple, tuple[int, int]]) -> pd.DataFrame:
    last = (len(wanted), 0)
    ranked = sorted(enumerate(rows), key=lambda nr: (wanted.get(_key(nr[1]), last), nr[0]))
    return pd.DataFrame([r for _, r in ranked])


def read_table(source) -> pd.DataFrame:
    """A sweep's table, from ``.parquet`` or ``.csv``: a path, or a binary file object with a ``name``
    (an upload). Raises :class:`InputError` naming the file if it is not a sweep's table."""
    name = Path(getattr(source, "name", None) or source)
    try:
        if name.suffix == ".csv":  # the swept values are text, as in the Parquet table
            names = swept_names(pd.read_csv(source, usecols=["recipe"]))
            if hasattr(source, "seek"):
                source.seek(0)
            table = pd.read_csv(source, dtype={n: str for n in names})
        else:
            table = pd.read_parquet(source)
    except (OSError, ValueError, KeyError) as exc:
        raise InputError(f"not a readable sweep table ({one_line(exc)})", path=name) from None
    missing = [c for c in (*KEY_COLUMNS, "setting", "correct") if c not in table.columns]
    if missing:
        raise InputError(f"not a sweep table: no column {', '.join(missing)}", path=name)
    return table


def write_table(table: pd.DataFrame, path: str | Path) -> None:
    """Write ``table`` to ``path`` atomically (a temporary file renamed over it), so that an interrupted
    write leaves the previous table whole."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    if path.suffix == ".csv":
        table.to_csv(tmp, index=False)
    else:
        table.to_parquet(tmp, index=False)
    os.replace(tmp, path)


# -- summaries and the figure -----------------------------------------------------------------------


def swept_names(table: pd.DataFrame) -> list[str]:
    """The names swept in ``table`` (from each row's recipe), in grid order."""
    names: dict[str, None] = {}
    for recipe in table["recipe"].drop_duplicates():
        names.update(dict.fromkeys(name for name, _ in json.loads(recipe)["grid"]))
    return list(names)


def summary(table: pd.DataFrame) -> pd.DataFrame:
    """One row per setting: sequences, errors, sequence accuracy, pair accuracy, mean pair fractions and
    the time spent (seconds, summed over the sequences), in the table's order."""
    groups = table.groupby("recipe", sort=False)
    out = pd.DataFrame(
        {
            "setting": groups["setting"].first(),
            **{name: groups[name].first() for name in swept_names(table) if name in table.columns},
            "sequences": groups.size(),
            "errors": groups["error"].apply(lambda e: int(e.notna().sum())),
            "accuracy": groups["correct"].mean(),
            "pair_accuracy": groups["pair_correct"].sum() / groups["pair_total"].sum().where(lambda t: t > 0),
            **{d: groups[d].mean() for d in DECISIONS},
            "seconds": groups["seconds"].sum(),
        }
    )
    return out.reset_index(drop=True)
