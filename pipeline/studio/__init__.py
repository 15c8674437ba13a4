"""`pipeline studio`: the original tool's interactive fit, and a live view of a capture,
in a browser.

- fit_session: a scene's parameter table, one fit at a time in a worker thread (the
  engine of `pipeline fit`), its live log and previews, Pause, Resume and Stop.
- capture_session: a capture's stage table (`pipeline status --json`'s), a run in a
  child process, a fit stage's live steps, photos with masks, cameras, the mesh.
- server: the FastAPI routes and the page (static/: plain HTML, CSS and JavaScript,
  with the three.js bundle of pipeline.viewer; no build step, nothing fetched at run
  time, so it works offline).

Why FastAPI with plain JavaScript rather than a widget framework (NiceGUI, Panel) or
viser: the page needs a few tables, forms, line plots and one three.js view, all of
which are short in plain JavaScript; FastAPI and uvicorn are small, widely used and
well kept, ship as pure-Python wheels, and keep the fit's Dr.Jit work in a thread
the studio owns instead of inside a framework's event loop. viser is built around a
3D scene, NiceGUI and Panel around their own widget servers (and larger installs).
"""
