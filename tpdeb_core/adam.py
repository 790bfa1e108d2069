"""Adam over one flat list of tensors with torch's `_foreach` kernels: one kernel per operation
for all parameters, and nothing else per step.

`torch.optim.Adam` computes the same update, but its first `step()` imports TorchDynamo (and
sympy with it: about 85 MiB of resident memory in a learner that is otherwise ~300 MiB) and
each step walks several layers of hooks and dispatch. The state dict has torch.optim.Adam's
layout, so checkpoints load either way.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import torch


class Adam:
    """Adam (Kingma & Ba 2015) without weight decay or AMSGrad, as torch.optim.Adam's defaults
    compute it; `param_groups[0]["lr"]` and `["eps"]` may be changed between steps."""

    def __init__(self, params: Iterable[torch.Tensor], lr: float = 1e-3,
                 betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8):
        self.params = list(params)
        if not self.params:
            raise ValueError("Adam: no parameters to optimise")
        if not lr >= 0.0 or not eps >= 0.0 or not all(0.0 <= b < 1.0 for b in betas):
            raise ValueError(f"Adam: lr={lr}, betas={betas}, eps={eps} out of range")
        self.param_groups = [{"lr": lr, "betas": tuple(betas), "eps": eps}]
        self.steps = 0
        self.exp_avg = [torch.zeros_like(p, memory_format=torch.preserve_format)
                        for p in self.params]
        self.exp_avg_sq = [torch.zeros_like(p, memory_format=torch.preserve_format)
                           for p in self.params]

    def zero_grad(self, set_to_none: bool = True) -> None:
        for p in self.params:
            if set_to_none:
                p.grad = None
            elif p.grad is not None:
                p.grad.zero_()

    @torch.no_grad()
    def step(self) -> None:
        group = self.param_groups[0]
        lr, (beta1, beta2), eps = group["lr"], group["betas"], group["eps"]
        live = [i for i, p in enumerate(self.params) if p.grad is not None]
        if not live:
            return
        params = [self.params[i] for i in live]
        grads = [self.params[i].grad for i in live]
        m = [self.exp_avg[i] for i in live]
        v = [self.exp_avg_sq[i] for i in live]
        self.steps += 1
        # m ← β1·m + (1−β1)·g;  v ← β2·v + (1−β2)·g²;  θ ← θ − lr/(1−β1^t) · m / (√v/√(1−β2^t) + ε)
        torch._foreach_lerp_(m, grads, 1.0 - beta1)
        torch._foreach_mul_(v, beta2)
        torch._foreach_addcmul_(v, grads, grads, 1.0 - beta2)
        denom = torch._foreach_sqrt(v)
        torch._foreach_div_(denom, math.sqrt(1.0 - beta2 ** self.steps))
        torch._foreach_add_(denom, eps)
        torch._foreach_addcdiv_(params, m, denom, -lr / (1.0 - beta1 ** self.steps))

    # -- torch.optim.Adam's state-dict layout
    def state_dict(self) -> dict:
        group = self.param_groups[0]
        state = {i: {"step": torch.tensor(float(self.steps)), "exp_avg": self.exp_avg[i],
                     "exp_avg_sq": self.exp_avg_sq[i]} for i in range(len(self.params))}
        return {"state": state if self.steps else {},
                "param_groups": [{"lr": group["lr"], "betas": group["betas"],
                                  "eps": group["eps"], "weight_decay": 0, "amsgrad": False,
                                  "maximize": False, "foreach": True, "capturable": False,
                                  "differentiable": False, "fused": None,
                                  "decoupled_weight_decay": False,
                                  "params": list(range(len(self.params)))}]}

    def load_state_dict(self, saved: dict) -> None:
        groups = saved["param_groups"]
        if len(groups) != 1 or len(groups[0]["params"]) != len(self.params):
            raise ValueError(f"optimizer state for {[len(g['params']) for g in groups]} "
                             f"parameters, this model has {len(self.params)}")
        group = groups[0]
        if group.get("weight_decay", 0) or group.get("amsgrad", False):
            raise ValueError("optimizer state uses weight decay or AMSGrad, which this Adam "
                             "does not")
        self.param_groups[0].update(lr=float(group["lr"]), betas=tuple(group["betas"]),
                                    eps=float(group["eps"]))
        state = {int(k): v for k, v in saved["state"].items()}
        steps = {float(s["step"]) for s in state.values()}
        if len(steps) > 1:
            raise ValueError(f"optimizer state with different step counts {sorted(steps)}")
        self.steps = int(steps.pop()) if steps else 0
        for i, p in enumerate(self.params):
            entry = state.get(int(group["params"][i]))
            if entry is None:
                self.exp_avg[i].zero_()
                self.exp_avg_sq[i].zero_()
                continue
            for name, held in (("exp_avg", self.exp_avg), ("exp_avg_sq", self.exp_avg_sq)):
                if entry[name].shape != p.shape:
                    raise ValueError(f"optimizer state {name}[{i}] has shape "
                                     f"{tuple(entry[name].shape)}, the parameter "
                                     f"{tuple(p.shape)}")
                held[i] = entry[name].detach().clone().to(p.dtype)
