"""Atomic checkpoint files: written to a temp file in the same directory, then renamed."""

from __future__ import annotations

import dataclasses
import os
import tempfile
from pathlib import Path

import torch


def save_atomic(state: dict, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save(state, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def load(path: str | Path) -> dict:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint {path} does not exist")
    return torch.load(path, map_location="cpu", weights_only=False)


def save_training(run_dir: str | Path, learner, config, global_step: int, tag: str) -> Path:
    """The learner's full state as `{tag}_{updates}_{global_step}.pt` (train, env steps)."""
    state = {**learner.state_dict(), "config": dataclasses.asdict(config),
             "global_step": int(global_step), "version": learner.updates}
    name = f"{tag}_{learner.updates}_{int(global_step)}.pt"
    return save_atomic(state, Path(run_dir) / "checkpoints" / name)
