"""artclass analyst app: ``streamlit run app/streamlit_app.py [-- --data-root DIR ...]``.

Opens on the bundled samples (``sample_data/``). Typed-in folders are confined to the data roots
(``--data-root DIR``, repeatable, or ``ARTCLASS_DATA_ROOTS``; the samples by default); sequences can
also be uploaded as zips. See ``app/__init__.py`` for the module layout.
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:  # the app's modules import as app.*, from the project root
    sys.path.insert(0, str(ROOT))

import streamlit as st  # noqa: E402

from app import state  # noqa: E402

st.set_page_config(page_title="artclass", page_icon=":material/view_in_ar:", layout="wide")
state.keep_state()
HERE = Path(__file__).resolve().parent
pages = [
    st.Page(
        HERE / "app_pages" / "analyse.py",
        title="Analyse a sequence",
        icon=":material/view_in_ar:",
        default=True,
    ),
    st.Page(HERE / "app_pages" / "evaluate.py", title="Evaluate", icon=":material/fact_check:"),
    st.Page(HERE / "app_pages" / "live.py", title="Live", icon=":material/videocam:"),
    st.Page(HERE / "app_pages" / "plugins.py", title="Plugins", icon=":material/extension:"),
]
with st.sidebar:
    st.markdown("### artclass\nArticulated, rigid or static? From an RGB-D video of a handled object.")
st.navigation(pages).run()
