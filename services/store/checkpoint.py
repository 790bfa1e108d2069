"""Learner checkpoints in a run directory's `checkpoints/`: atomic files, rotation, the choice of
the checkpoint to resume from, and the parameter-version mark.

Files:
- `ckpt_{updates}_{global_step}.pt`, written every `checkpoint_interval_s`; the newest
  `keep_checkpoints` stay.
- `final_{updates}_{global_step}.pt`, written when the run's budget is used up; never rotated
  away. A run stopped before (Ctrl-C, SIGTERM) writes a `ckpt_` one, which resuming continues.
- `best.pt`, the learner's state at the best evaluation while training (services/evaluator.py);
  not a checkpoint to resume from.
- `params_version.json`, the high-water mark of published parameter versions (`VersionMark`).

Every file is written to a temp file in the same directory, fsynced and renamed (then the
directory is fsynced), so a reader sees the old file or the new one, never half of one. A crash
mid-write leaves at most a `.{name}.XXXX` temp file, which no reader looks at and the next
rotation removes.
"""

from __future__ import annotations

import dataclasses
import json
import re
import time
from collections.abc import Callable
from pathlib import Path

import torch

from tpdeb.services.config import ConfigError
from tpdeb.services.store.diskio import write_atomic
from tpdeb.tpdeb_core.policy import policy_std_of

PERIODIC, FINAL = "ckpt", "final"
BEST_CHECKPOINT = "best.pt"  # the best evaluation's (services/evaluator.py); never resumed from
_NAME = re.compile(r"(ckpt|final)_(\d+)_(\d+)\.pt")
# What a checkpoint must hold to restore a learner (Learner.state_dict plus the run's counters).
REQUIRED_KEYS = ("model", "target_policy", "optimizer", "kl_coef", "updates", "global_step",
                 "version")
VERSION_BLOCK = 1000


def checkpoint_dir(run_dir: str | Path) -> Path:
    return Path(run_dir) / "checkpoints"


def save_atomic(state: dict, path: str | Path) -> Path:
    return write_atomic(path, lambda f: torch.save(state, f))


def load(path: str | Path) -> dict:
    """A checkpoint's state. `weights_only`: tensors and plain values only, so loading a file
    never runs code from it."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint {path} does not exist")
    return torch.load(path, map_location="cpu", weights_only=True)


def spec_fields(spec) -> dict:
    """What a checkpoint records of the run spec: what refuses resuming into another env, and
    the action bounds a policy taken out of the run clips to."""
    return {"env_id": spec.env_id, "obs_dim": int(spec.obs_dim), "act_dim": int(spec.act_dim),
            "hidden_sizes": [int(h) for h in spec.hidden_sizes], "policy_std": spec.policy_std,
            "action_low": [float(x) for x in spec.action_low],
            "action_high": [float(x) for x in spec.action_high]}


def save_training(run_dir: str | Path, learner, config, global_step: int, tag: str,
                  version: int | None = None, spec=None, train_elapsed_s: float = 0.0,
                  name: str | None = None, extra: dict | None = None) -> Path:
    """The learner's full state as `{tag}_{updates}_{global_step}.pt` (train, env steps), or
    `name` (with `extra` entries):
    model with its normalisers, target policy, optimiser, KL coefficient, update count, the
    parameter version (default: the update count), global step, the seconds of training so far
    (what a time limit counts), config and run spec."""
    state = {**learner.state_dict(), "config": dataclasses.asdict(config),
             "global_step": int(global_step), "train_elapsed_s": float(train_elapsed_s),
             "version": int(learner.updates if version is None else version),
             "spec": spec_fields(spec) if spec is not None else None, **(extra or {})}
    name = name or f"{tag}_{learner.updates}_{int(global_step)}.pt"
    return save_atomic(state, checkpoint_dir(run_dir) / name)


@dataclasses.dataclass(frozen=True)
class CheckpointFile:
    path: Path
    tag: str
    updates: int
    global_step: int


def list_checkpoints(directory: str | Path) -> list[CheckpointFile]:
    """Checkpoints in `directory`, oldest first by (updates, global step); temp files and
    other names are not checkpoints."""
    found = []
    for path in Path(directory).glob("*.pt"):
        match = _NAME.fullmatch(path.name)
        if match:
            found.append(CheckpointFile(path, match[1], int(match[2]), int(match[3])))
    return sorted(found, key=lambda c: (c.updates, c.global_step, c.tag == FINAL))


def rotate(directory: str | Path, keep: int) -> list[Path]:
    """Delete all but the `keep` most recently written periodic checkpoints (write order, so a
    just-written checkpoint is never the one removed) and any temp file a crash left behind."""
    directory = Path(directory)
    periodic = [c for c in list_checkpoints(directory) if c.tag == PERIODIC]
    # mtimes tick coarsely (a few ms): equal ones fall back to the update count
    periodic.sort(key=lambda c: (c.path.stat().st_mtime_ns, c.updates, c.global_step))
    doomed = [c.path for c in periodic[:max(0, len(periodic) - keep)]]
    # mkstemp's names: `.{name}.{random}`
    doomed += [p for p in directory.glob(".*.pt.*")
               if _NAME.fullmatch(p.name[1:].rsplit(".", 1)[0])]
    for path in doomed:
        path.unlink(missing_ok=True)
    return doomed


def _short(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0][:120]}" if text else type(exc).__name__


def read_checkpoint(path: str | Path) -> dict:
    """A checkpoint's state, or ValueError saying in one line why it cannot be used."""
    try:
        state = load(path)
    except Exception as exc:  # a torn or foreign file fails in torch, zipfile or pickle
        raise ValueError(f"unreadable ({_short(exc)})") from None
    if not isinstance(state, dict):
        raise ValueError(f"not a learner checkpoint (holds a {type(state).__name__})")
    missing = [k for k in REQUIRED_KEYS if k not in state]
    if missing:
        raise ValueError(f"not a learner checkpoint (no {', '.join(missing)})")
    return state


def newest_loadable(directory: str | Path,
                    skipped: Callable[[str], None]) -> tuple[Path, dict] | None:
    """The checkpoint with the most updates that loads; each one that does not is reported
    through `skipped` (one line) and passed over."""
    for ckpt in reversed(list_checkpoints(directory)):
        try:
            return ckpt.path, read_checkpoint(ckpt.path)
        except ValueError as exc:
            skipped(f"skipping checkpoint {ckpt.path}: {exc}")
    return None


def choose_resume(resume: str, run_dir: str | Path,
                  skipped: Callable[[str], None]) -> tuple[Path, dict] | None:
    """`--resume auto|never|PATH` → (path, state) to restore, or None for a fresh start.
    A PATH that is missing or does not load raises ConfigError."""
    if resume == "never":
        return None
    if resume == "auto":
        return newest_loadable(checkpoint_dir(run_dir), skipped)
    path = Path(resume)
    if not path.is_file():
        raise ConfigError(f"--resume {resume}: no such checkpoint file; pass an existing "
                          "checkpoint, auto (the run dir's newest) or never")
    try:
        return path, read_checkpoint(path)
    except ValueError as exc:
        raise ConfigError(f"--resume {resume}: {exc}; pass another checkpoint, auto or "
                          "never") from None


def spec_problem(state: dict, spec) -> str | None:
    """Why a checkpoint cannot continue the run with this spec (None if it can)."""
    saved = state.get("spec") or {"env_id": (state.get("config") or {}).get("env_id")}
    here = spec_fields(spec)
    if saved.get("env_id") not in (None, here["env_id"]) or any(
            saved.get(k) not in (None, here[k]) for k in ("obs_dim", "act_dim")):
        return (f"it was trained on {saved.get('env_id')} (obs_dim {saved.get('obs_dim', '?')}, "
                f"act_dim {saved.get('act_dim', '?')}); this run trains {here['env_id']} (obs_dim "
                f"{here['obs_dim']}, act_dim {here['act_dim']})")
    if saved.get("hidden_sizes") not in (None, here["hidden_sizes"]):
        return (f"its networks have hidden sizes {saved['hidden_sizes']}; this run's have "
                f"{here['hidden_sizes']} (--hidden-sizes)")
    # checkpoints from before the setting hold a global log-std: their weights say which
    saved_std = saved.get("policy_std") or policy_std_of(state.get("model") or {})
    if saved_std != here["policy_std"]:
        return (f"its policy has a {saved_std} log-std; this run's has a {here['policy_std']} "
                f"one (--policy-std {saved_std} to continue it)")
    return None


def set_aside(run_dir: str | Path) -> Path | None:
    """Move the checkpoints of an earlier start, and the metrics, events, policy and end record
    it wrote, into `checkpoints/before_{unix time}/`, so a fresh start's files are the only ones
    `auto`, rotation and the plots see (nothing is deleted)."""
    directory = checkpoint_dir(run_dir)
    old = [c.path for c in list_checkpoints(directory)] if directory.is_dir() else []
    if not old:
        return None
    run_dir = Path(run_dir)
    old += [run_dir / name for name in ("metrics.jsonl", "end.json", "policy.npz")
            if (run_dir / name).is_file()]
    old += sorted(run_dir.glob("events.out.tfevents.*"))
    aside = directory / f"before_{time.time_ns() // 1_000_000}"
    aside.mkdir()
    for path in old:
        path.rename(aside / path.name)
    return aside


class VersionMark:
    """High-water mark of the parameter versions this run's learners have published, kept in
    `checkpoints/params_version.json`.

    Actors ignore parameters older than the ones they hold, so a restarted learner must never
    publish a version ≤ one already published, including versions its predecessor published
    after its last checkpoint, which no checkpoint records. Invariant: every published version is
    ≤ the mark on disk. Before publishing a version above the mark, the learner raises the mark
    `block` versions ahead (one small fsynced write per `block` versions, not one per update).
    A (re)started learner publishes `updates + offset` with offset = max(0, mark + 1 − restored
    updates), so its first version is above anything published before. The price of a crash: up
    to `block` versions are skipped, so fragments collected before the restart look that many
    versions older in the policy-lag metrics.
    """

    FILE = "params_version.json"

    def __init__(self, directory: str | Path, block: int | None = None):
        self.path = Path(directory) / self.FILE
        self.block = block or VERSION_BLOCK
        self.reserved = self._read()  # -1: nothing published yet

    def _read(self) -> int:
        if not self.path.exists():
            return -1
        try:
            value = json.loads(self.path.read_text())["reserved_version"]
            if isinstance(value, bool) or not isinstance(value, int):
                raise ValueError(f"reserved_version={value!r} is not an integer")
            return value
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise ConfigError(
                f"{self.path}: unreadable parameter-version mark ({_short(exc)}); it keeps "
                "versions increasing across restarts: write {\"reserved_version\": N} with N at "
                "least the actors' param_version, or delete it if no actor of this run is "
                "running") from None

    def offset(self, restored_updates: int, restored_version: int = -1) -> int:
        """What to add to the update count so the next version exceeds both the mark and the
        restored checkpoint's version (the latter covers a deleted mark file)."""
        floor = max(self.reserved, restored_version) + 1
        return max(0, floor - restored_updates)

    def reserve(self, version: int) -> None:
        """Call before publishing `version`."""
        if version > self.reserved:
            reserved = version + self.block
            write_atomic(self.path, lambda f: f.write(
                json.dumps({"reserved_version": reserved}).encode()))
            self.reserved = reserved
