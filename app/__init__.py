"""The artclass Streamlit app (``streamlit run app/streamlit_app.py``).

This folder is not installed. The app puts the project root on ``sys.path`` and imports its modules
as ``app.state``, ``app.uploads`` ...; the Plotly figure builders it draws with are installed with
artclass (:mod:`artclass_plugins.figures`), so a notebook imports them directly::

    from artclass_plugins.figures import decision_timeline, motion_arrows

Modules without Streamlit (usable anywhere): :mod:`app.uploads` (zip uploads and data-root
confinement). With Streamlit: :mod:`app.state` (the stage cache, pipelines, session state; a run is
:meth:`artclass_core.Pipeline.run`), :mod:`app.controls` (sidebar widgets built from the parameter
metadata), and the pages in ``app/app_pages/``.
"""
