"""Between the core's objects and the wire's messages: fragments, parameters, the run spec."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch

from protocol import DecodeError, Params, RunSpec, Trajectory
from protocol.codec import check_params_shapes
from services.train_config import TrainConfig
from tpdeb_core.fragments import Fragment
from tpdeb_core.model import ActorCritic

_FRAGMENT_FIELDS = [f.name for f in dataclasses.fields(Fragment)]


def run_spec(config: TrainConfig, obs_dim: int, act_dim: int, low, high) -> RunSpec:
    return RunSpec(
        env_id=config.env_id, obs_dim=obs_dim, act_dim=act_dim, fragment_len=config.fragment_len,
        hidden_sizes=list(config.hidden_sizes), gamma=config.gamma, obs_clip=config.obs_clip,
        init_log_std=config.init_log_std, priority_mode=config.priority_mode,
        priority_kappa=config.priority_kappa, action_low=np.asarray(low, np.float32),
        action_high=np.asarray(high, np.float32))


def spec_mismatch(served: RunSpec, env_id: str, obs_dim: int, act_dim: int) -> str | None:
    """Why an actor with this env cannot join the run served by the replay (None if it can)."""
    if served.env_id != env_id:
        return (f"the run trains {served.env_id!r} but this process was started with env_id "
                f"{env_id!r}: pass --env-id {served.env_id} or join another --run-id")
    if (served.obs_dim, served.act_dim) != (obs_dim, act_dim):
        return (f"{env_id}: the run expects obs_dim {served.obs_dim}, act_dim {served.act_dim}; "
                f"this installation's env has {obs_dim}, {act_dim} (different gymnasium version?)")
    return None


def model_for(spec: RunSpec) -> ActorCritic:
    return ActorCritic(spec.obs_dim, spec.act_dim, tuple(spec.hidden_sizes), spec.init_log_std,
                       spec.obs_clip)


def fragment_to_message(fragment: Fragment, reward_scale: float,
                        incarnation: int = 0) -> Trajectory:
    return Trajectory(reward_scale=float(reward_scale), incarnation=int(incarnation),
                      **{name: getattr(fragment, name) for name in _FRAGMENT_FIELDS})


def message_to_fragment(message: Trajectory) -> Fragment:
    return Fragment(**{name: getattr(message, name) for name in _FRAGMENT_FIELDS})


FLOAT16_MAX = float(np.finfo(np.float16).max)


def params_message(model: ActorCritic, version: int, dtype: str = "float32") -> Params:
    """The model's state as a message; with dtype float16 the float32 weights are halved
    (a tensor with values beyond float16's range stays float32)."""
    arrays = {k: v.detach().cpu().numpy() for k, v in model.state_dict().items()}
    if dtype == "float16":
        arrays = {k: a.astype(np.float16) if a.dtype == np.float32 and (
            a.size == 0 or np.abs(a).max() < FLOAT16_MAX) else a for k, a in arrays.items()}
    return Params(version=int(version), arrays=arrays)


def expected_shapes(model: ActorCritic) -> dict[str, tuple[int, ...]]:
    return {k: tuple(v.shape) for k, v in model.state_dict().items()}


def load_params(model: ActorCritic, message: Params) -> None:
    """Load received parameters; a message that does not fit the model raises DecodeError."""
    check_params_shapes(message, expected_shapes(model))
    state = model.state_dict()
    for name, array in message.arrays.items():
        held = torch.empty((), dtype=state[name].dtype).numpy().dtype
        if array.dtype != held and not (array.dtype == np.float16 and held == np.float32):
            raise DecodeError("dtype", f"params[{name!r}] is {array.dtype}, "
                              f"the model holds {state[name].dtype}")
    model.load_state_dict({k: torch.from_numpy(np.array(v, dtype=state[k].numpy().dtype))
                           for k, v in message.arrays.items()})


def finite_values(values: dict) -> dict:
    """Stats travel only as finite numbers (and strings): NaN/inf mean "not measured yet"."""
    return {k: v for k, v in values.items()
            if isinstance(v, str) or (not isinstance(v, bool) and math.isfinite(v))}
