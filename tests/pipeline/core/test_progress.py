"""Progress off a terminal (a log file, CI, a batch worker): a line now and then, with
the steps done and the time left, and the last step always."""

import logging

from pipeline import logger
from pipeline.core import progress


class _Lines(logging.Handler):
    def __init__(self):
        super().__init__(logging.INFO)
        self.lines = []

    def emit(self, record):
        self.lines.append(record.getMessage())


def test_off_a_terminal_long_work_says_how_far_it_is(monkeypatch):
    clock = iter(range(0, 1000, 4))  # each step takes 4 s
    monkeypatch.setattr(progress.time, "monotonic", lambda: float(next(clock)))
    monkeypatch.setattr(progress, "_enabled", True)  # an earlier --quiet CLI call may have turned it off
    monkeypatch.setattr(logger, "handlers", [seen := _Lines()])
    assert not progress.console.is_terminal  # pytest captures stderr
    assert list(progress.track(range(10), "rendering views")) == list(range(10))
    # 40 s of work: a line at 12 s, 24 s, 36 s (every 10 s or more) and at the end
    assert seen.lines == [
        "rendering views: 3/10 in 12 s, about 28 s left",
        "rendering views: 6/10 in 24 s, about 16 s left",
        "rendering views: 9/10 in 36 s, about 4 s left",
        "rendering views: 10/10 in 40 s, about 0 s left",
    ]
    seen.lines.clear()
    with progress.in_stage("fit_material"), progress.steps(3, "fit") as advance:
        for loss in (0.3, 0.2, 0.1):
            advance(f"loss {loss}")
    assert seen.lines == ["fit_material: fit: 3/3 in 12 s, about 0 s left (loss 0.1)"]
