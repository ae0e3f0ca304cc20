"""How long the app takes: a cold run of a sequence, and re-runs after moving a slider.

Prints numbers (no pass/fail). Runs the real app script headless through Streamlit's AppTest, in
this process, so the times are the server's (script + caches + pipeline), without the browser::

    .venv/bin/python -m app.benchmark                      # the first articulated bundled sample
    .venv/bin/python -m app.benchmark sample_data/NAME     # a given sequence folder
    .venv/bin/python -m app.benchmark --repeat 5
    .venv/bin/python -m app.benchmark --paper             # the paper's plugins instead of the defaults

Each slider is moved from the cold state's values; the re-run time is the median over ``--repeat``
moves back and forth. For comparison it also times ``Pipeline.run`` on the same sequence.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def _timed_run(at, timeout: float) -> float:
    t0 = time.perf_counter()
    at.run(timeout=timeout)
    seconds = time.perf_counter() - t0
    if at.exception or at.error:
        problems = [e.value for e in at.exception] + [e.value for e in at.error]
        raise SystemExit(f"the app reported: {problems}")
    return seconds


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m app.benchmark", description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "sequence", nargs="?", help="a sequence folder (default: the first articulated sample)"
    )
    parser.add_argument("--repeat", type=int, default=3, help="slider moves per measurement (default 3)")
    parser.add_argument(
        "--paper",
        action="store_true",
        help="the paper's pipeline as written (paper preprocessor and rule, no pre-alignment) "
        "instead of the default plugins",
    )
    parser.add_argument("--timeout", type=float, default=600.0)
    args = parser.parse_args(argv)

    import streamlit as st
    from streamlit.testing.v1 import AppTest

    from artclass_core import Config, Pipeline, load_registry, open_sequences

    if args.sequence:
        folder = Path(args.sequence).resolve()
        os.environ["ARTCLASS_SAMPLE_DATA"] = str(folder.parent)
    at = AppTest.from_file(str(ROOT / "app" / "streamlit_app.py"), default_timeout=args.timeout)
    if args.paper:
        at.session_state["cfg_plugin:preprocessor"] = "paper"
        at.session_state["cfg_plugin:rule"] = "paper"
        at.session_state["cfg_p:pipeline:core:prealign"] = False
    st.cache_data.clear()
    st.cache_resource.clear()
    t_first = _timed_run(at, args.timeout)  # imports, plugin registry, every stage
    if args.sequence:
        at.selectbox(key="an_sample").set_value(folder.name)
    st.cache_data.clear()
    t_cold = _timed_run(at, args.timeout)  # every stage computed, modules loaded
    name = at.title[0].value
    about = next(iter(at.caption)).value.split("·")
    rows = [
        ("first run of a fresh server (imports, registry, stages)", t_first),
        ("run of a new sequence (every stage computed)", t_cold),
        (
            "re-run, nothing changed (all cached)",
            statistics.median(_timed_run(at, args.timeout) for _ in range(args.repeat)),
        ),
    ]

    def move(key: str, values: list, title: str) -> None:
        """Set the slider to each value in turn (values not seen before: nothing cached for them)."""
        times = []
        for value in values[: args.repeat]:
            at.select_slider(key=key).set_value(value)
            times.append(_timed_run(at, args.timeout))
        rows.append((title, statistics.median(times)))

    def around(key: str, options: list) -> list:
        """Options next to the slider's value, alternately above and below (as a user nudges it)."""
        i = options.index(at.session_state[key])
        out = []
        for step in range(1, len(options)):
            out += [options[j] for j in (i + step, i - step) if 0 <= j < len(options)]
        return out

    from app import controls
    from artclass_core import describe

    rule = at.session_state["cfg_plugin:rule"]
    spec = next(
        (
            p
            for p in describe(load_registry().get("rule", rule).Params)
            if controls.widget_kind(p) == "slider"
        ),
        None,
    )
    if spec is not None:
        key = controls.value_key("rule", rule, spec.name)
        move(
            key,
            around(key, controls.slider_options(spec)),
            f"rule slider {spec.name} moved (re-decide, no ICP)",
        )
    move("cfg_p:pipeline:core:w", [1, 5, 7, 9, 11], "w moved (re-filter only)")
    at.checkbox(key="cfg_auto:pipeline:core:cell_size_m").uncheck()
    _timed_run(at, args.timeout)
    x_key = "cfg_p:pipeline:core:cell_size_m"
    move(
        x_key,
        around(
            x_key,
            controls.slider_options(
                next(p for p in describe(type(Config().pipeline)) if p.name == "cell_size_m")
            ),
        ),
        "x moved (re-register, no re-segmenting)",
    )
    move("cfg_p:pipeline:core:k", [3, 4, 6, 7, 8, 2, 9], "k moved (new pairs registered, frames cached)")

    registry = load_registry()
    samples = Path(os.environ.get("ARTCLASS_SAMPLE_DATA") or ROOT / "sample_data")
    seq = open_sequences(registry, samples / name)[0]
    t0 = time.perf_counter()
    Pipeline(registry, Config.paper() if args.paper else Config()).run(seq)
    rows.append(("for comparison: Pipeline.run (CLI path, no app)", time.perf_counter() - t0))

    print(
        f"app benchmark: {name} ({'·'.join(about[:3]).strip()}), rule {rule}; "
        f"median of {args.repeat} where repeated"
    )
    for title, seconds in rows:
        print(f"  {title:<55} {seconds:7.2f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
