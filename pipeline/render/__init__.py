"""Mitsuba 3: choosing the variant this machine runs (``mitsuba_variant``), writing
and editing scene XML (``scene_xml``), the material models with their parameters,
bounds and integrators (``materials``), a capture's scene files (``capture_scene``),
scene files as users write them made ready to fit (``user_scene``), and the
numerical stability probe of the models (``stability``)."""
