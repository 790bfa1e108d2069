"""The torch model's side of the parameter message: build one from an `ActorCritic`, load one
into it. Only the learner and the tools that evaluate a network import this (and torch)."""

from __future__ import annotations

import numpy as np
import torch

from protocol import Params, RunSpec
from services.wire import check_params
from tpdeb_core.model import ActorCritic

FLOAT16_MAX = float(np.finfo(np.float16).max)


def model_for(spec: RunSpec) -> ActorCritic:
    return ActorCritic(spec.obs_dim, spec.act_dim, tuple(spec.hidden_sizes), spec.init_log_std,
                       spec.obs_clip)


def params_message(model: ActorCritic | dict[str, torch.Tensor], version: int,
                   dtype: str = "float32") -> Params:
    """The model's state (or a state dict of it) as a message; with dtype float16 the float32
    weights are halved (a tensor with values beyond float16's range stays float32)."""
    arrays = (model.arrays() if isinstance(model, ActorCritic)
              else {k: v.detach().numpy() for k, v in model.items()})
    if dtype == "float16":
        arrays = {k: a.astype(np.float16) if a.dtype == np.float32 and (
            a.size == 0 or np.abs(a).max() < FLOAT16_MAX) else a for k, a in arrays.items()}
    return Params(version=int(version), arrays=arrays)


def load_params(model: ActorCritic, message: Params) -> None:
    """Load received parameters; a message that does not fit the model raises DecodeError."""
    state = model.state_dict()
    check_params(message, {k: tuple(v.shape) for k, v in state.items()})
    model.load_state_dict({k: torch.from_numpy(np.array(v, dtype=state[k].numpy().dtype))
                           for k, v in message.arrays.items()})
