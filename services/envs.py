"""Environment construction, with one clear line for every way it can go wrong."""

from __future__ import annotations

import difflib
import importlib
import json
import os
import sys

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode

from tpdeb.services.config import ConfigError, tomllib

# MuJoCo warnings that say nothing to a user: gymnasium's MuJoCo XML (HalfCheetah's among
# others) still uses the deprecated, harmless `settotalmass`, printed once per env built.
HARMLESS_MUJOCO_WARNINGS = ("compiler attribute 'settotalmass' is deprecated",)


def mujoco_warning(message: str, out=None) -> None:
    """MuJoCo's warning handler here: the harmless ones dropped, the rest printed as MuJoCo
    would (to stderr)."""
    if not message.startswith(HARMLESS_MUJOCO_WARNINGS):
        print(f"WARNING: {message}", file=out or sys.stderr, flush=True)


def quiet_mujoco() -> None:
    """Install `mujoco_warning` as MuJoCo's warning handler (where MuJoCo is installed)."""
    try:
        import mujoco
    except ImportError:
        return
    if mujoco.get_mju_user_warning() is not mujoco_warning:
        mujoco.set_mju_user_warning(mujoco_warning)


def import_env_module(env_id: str) -> None:
    """For an id `module:Env-v0`, import `module` as `python -m` would: from the current
    directory first (console scripts do not put it on sys.path), so that its registration
    runs. One line where the module cannot be imported."""
    if ":" not in env_id:
        return
    module = env_id.split(":", 1)[0]
    here = os.getcwd()
    if here not in sys.path:
        sys.path.insert(0, here)
    try:
        importlib.import_module(module)
    except Exception as exc:  # the user's module may fail in any way while it imports
        raise ConfigError(f"env_id {env_id!r}: module {module!r} cannot be imported from {here} "
                          f"or the installed packages ({type(exc).__name__}: "
                          f"{str(exc).splitlines()[0][:160] if str(exc) else ''})") from None


def parse_env_kwargs(text: str) -> dict:
    """`env_kwargs` as a dict: a JSON object or a TOML inline table ('{ a = 1 }' or 'a = 1,
    b = "x"'); empty: no arguments. ValueError, in one line, for anything else."""
    text = text.strip()
    if not text:
        return {}
    try:
        value = json.loads(text)
    except json.JSONDecodeError:
        body = text[1:-1] if text.startswith("{") and text.endswith("}") else text
        try:
            value = tomllib.loads(f"kwargs = {{ {body} }}")["kwargs"]
        except tomllib.TOMLDecodeError:
            raise ValueError(f"env_kwargs={text!r} is neither a JSON object nor a TOML inline "
                             'table (e.g. \'{"ctrl_cost_weight": 0.2}\' or '
                             "'ctrl_cost_weight = 0.2')") from None
    if not isinstance(value, dict):
        raise ValueError(f"env_kwargs={text!r} must be an object of keyword arguments, not a "
                         f"{type(value).__name__}")
    return value


def canonical_env_kwargs(text: str) -> str:
    """The one text of a set of keyword arguments (sorted JSON; '' for none): what the run spec
    carries and peers compare."""
    kwargs = parse_env_kwargs(text)
    return json.dumps(kwargs, sort_keys=True, separators=(",", ":")) if kwargs else ""


def make_vector_env(env_id: str, num_envs: int, env_kwargs: str = "") -> gym.vector.VectorEnv:
    """A synchronous vector env in SAME_STEP autoreset mode (the real final observation is in
    info["final_obs"], so no step is spent on resets). Continuous (Box) actions and flat
    observations only. `env_kwargs`: gym.make's keyword arguments (see parse_env_kwargs)."""
    quiet_mujoco()
    import_env_module(env_id)
    try:
        kwargs = parse_env_kwargs(env_kwargs)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    try:
        envs = gym.make_vec(
            env_id, num_envs=num_envs, vectorization_mode="sync",
            vector_kwargs={"autoreset_mode": AutoresetMode.SAME_STEP}, **kwargs)
    except (ImportError, gym.error.DependencyNotInstalled) as exc:
        raise ConfigError(f"env_id {env_id!r} needs a missing package: {exc}") from None
    except gym.error.Error as exc:
        close = difflib.get_close_matches(env_id, list(gym.registry.keys()), n=3)
        hint = f" Did you mean {', '.join(close)}?" if close else ""
        raise ConfigError(f"env_id {env_id!r} is not a registered gymnasium environment: "
                          f"{exc}{hint}") from None
    except TypeError as exc:  # a keyword the env's constructor does not take
        if not kwargs:
            raise
        raise ConfigError(f"env_kwargs {json.dumps(kwargs)} do not fit {env_id!r}: "
                          f"{str(exc).splitlines()[0][:160]}") from None
    if not isinstance(envs.single_action_space, gym.spaces.Box):
        envs.close()
        raise ConfigError(f"env_id {env_id!r} has {envs.single_action_space} actions: TPDEB "
                          "trains continuous (Box) action spaces only")
    if len(envs.single_observation_space.shape) != 1:
        envs.close()
        raise ConfigError(f"env_id {env_id!r} has observations of shape "
                          f"{envs.single_observation_space.shape}: flat vectors only")
    return envs


def space_dims(envs) -> tuple[int, int, np.ndarray, np.ndarray]:
    """(obs_dim, act_dim, action_low, action_high) of a vector env."""
    act = envs.single_action_space
    return (int(envs.single_observation_space.shape[0]), int(act.shape[0]),
            act.low.astype(np.float32), act.high.astype(np.float32))
