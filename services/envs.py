"""Environment construction, with one clear line for every way it can go wrong."""

from __future__ import annotations

import difflib
import sys

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode

from tpdeb.services.config import ConfigError

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


def make_vector_env(env_id: str, num_envs: int) -> gym.vector.VectorEnv:
    """A synchronous vector env in SAME_STEP autoreset mode (the real final observation is in
    info["final_obs"], so no step is spent on resets). Continuous (Box) actions only."""
    quiet_mujoco()
    try:
        envs = gym.make_vec(
            env_id, num_envs=num_envs, vectorization_mode="sync",
            vector_kwargs={"autoreset_mode": AutoresetMode.SAME_STEP})
    except (ImportError, gym.error.DependencyNotInstalled) as exc:
        raise ConfigError(f"env_id {env_id!r} needs a missing package: {exc}") from None
    except gym.error.Error as exc:
        close = difflib.get_close_matches(env_id, list(gym.registry.keys()), n=3)
        hint = f" Did you mean {', '.join(close)}?" if close else ""
        raise ConfigError(f"env_id {env_id!r} is not a registered gymnasium environment: "
                          f"{exc}{hint}") from None
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
