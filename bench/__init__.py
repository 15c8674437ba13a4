"""Benchmarks: each measures what an issue asks and rewrites its section of
docs/benchmarks.md (``--write``). Run from the repository root as
``.venv/bin/python -m bench.NAME``; ``--help`` gives each one's options.

bench.studies holds one-off investigations behind a decision (their figures are in the
decision's commit and docs); bench.tools the helpers a change is checked with
(``bench.tools.same_outputs``: two runs' outputs compared file by file).
"""
