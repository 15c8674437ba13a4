"""Differentiable fitting: the optimisation loop shared by the fit stages and
``pipeline fit`` (``engine``), and ``pipeline fit`` itself on any Mitsuba scene
(``scene_fit``)."""
