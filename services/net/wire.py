"""Between the core's objects and the wire's messages: parameters and the run spec. (Fragments
and batches need nothing here: the wire's Trajectory and Batch are the core's classes.)

Torch-free: actors and the replay server import it. The torch model's side of the parameter
message (the model for a spec, a message of its state) is in services/net/model_wire.py.
"""

from __future__ import annotations

import math

import numpy as np

from tpdeb.protocol import DecodeError, Params, RunSpec
from tpdeb.protocol.codec import check_params_shapes
from tpdeb.services.config.train import SamplingConfig
from tpdeb.tpdeb_core.policy import NumpyPolicy, param_shapes


def run_spec(config: SamplingConfig, obs_dim: int, act_dim: int, low, high) -> RunSpec:
    return RunSpec(
        env_id=config.env_id, obs_dim=obs_dim, act_dim=act_dim, fragment_len=config.fragment_len,
        hidden_sizes=list(config.hidden_sizes), gamma=config.gamma, obs_clip=config.obs_clip,
        init_log_std=config.init_log_std, policy_std=config.policy_std,
        priority_mode=config.priority_mode,
        priority_kappa=config.priority_kappa, action_low=np.asarray(low, np.float32),
        action_high=np.asarray(high, np.float32), env_kwargs=config.env_kwargs,
        replay_shards=config.replay_shards)


def spec_mismatch(served: RunSpec, env_id: str, obs_dim: int, act_dim: int,
                  env_kwargs: str = "") -> str | None:
    """Why an actor with this env cannot join the run served by the replay (None if it can)."""
    if served.env_id != env_id:
        return (f"the run trains {served.env_id!r} but this process was started with env_id "
                f"{env_id!r}: pass --env-id {served.env_id} or join another --run-id")
    if served.env_kwargs != env_kwargs:
        return (f"the run makes {env_id} with env_kwargs {served.env_kwargs or '{}'} but this "
                f"process with {env_kwargs or '{}'}: pass the run's --env-kwargs")
    if (served.obs_dim, served.act_dim) != (obs_dim, act_dim):
        return (f"{env_id}: the run expects obs_dim {served.obs_dim}, act_dim {served.act_dim}; "
                f"this installation's env has {obs_dim}, {act_dim} (different gymnasium version?)")
    return None


def expected_shapes(spec: RunSpec) -> dict[str, tuple[int, ...]]:
    return param_shapes(spec.obs_dim, spec.act_dim, spec.hidden_sizes, spec.policy_std)


def check_params(message: Params, shapes: dict[str, tuple[int, ...]]) -> None:
    """Refuse parameters that do not fit the model (`shapes`: its arrays' names and shapes) by
    name, shape or dtype (normaliser moments are float64, weights float32, or float16 from a
    reduced-precision broadcast)."""
    check_params_shapes(message, shapes)
    for name, array in message.arrays.items():
        held = np.float64 if name.endswith(("rms.count", "rms.mean", "rms.m2")) else np.float32
        if array.dtype != held and not (array.dtype == np.float16 and held == np.float32):
            raise DecodeError("dtype", f"params[{name!r}] is {array.dtype}, "
                                       f"the model holds {np.dtype(held)}")


def policy_from_params(message: Params, spec: RunSpec) -> NumpyPolicy:
    """The acting policy of a received parameter message (DecodeError if it does not fit)."""
    check_params(message, expected_shapes(spec))
    return NumpyPolicy(message.arrays, spec.obs_clip)


def finite_values(values: dict) -> dict:
    """Stats travel only as finite numbers (and strings): NaN/inf mean "not measured yet"."""
    return {k: v for k, v in values.items()
            if isinstance(v, str) or (not isinstance(v, bool) and math.isfinite(v))}
