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
import difflib
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

from tpdeb.services.policy_file import Policy, PolicyError, load_policy

__all__ = ["Policy", "PolicyError", "Run", "TrainError", "load_policy", "train"]


class TrainError(ValueError):
    """A setting that cannot work, or a run that failed: one line saying which and why."""


@dataclasses.dataclass
class Run:
    """A finished run: where it is and how it ended."""

    run_dir: Path
    env_id: str
    ended_by: str | None  # "total_timesteps" or "train_for_seconds": the limit that bound
    global_step: int
    checkpoint: Path | None  # the final checkpoint

    @classmethod
    def read(cls, run_dir: Path, env_id: str) -> Run:
        end_file = run_dir / "end.json"
        end = json.loads(end_file.read_text()) if end_file.is_file() else {}
        checkpoint = end.get("checkpoint")
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
    from tpdeb.services.config import ConfigError
    from tpdeb.services.config.train import TrainConfig
    from tpdeb.services.launcher.plan import coerce_train

    names = {f.name for f in dataclasses.fields(TrainConfig)}
    for key in settings:
        if key not in names:
            near = difflib.get_close_matches(key, names, n=1)
            raise TrainError(f"unknown setting {key!r}" + (f" (did you mean {near[0]!r}?)"
                                                             if near else ""))
    values = {**{k: _text(v) for k, v in settings.items()}, "env_id": env_id,
              "total_timesteps": total_timesteps, "seed": seed,
              "train_for_seconds": train_for_seconds}
    if run_dir is not None:
        values["run_dir"] = str(run_dir)
    try:
        config = coerce_train(values)
        from tpdeb.services.envs import make_vector_env

        make_vector_env(config.env_id, 1, config.env_kwargs).close()  # a bad env: one line
    except ConfigError as exc:
        raise TrainError(str(exc)) from None
    if not config.run_dir:
        config.run_dir = str(config.default_run_dir())
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
          run_dir: str | os.PathLike | None = None, quiet: bool = False, **settings) -> Run:
    """Train on `env_id` (its preset applies, as on the command line) and return the run.

    `cluster`: separate replay, learner and actor processes (`actors` of them) instead of one
    process; `settings`: any training setting by name (`learning_rate=3e-4`,
    `hidden_sizes=[256, 256]`, `env_kwargs={"ctrl_cost_weight": 0.1}`). Raises TrainError for a
    setting that cannot work (before anything starts) or a run that fails; KeyboardInterrupt
    stops the run, which writes its checkpoint first."""
    if actors is not None and not cluster:
        raise TrainError("actors= needs cluster=True (one process runs one actor)")
    config = settings_for(env_id, total_timesteps, seed, train_for_seconds, run_dir, settings)
    from tpdeb.services.config import to_toml

    out_dir = Path(config.run_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if not cluster:
        (out_dir / "api-config.toml").write_text(to_toml(config))
    log = (out_dir / "train.log").open("w") if quiet else None
    proc = subprocess.Popen(command(config, settings, cluster, actors), stdout=log,
                            stderr=subprocess.STDOUT if quiet else None,
                            stdin=subprocess.DEVNULL, start_new_session=True)
    try:
        code = proc.wait()
    except BaseException:  # KeyboardInterrupt: the run stops as it would on Ctrl-C
        os.killpg(proc.pid, signal.SIGINT)
        proc.wait()
        raise
    finally:
        if log is not None:
            log.close()
    if code != 0:
        where = f"; see {out_dir / 'train.log'}" if quiet else " (its output is above)"
        raise TrainError(f"the run in {out_dir} failed with exit status {code}{where}")
    return Run.read(out_dir, config.env_id)
