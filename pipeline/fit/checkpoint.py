"""Checkpoints that let a killed fit resume where it was.

A stage opens a scope with ``resumable(folder)``; every fit loop run inside it
(pipeline.fit.engine) takes the next checkpoint file in call order
(``00.npz``, ``01.npz``, ...), saves its whole state there every ``every_s``
seconds and once more when it ends, and on entry resumes from the file when
there is one. A stage that runs several fits (texture levels, geometry rounds)
therefore skips the finished ones and continues the interrupted one. The runner
gives each stage run a folder named after its cache key, so a checkpoint is only
ever resumed by a run with the same inputs and settings, and deletes it once the
stage's result is committed.

A checkpoint is one ``.npz`` (no pickle): Adam's state per parameter (value, step
count, both moments), the loop's arrays (the best values so far) and a JSON
record (iteration, log, best iteration and error, why the loop stopped). Files
are replaced atomically, so a kill while saving leaves the previous checkpoint.
Beside it, ``NN.steps.jsonl`` gets each step's log entry as it is made: what a
watcher (`pipeline studio`) reads to follow a stage's fit live.

Limitations: the optimiser state is read from ``drjit.opt.Adam.state`` (value,
promoted, learning rate, (t, m_t, v_t, v_max)), Dr.Jit 1.5's layout; AMSGrad's
``v_max`` is not saved (the pipeline does not use it). Resumed fits are not
bit-identical to uninterrupted ones (Dr.Jit's LLVM fits are not either).
"""

from __future__ import annotations

import contextlib
import functools
import json
import os
import time
import zipfile
import zlib
from contextvars import ContextVar
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from pipeline import logger

CHECKPOINT_EVERY_S = 30.0
"""Seconds between checkpoints: a kill loses at most this much of a fit."""


@dataclass
class _Scope:
    folder: Path
    every_s: float
    calls: int = 0


_scope: ContextVar[_Scope | None] = ContextVar("checkpoint_scope", default=None)


@contextlib.contextmanager
def resumable(folder: Path | None, every_s: float | None = None) -> Iterator[None]:
    """Fits inside the ``with`` block checkpoint into ``folder`` (every ``every_s``
    seconds, CHECKPOINT_EVERY_S by default) and resume from it."""
    every_s = CHECKPOINT_EVERY_S if every_s is None else every_s
    token = _scope.set(_Scope(folder, every_s) if folder is not None else None)
    try:
        yield
    finally:
        _scope.reset(token)


def resumable_stage(main):
    """Decorates a stage's ``main``: its fits checkpoint into the folder the runner
    gives the stage run (``inputs.checkpoint_dir``) and resume from it."""

    @functools.wraps(main)
    def with_checkpoints(conf, inputs, out_dir):
        with resumable(inputs.checkpoint_dir):
            return main(conf, inputs, out_dir)

    return with_checkpoints


def next_checkpoint() -> "Checkpoint | None":
    """The checkpoint of the next fit loop in the current scope; None outside one."""
    scope = _scope.get()
    if scope is None:
        return None
    checkpoint = Checkpoint(scope.folder / f"{scope.calls:02d}.npz", scope.every_s)
    scope.calls += 1
    return checkpoint


@dataclass
class Resumed:
    """What a checkpoint restored besides the optimiser's state."""

    arrays: dict[str, np.ndarray]
    record: dict[str, Any]


class Checkpoint:
    def __init__(self, path: Path, every_s: float):
        self.path = path
        self.every_s = every_s
        self._last = time.perf_counter()

    def due(self) -> bool:
        return time.perf_counter() - self._last >= self.every_s

    def save(self, optimizer, arrays: dict[str, np.ndarray], record: dict[str, Any]) -> None:
        stored = {f"array/{name}": value for name, value in arrays.items()}
        for key, (value, _, _, (t, m_t, v_t, _)) in optimizer.state.items():
            stored[f"adam/{key}/value"] = np.array(value)
            stored[f"adam/{key}/t"] = np.array(t)
            stored[f"adam/{key}/m"] = np.array(m_t)
            stored[f"adam/{key}/v"] = np.array(v_t)
        stored["record"] = np.array(json.dumps(record))
        self.path.parent.mkdir(parents=True, exist_ok=True)
        partial = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")
        with partial.open("wb") as f:
            np.savez(f, **stored)
        os.replace(partial, self.path)
        self._last = time.perf_counter()

    @property
    def steps_path(self) -> Path:
        return self.path.with_suffix(".steps.jsonl")

    def log_step(self, entry: dict[str, Any]) -> None:
        """Append one step's log entry to the live log (one JSON line, flushed)."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with self.steps_path.open("a") as f:
            f.write(json.dumps(entry) + "\n")

    def restore(self, optimizer) -> Resumed | None:
        """Load the checkpoint into ``optimizer`` (whose keys it must hold); None if there
        is none, or if it is damaged (truncated, flipped bytes, another fit's keys): then
        it is removed, with a warning, and the fit starts afresh instead of failing on
        every rerun."""
        if not self.path.is_file():
            return None
        try:
            stored, record = self._read(optimizer)
        except (OSError, EOFError, ValueError, KeyError, zipfile.BadZipFile, zlib.error) as error:
            logger.warning("fit checkpoint %s is damaged (%s): removed; the fit starts afresh", self.path, error)
            self.path.unlink(missing_ok=True)
            self.steps_path.unlink(missing_ok=True)
            return None
        import drjit as dr

        for key in list(optimizer.keys()):
            value, promoted, lr, (t, m_t, v_t, v_max) = optimizer.state[key]
            kind = type(value)
            restored = stored[f"adam/{key}/value"]
            optimizer[key] = kind(restored) if dr.is_tensor_v(kind) else kind(*restored.ravel().tolist())
            value, promoted, lr, _ = optimizer.state[key]
            moments = (
                type(t)(stored[f"adam/{key}/t"].ravel()),
                type(m_t)(stored[f"adam/{key}/m"].ravel()),
                type(v_t)(stored[f"adam/{key}/v"].ravel()),
                v_max,
            )
            optimizer.state[key] = (value, promoted, lr, moments)
        arrays = {name[len("array/") :]: value for name, value in stored.items() if name.startswith("array/")}
        logger.info("resuming a fit from %s at iteration %d", self.path, record["iteration"])
        return Resumed(arrays, record)

    def _read(self, optimizer) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Every array of the checkpoint, read and checked against ``optimizer`` before
        anything is set: a damaged file raises here, not halfway through a restore."""
        with np.load(self.path, allow_pickle=False) as archive:
            stored = {name: archive[name] for name in archive.files}
        record = json.loads(str(stored["record"]))
        if not isinstance(record, dict) or not isinstance(record.get("iteration"), int):
            raise ValueError("its record has no iteration")
        for key in optimizer.keys():
            size = np.asarray(optimizer.state[key][0]).size
            for part in ("value", "t", "m", "v"):
                found = stored[f"adam/{key}/{part}"]
                if part != "t" and found.size != size or not np.all(np.isfinite(found)):
                    raise ValueError(f"adam/{key}/{part} does not fit the parameter")
        return stored, record


__all__ = ["CHECKPOINT_EVERY_S", "Checkpoint", "Resumed", "next_checkpoint", "resumable", "resumable_stage"]
