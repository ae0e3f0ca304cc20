"""The registered plugins and their parameters (what ``artclass plugins`` prints)."""

from __future__ import annotations

import pandas as pd
import streamlit as st

from app import controls, state
from artclass_core import PipelineParams, describe
from artclass_core.cli import plugin_table

reg = state.registry()
st.title("Plugins")
st.caption(
    "Every plugin registered through the `artclass` entry points, built-in or third-party. A new plugin "
    "appears here and in the sidebar without changes to the app."
)
for name, err in reg.failures.items():
    st.warning(f"Plugin {name!r} failed to load: {err}")


def _rows(specs) -> list[dict]:
    return [
        dict(
            parameter=s.name,
            symbol=controls.symbol(s),
            unit=s.unit,
            default=("auto" if s.default is None else str(s.default)),
            bounds=f"[{s.bounds[0]}, {s.bounds[1]}]",
            auto=s.auto,
            help=s.help,
        )
        for s in specs
    ]


for kind, items in plugin_table(reg).items():
    st.subheader(f"{kind.replace('_', ' ').capitalize()}s")
    if not items:
        st.caption("none registered")
    for item in items:
        with st.expander(f"**{item['name']}** — {item['description']}"):
            st.caption(f"from {item['source']}")
            cls = reg.get(kind, item["name"]).Params
            rows = _rows(describe(cls))
            if rows:
                st.dataframe(pd.DataFrame(rows), hide_index=True, width="stretch")
            else:
                st.caption("no parameters")
st.subheader("Pipeline")
st.dataframe(pd.DataFrame(_rows(describe(PipelineParams))), hide_index=True, width="stretch")
