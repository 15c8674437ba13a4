"""Differentiable fitting: the optimisation loop shared by the fit stages and
``pipeline fit`` (``engine``); photos as views in windows around their masks,
with the held-out choice (``views``); a texture fitted coarse to fine
(``texture``); fit_geometry's shape and material passes (``passes``); what a
fit writes beside its scene (``outputs``); and ``pipeline fit`` on any Mitsuba
scene (``scene_fit``)."""
