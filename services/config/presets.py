"""Per-task presets and the algorithm switch: the two layers between a config's defaults and
what the user sets.

Precedence, lowest first: dataclass defaults < the task's preset (`deploy/presets/{env_id}.toml`,
picked by env id; for a run with a wall-clock budget, `train_for_seconds`, its race preset
`deploy/presets/race/{env_id}.toml` where there is one; `--preset none` skips it, `--preset FILE`
names another) < the algorithm's
defining settings (`--algo impact|ppo-per`) < `--config FILE` < `TPDEB_*` < flags. A user
setting that contradicts what the chosen algorithm is made of (IMPACT with a KL term) is refused,
not silently overridden: the run would not be the algorithm its name says.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from tpdeb.services.config import ConfigError, load_toml, read_sections, section_of

PRESETS_DIR = Path(__file__).resolve().parents[2] / "deploy" / "presets"
RACE_DIR = PRESETS_DIR / "race"


def _ppo_per(values: dict) -> dict:
    batch = int(values.get("batch_fragments", 8))
    return {"zeta": 1.0, "priority_mode": "step", "replay_retention": "fifo",
            "prioritized_capacity": 3 * batch, "replay_ratio": 1.0,
            "uniform_capacity_steps": int(values.get("fragment_len", 64)),
            "clip_anchor": "behaviour", "kl_coef": 0.0, "kl_target": 0.0}


# What each algorithm is made of (DESIGN §7, "Baselines"), as settings over the task's preset;
# a function of the other values where it depends on them.
ALGORITHMS = {
    # The paper's method: both buffers, trajectory priorities, KL(μ‖π_θ), soft target τ.
    "tpdeb": lambda values: {},
    # IMPACT: one uniform circular buffer (ζ = 0 bypasses B_p), no KL term, the surrogate
    # clipped around a target network (soft τ, an allowed equivalent of IMPACT's periodic copy).
    "impact": lambda values: {"zeta": 0.0, "kl_coef": 0.0, "kl_target": 0.0},
    # PPO + PER: a FIFO holding three batches, one third of it (a batch) replaced per update, so
    # one sampled step per inserted step whatever the preset's replay ratio; sampled by
    # step-level PER (|δ|, α, β as TPDEB); the clip on the ratio to the behaviour policy (no
    # target policy); no KL term.
    "ppo-per": _ppo_per,
}


def preset_path(env_id: str, choice: str, by_clock: bool = False) -> Path | None:
    """The preset file for `env_id` under `choice` ("auto", "none" or a path); `by_clock`: the
    run's budget is wall-clock seconds, so auto picks the task's race preset where there is one
    (tuned for what a run makes of its minutes, not for a number of env steps)."""
    if choice == "none":
        return None
    if choice in ("", "auto"):
        candidates = [RACE_DIR / f"{env_id}.toml"] if by_clock else []
        candidates.append(PRESETS_DIR / f"{env_id}.toml")
        return next((path for path in candidates if path.is_file()), None)
    path = Path(choice)
    if not path.is_file():
        raise ConfigError(f"preset={choice!r}: no such file (use auto, none or a TOML file)")
    return path


def load_preset(cls, path: Path) -> dict:
    """The preset's values for `cls`'s fields, from its training tables (those of other
    services are left out; a setting of the run's identity or of the network is refused)."""
    from tpdeb.services.config.train import TrainConfig

    tables = {section_of(TrainConfig, f.name) for f in dataclasses.fields(TrainConfig)} - {"run"}
    return read_sections(cls, load_toml(path, "preset"), f"preset {path}", allowed=tables,
                         why=" (a preset holds training settings, not the run's)")


def layer(cls, user: dict) -> dict:
    """`user` (file, environment and flag values, already coerced) on top of the preset and the
    algorithm's settings; `preset` in the result is the file used (or "none")."""
    defaults = {f.name: f.default for f in dataclasses.fields(cls)
                if f.default is not dataclasses.MISSING}
    env_id = user.get("env_id", defaults["env_id"])
    by_clock = user.get("train_for_seconds", defaults.get("train_for_seconds", 0.0)) > 0
    path = preset_path(env_id, user.get("preset", defaults["preset"]), by_clock)
    values = load_preset(cls, path) if path is not None else {}
    values.update(user)
    algo = values.get("algo", defaults["algo"])
    if algo not in ALGORITHMS:
        raise ConfigError(f"algo={algo!r}: must be one of {', '.join(ALGORITHMS)}")
    names = {f.name for f in dataclasses.fields(cls)}
    for key, fixed in ALGORITHMS[algo]({**defaults, **values}).items():
        if key not in names:
            continue  # a setting of another service
        if key in user and user[key] != fixed:
            raise ConfigError(f"algo={algo} fixes {key}={fixed!r}, but {key}={user[key]!r} was "
                              f"given: drop that setting (or use --algo tpdeb to vary it)")
        values[key] = fixed
    values["preset"] = str(path.resolve()) if path is not None else "none"
    return values


def shown(preset: str) -> str:
    """A preset path as announced: relative to the working directory where it is inside it."""
    if preset == "none":
        return "none (defaults)"
    path = Path(preset)
    why = " (the task's race preset: a wall-clock budget)" if path.parent == RACE_DIR else ""
    try:
        return str(path.relative_to(Path.cwd())) + why
    except ValueError:
        return preset + why
