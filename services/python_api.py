"""TPDEB from Python: `tpdeb.train(...)` runs a training run and returns it; `tpdeb.load_policy`
gives its policy for numpy alone.

    import tpdeb

    run = tpdeb.train("Hopper-v5", total_timesteps=300_000, seed=1)     # one process
    run = tpdeb.train("Hopper-v5", total_timesteps=1_000_000, cluster=True, actors=3,
                      learning_rate=3e-4)                                # separate processes
    run.returns[-5:], run.ended_by, run.checkpoint
    policy = run.policy()                  # or tpdeb.load_policy("runs/…"): no torch needed
    action = policy.act(obs)

A run is the command line's run (`tpdeb-train`, or `tpdeb-cluster` with `cluster=True`) in a
child process, its output shown as it goes (or, `quiet=True`, kept in `{run_dir}/train.log`):
the same code, seeds and run directory, and the caller's process keeps its own threads and
signal handlers. Settings are checked here first, so a bad one raises before anything starts.
"""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

from tpdeb.services.evaluate import Evaluation, evaluate
from tpdeb.services.policy_file import Policy, PolicyError, load_policy

__all__ = ["Evaluation", "Policy", "PolicyError", "Run", "TrainError", "evaluate", "load_policy",
           "train"]


class TrainError(ValueError):
    """A setting that cannot work, or a run that failed: one line saying which and why."""


@dataclasses.dataclass
class Run:
    """A run and how it ended; `tpdeb.train(..., run_dir=run.run_dir)` continues it."""

    run_dir: Path
    env_id: str
    ended_by: str | None  # "total_timesteps", "train_for_seconds", or "on_progress" (stopped)
    global_step: int
    checkpoint: Path | None  # the final checkpoint (a stopped run's: its newest)

    @classmethod
    def read(cls, run_dir: str | os.PathLike, env_id: str | None = None) -> Run:
        """The run in `run_dir` as its files record it (the env id too)."""
        from tpdeb.services.preflight import recorded_settings

        run_dir = Path(run_dir)
        if env_id is None:
            recorded = recorded_settings(run_dir)
            if recorded is None:
                raise TrainError(f"{run_dir}: not a run directory (no train.toml or config.toml)")
            env_id = recorded[1].get("env_id", "")
        end_file = run_dir / "end.json"
        end = json.loads(end_file.read_text()) if end_file.is_file() else {}
        checkpoint = end.get("checkpoint")
        if not end:  # stopped before its end (or still running): its newest checkpoint
            from tpdeb.services.store.checkpoint import checkpoint_dir, list_checkpoints

            found = list_checkpoints(checkpoint_dir(run_dir)) if (run_dir / "checkpoints"
                                                                   ).is_dir() else []
            if found:
                checkpoint, end["global_step"] = str(found[-1].path), found[-1].global_step
        return cls(run_dir=run_dir, env_id=env_id, ended_by=end.get("ended_by"),
                   global_step=int(end.get("global_step", 0)),
                   checkpoint=Path(checkpoint) if checkpoint and Path(checkpoint).is_file()
                   else None)

    @property
    def metrics(self) -> list[dict]:
        """Every row of metrics.jsonl (x-axis `global_step`)."""
        from tpdeb.services.store.metrics import read_metrics

        path = self.run_dir / "metrics.jsonl"
        return read_metrics(path) if path.is_file() else []

    @property
    def returns(self) -> list[tuple[int, float]]:
        """(env step, episodic return) of every episode the run logged."""
        return [(r["global_step"], r["charts/episodic_return"]) for r in self.metrics
                if "charts/episodic_return" in r]

    def policy(self) -> Policy:
        return load_policy(self.run_dir)


def settings_for(env_id: str, total_timesteps: int, seed: int, train_for_seconds: float,
                 run_dir: str | os.PathLike | None, settings: dict):
    """The run's validated TrainConfig (preset included), or TrainError naming the setting."""
    from tpdeb.services.config import ConfigError, check_environment, unknown_setting
    from tpdeb.services.config.train import TrainConfig
    from tpdeb.services.launcher.plan import coerce_train
    from tpdeb.services.preflight import preflight, run_dir_resume

    names = {f.name for f in dataclasses.fields(TrainConfig)}
    values = {**{k: _text(v) for k, v in settings.items()}, "env_id": env_id,
              "total_timesteps": total_timesteps, "seed": seed,
              "train_for_seconds": train_for_seconds}
    if run_dir is not None:
        values["run_dir"] = str(run_dir)
    try:
        check_environment(os.environ)
        for key in settings:
            if key not in names:
                raise unknown_setting(key, "train()")
        config = coerce_train(values)
        if not config.run_dir:
            config.run_dir = str(config.default_run_dir())
        preflight(config)
        run_dir_resume(config)
    except ConfigError as exc:
        raise TrainError(str(exc)) from None
    return config


def _text(value) -> str:
    """A setting as the command line would give it."""
    if isinstance(value, dict):
        return json.dumps(value)
    if isinstance(value, (list, tuple)):
        return ",".join(str(v) for v in value)
    if isinstance(value, bool):
        return "true" if value else "false"
    return str(value)


def command(config, settings: dict, cluster: bool, actors: int | None) -> list[str]:
    """The child's command line: tpdeb-train with the resolved configuration as its --config,
    or tpdeb-cluster with the run's flags and each setting as --set."""
    if not cluster:
        return [sys.executable, "-m", "tpdeb.services.serial", "--config",
                str(Path(config.run_dir) / "api-config.toml")]
    cmd = [sys.executable, "-m", "tpdeb.services.cluster", "--env-id", config.env_id,
           "--total-timesteps", str(config.total_timesteps), "--seed", str(config.seed),
           "--train-for-seconds", str(config.train_for_seconds), "--run-dir", config.run_dir]
    if actors is not None:
        cmd += ["--actors", str(actors)]
    for key, value in settings.items():
        cmd += ["--set", f"{key}={_text(value)}"]
    return cmd


def train(env_id: str, total_timesteps: int = 1_000_000, seed: int = 1, *,
          cluster: bool = False, actors: int | None = None, train_for_seconds: float = 0.0,
          run_dir: str | os.PathLike | None = None, quiet: bool = False,
          on_progress: Callable[[int, dict], bool | None] | None = None, **settings) -> Run:
    """Train on `env_id` (its preset applies, as on the command line) and return the run.

    `cluster`: separate replay, learner and actor processes (`actors` of them) instead of one
    process; `settings`: any training setting by name (`learning_rate=3e-4`,
    `hidden_sizes=[256, 256]`, `env_kwargs={"ctrl_cost_weight": 0.1}`). An existing `run_dir`
    of the same configuration is continued from its newest checkpoint up to this
    `total_timesteps` (the run's total, not more steps on top). `on_progress(step, metrics)`
    is called with every row the run logs (its progress every `log_interval_s`, 5 s by default,
    and each episode's return; it sees a row within ~0.25 s of its writing); returning False
    stops the run, which writes its checkpoint and ends with `ended_by == "on_progress"`.
    Raises TrainError for a setting that cannot work (before anything starts, leaving no run
    dir) or a run that fails; KeyboardInterrupt stops the run, which writes its checkpoint
    first."""
    if actors is not None and not cluster:
        raise TrainError("actors= needs cluster=True (one process runs one actor)")
    config = settings_for(env_id, total_timesteps, seed, train_for_seconds, run_dir, settings)
    from tpdeb.services.config import to_toml

    out_dir = Path(config.run_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if not cluster:
        (out_dir / "api-config.toml").write_text(to_toml(config))
    log = (out_dir / "train.log").open("a") if quiet else None
    progress = Progress(out_dir / "metrics.jsonl", on_progress)
    proc = subprocess.Popen(command(config, settings, cluster, actors), stdout=log,
                            stderr=subprocess.STDOUT if quiet else None,
                            stdin=subprocess.DEVNULL, start_new_session=True)
    stopped = False
    try:
        while True:
            try:
                code = proc.wait(timeout=progress.poll_s if on_progress else None)
                break
            except subprocess.TimeoutExpired:
                if not stopped and progress.poll() is False:
                    stopped = True
                    os.killpg(proc.pid, signal.SIGINT)  # as Ctrl-C: its checkpoint, then exit
        if on_progress and not stopped:
            progress.poll()  # the rows of the run's last moments
    except BaseException:  # KeyboardInterrupt: the run stops as it would on Ctrl-C
        os.killpg(proc.pid, signal.SIGINT)
        proc.wait()
        raise
    finally:
        if log is not None:
            log.close()
    if code != 0 and not (stopped and code == 130):
        where = f"; see {out_dir / 'train.log'}" if quiet else " (its output is above)"
        raise TrainError(f"the run in {out_dir} failed with exit status {code}{where}")
    run = Run.read(out_dir, config.env_id)
    if stopped:
        run.ended_by = "on_progress"
    return run


class Progress:
    """The rows a run appends to its metrics.jsonl, handed to `on_progress` as they come."""

    poll_s = 0.25

    def __init__(self, path: Path, hook: Callable[[int, dict], bool | None] | None):
        self.path, self.hook = path, hook
        # A continued run's earlier rows are history, not progress.
        self.offset = path.stat().st_size if path.is_file() else 0

    def poll(self) -> bool | None:
        """Call the hook on every whole new row; False as soon as it returns False."""
        if self.hook is None or not self.path.is_file():
            return None
        with self.path.open("rb") as f:
            f.seek(self.offset)
            data = f.read()
        end = data.rfind(b"\n") + 1  # whole lines only: the writer may be mid-line
        self.offset += end
        for line in data[:end].splitlines():
            if line.strip():
                row = json.loads(line)
                if self.hook(int(row.pop("global_step", 0)), row) is False:
                    return False
        return None
