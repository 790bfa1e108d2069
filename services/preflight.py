"""What a run checks before anything starts (`tpdeb-train`, `tpdeb-cluster`, `tpdeb.train`): the
env can be made, the learner's device exists, the run dir can be written, and an existing run dir
is this run's to continue. Each refusal is one line (ConfigError, exit status 2), and a refused
run leaves no run dir behind."""

from __future__ import annotations

from pathlib import Path

from tpdeb.services.config import ConfigError
from tpdeb.services.store.diskio import OutputError, writable_path


def writable_dir(path: str | Path, what: str) -> Path:
    """`path` is (or can be made) a directory this process can write in; nothing is created."""
    try:
        return writable_path(path, what, directory=True)
    except OutputError as exc:
        raise ConfigError(str(exc)) from None


def preflight(train, device: str | None = None) -> None:
    """A training configuration's checks, in the order a user would fix them (`device`: the
    learner's, where it differs from the training settings')."""
    from tpdeb.services.device import resolve_device
    from tpdeb.services.envs import make_vector_env

    make_vector_env(train.env_id, 1, train.env_kwargs).close()
    resolve_device(device or train.device)
    writable_dir(train.default_run_dir(), "run_dir")


# What makes a run this run: a run dir that recorded other values holds another run, which
# resuming would mix into this one's checkpoints and metrics. Everything else (budgets, the
# learning rate, the logging) may change when a run is continued.
IDENTITY = ("env_id", "env_kwargs", "algo", "seed", "fragment_len", "hidden_sizes",
            "policy_std")
RECORDS = ("train.toml", "config.toml")  # what tpdeb-cluster and tpdeb-train write in a run dir


def recorded_settings(run_dir: str | Path) -> tuple[Path, dict] | None:
    """The training settings a run dir records (its file and the flat settings), if any."""
    from tpdeb.services.config import flat, load_toml

    for name in RECORDS:
        path = Path(run_dir) / name
        if path.is_file():
            return path, flat(load_toml(path, "run dir's"))
    return None


def run_dir_resume(train, learner=None) -> bool:
    """Whether this start continues an existing run dir (`resume` not never, and settings
    recorded there); refused in one line where that run is another configuration's."""
    resume = (learner or train).resume
    recorded = recorded_settings(train.default_run_dir())
    if resume == "never" or recorded is None:
        return False
    path, settings = recorded
    for name in IDENTITY:
        before, now = settings.get(name), getattr(train, name)
        if isinstance(now, tuple):
            before = tuple(before) if isinstance(before, list) else before
        if before is not None and before != now:
            raise ConfigError(f"run dir {train.default_run_dir()} holds another run ({path} has "
                              f"{name}={before!r}, this one {now!r}): pass another --run-dir, "
                              "or --resume never to start it over there")
    return True
