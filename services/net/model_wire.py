"""The torch model's side of the parameter message: the model for a run spec and a message of
its state. Only the learner and the tools that evaluate a network import this (and torch);
actors read parameter messages with `tpdeb.services.net.wire.policy_from_params`."""

from __future__ import annotations

import numpy as np

from tpdeb.protocol import Params, RunSpec
from tpdeb.tpdeb_core.model import ActorCritic

FLOAT16_MAX = float(np.finfo(np.float16).max)


def model_for(spec: RunSpec) -> ActorCritic:
    return ActorCritic(spec.obs_dim, spec.act_dim, tuple(spec.hidden_sizes), spec.init_log_std,
                       spec.obs_clip, spec.policy_std)


def params_message(arrays: dict[str, np.ndarray], version: int,
                   dtype: str = "float32") -> Params:
    """A model's state arrays (`ActorCritic.arrays()`) as a message; with dtype float16 the
    float32 weights are halved (a tensor with values beyond float16's range stays float32)."""
    if dtype == "float16":
        arrays = {k: a.astype(np.float16) if a.dtype == np.float32 and (
            a.size == 0 or np.abs(a).max() < FLOAT16_MAX) else a for k, a in arrays.items()}
    return Params(version=int(version), arrays=arrays)
