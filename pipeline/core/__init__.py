"""The framework: what a stage is, how the DAG is planned, cached and run, and how
configuration is layered and validated.

Nothing here knows about photos, cameras or Mitsuba; the domain packages beside it
never import it except for ``errors`` (user-facing exceptions) and ``progress``.
"""
