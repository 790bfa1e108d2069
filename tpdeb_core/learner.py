"""The TPDEB learner (DESIGN §2, "The loss"): one update is the networks on the batch, the
targets (V-trace, advantages, ratios, weights) and the loss of `tpdeb_core/loss.py`,
differentiated by autograd, clipped and stepped by `torch.optim.Adam`, then the soft target
policy and the KL coefficient.

The update is one function, `Update.__call__(state, batch, norm)`, of the learner's tensors
(`State`: parameters, target policy, Adam's moments and step counts, learning rate, KL
coefficient, log-std ceiling, metric sums), which it changes in place: the networks on the batch
(`tpdeb_core.policy`'s functions on those tensors), the targets and the loss, the loss's gradient
with respect to the parameters (autograd; `torch.func.grad` when compiled, so that the forward,
the backward and the step make one graph), the gradients' norm clipped by torch, torch's Adam
(`torch.optim.adam.adam` on the state of a `torch.optim.Adam`), the log-std ceiling, the soft
target and the KL coefficient. Because it reads nothing but its arguments and fixed settings, a
compiled version traced on one learner runs any learner of the same shapes (the caller swaps it
in with `use`, as `services/learner.py` does). Everything it computes stays on the learner's
device: no numpy and no read-back to the host inside it. The batch arrives placed (`place`: one
copy of its arrays, static shapes); the metrics add up on the device and are read with
`read_metrics` (at the logging interval); the new priorities leave as one tensor per batch,
which the caller copies out when it needs them.

Pure: a `Learner` takes fragments and replay weights and returns metrics and new priorities.
Where the fragments come from and where parameters go is the caller's business.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
import torch
from torch.optim.adam import adam

from tpdeb.tpdeb_core import loss, policy
from tpdeb.tpdeb_core.fragments import Fragment, FragmentBatch
from tpdeb.tpdeb_core.loss_config import LossConfig
from tpdeb.tpdeb_core.model import TORCH, ActorCritic
from tpdeb.tpdeb_core.vtrace import discounted_sums

# What `read_metrics` returns, in the order of the device's metrics vector.
METRICS = ("losses/policy_loss", "losses/value_loss", "losses/entropy", "losses/kl_behaviour",
           "losses/approx_kl", "losses/clipfrac", "losses/explained_variance",
           "losses/target_is_clipfrac", "losses/grad_norm", "losses/kl_coef")
# A batch's truncated steps are padded to at least this many (then to the next power of two), so
# that batches keep one shape and a compiled update is not traced again for each count.
TRUNC_SLOTS = 8
ADAM_BETAS = (0.9, 0.999)  # torch.optim.Adam's defaults


class Batch(NamedTuple):
    """One batch on the learner's device, in shapes that do not change from batch to batch."""

    obs: torch.Tensor  # [T+1, B, obs] raw
    actions: torch.Tensor  # [T, B, A]
    rewards: torch.Tensor  # [T, B] raw
    terminated: torch.Tensor  # [T, B] bool
    truncated: torch.Tensor  # [T, B] bool
    behaviour_mean: torch.Tensor  # [T, B, A]
    behaviour_log_std: torch.Tensor  # [T, B, A]
    behaviour_logp: torch.Tensor  # [T, B]
    weights: torch.Tensor  # [T, B] the replay's importance weights (not yet normalised)
    trunc_obs: torch.Tensor  # [K, obs] real final observations of truncated steps, zero-padded
    trunc_at: torch.Tensor  # [K] int64 their flat index t·B + b (0 for padding)
    trunc_live: torch.Tensor  # [K] 1 where the step bootstraps (truncated, not terminated), else 0


def place(fragments: FragmentBatch, weights: np.ndarray, step_weights: np.ndarray | None,
          device: torch.device, pin: bool = False) -> Batch:
    """A stacked batch as tensors on `device`: each array copied once (through pinned memory
    and without waiting when `pin`, for an accelerator); the replay weights spread over the
    steps ([B] per fragment, or [B, T] per step), the truncations padded to a fixed count."""
    f = fragments
    steps, count = f.rewards.shape
    if step_weights is not None:
        w = np.asarray(step_weights, np.float32)[:, :steps].T
    else:
        w = np.broadcast_to(np.asarray(weights, np.float32), (steps, count))
    n = len(f.trunc_t)
    slots = max(TRUNC_SLOTS, 1 << max(n - 1, 0).bit_length())
    trunc_obs = np.zeros((slots, f.obs.shape[-1]), np.float32)
    trunc_obs[:n] = f.trunc_obs
    trunc_at = np.zeros(slots, np.int64)
    trunc_at[:n] = np.asarray(f.trunc_t, np.int64) * count + f.trunc_b
    trunc_live = np.zeros(slots, np.float32)
    trunc_live[:n] = ~f.terminated[f.trunc_t, f.trunc_b]
    arrays = (f.obs, f.actions, f.rewards, f.terminated, f.truncated, f.behaviour_mean,
              f.behaviour_log_std, f.behaviour_logp, w, trunc_obs, trunc_at, trunc_live)
    return Batch(*(to_device(x, device, pin) for x in arrays))


def to_device(x: np.ndarray, device: torch.device, pin: bool = False) -> torch.Tensor:
    """A copy of `x` on `device` (arrays decoded from the wire are read-only views of the
    message: torch must not share them)."""
    host = torch.from_numpy(np.array(x, copy=True))
    if device.type == "cpu":
        return host
    return (host.pin_memory() if pin else host).to(device, non_blocking=pin)


class LossInputs(NamedTuple):
    """What `loss.loss` takes for one batch, and what the priorities and metrics read."""

    mean: torch.Tensor  # π_θ's mean [T, B, A], with its graph
    log_std: torch.Tensor  # its log-std: the parameter [A] or [T, B, A] from the head
    values: torch.Tensor  # V_φ [T+1, B], with its graph
    targets: loss.Targets
    batch: Batch  # μ's log-std read under the log-std ceiling
    rewards: torch.Tensor  # scaled, truncations bootstrapped through them
    discounts: torch.Tensor  # γ_t, zero at episode ends
    target_logp: torch.Tensor  # log π_θ̄(a_t|s_t) (π_θ's when the clip is PPO's)


class State(NamedTuple):
    """The learner's tensors that an update reads and changes in place."""

    params: list[torch.Tensor]  # the model's parameters, as `model.named_parameters()` lists them
    target: list[torch.Tensor]  # the target policy's, as its `named_parameters()` lists them
    exp_avgs: list[torch.Tensor]  # Adam's moments and step counts, per parameter
    exp_avg_sqs: list[torch.Tensor]
    steps: list[torch.Tensor]
    lr: torch.Tensor
    kl_coef: torch.Tensor
    ceiling: torch.Tensor  # the log-std ceiling (+∞: none)
    metric_sums: torch.Tensor  # [len(METRICS)]


@dataclass(frozen=True)
class Layout:
    """Where a policy's and a value net's tensors sit in a parameter list (by the names
    `named_parameters()` gives them): each linear layer's (weight, bias) indices, and the
    log-std's (the parameter's index, or the head's layer)."""

    mean_layers: tuple[tuple[int, int], ...]
    log_std_at: int | tuple[int, int]
    value_layers: tuple[tuple[int, int], ...]

    @classmethod
    def of(cls, names: list[str]) -> Layout:
        def layers(prefix: str) -> tuple[tuple[int, int], ...]:
            found = sorted(int(n[len(prefix):].split(".")[0]) for n in names
                           if n.startswith(prefix) and n.endswith(".weight"))
            return tuple((names.index(f"{prefix}{i}.weight"), names.index(f"{prefix}{i}.bias"))
                         for i in found)
        policy = "policy." if any(n.startswith("policy.") for n in names) else ""
        head = f"{policy}log_std_head."
        log_std = ((names.index(f"{head}weight"), names.index(f"{head}bias"))
                   if f"{head}weight" in names else names.index(f"{policy}log_std"))
        return cls(layers(f"{policy}mean."), log_std, layers("value_net."))

    def policy(self, tensors: list[torch.Tensor], obs: torch.Tensor):
        """(mean, log-std) of the policy whose tensors these are, on normalised `obs`."""
        at = self.log_std_at
        log_std = tensors[at] if isinstance(at, int) else tuple(tensors[i] for i in at)
        return policy.gaussian([(tensors[w], tensors[b]) for w, b in self.mean_layers], log_std,
                               obs, TORCH)

    def value(self, tensors: list[torch.Tensor], obs: torch.Tensor) -> torch.Tensor:
        return policy.mlp([(tensors[w], tensors[b]) for w, b in self.value_layers], obs,
                          TORCH).squeeze(-1)


class Update:
    """One update as a function of a learner's tensors (`State`), a placed batch and the
    normalisers' affine map; it holds only fixed settings, so one compiled version serves every
    learner of the same shapes."""

    def __init__(self, config: LossConfig, names: list[str], target_names: list[str],
                 obs_clip: float | None, global_log_std: bool, device_type: str):
        """`names`, `target_names`: the model's and the target policy's parameter names."""
        self.config, self.layout = config, Layout.of(names)
        self.target_layout = Layout.of(target_names)
        # the policy's parameters in the model's list, in the target policy's order
        self.policy_indices = tuple(names.index(f"policy.{n}") for n in target_names)
        self.obs_clip, self.global_log_std, self.device_type = obs_clip, global_log_std, device_type
        # data-parallel learners: (gradients, metrics) ↦ their average over the group, in place,
        # between the gradients and the step (the caller's; None alone)
        self.reduce: Callable[[list[torch.Tensor], torch.Tensor], None] | None = None

    @torch.no_grad()
    def __call__(self, state: State, batch: Batch, norm: torch.Tensor) -> torch.Tensor:
        """L's gradient with respect to the parameters, its norm clipped, Adam, the log-std
        ceiling, the soft target update, the KL coefficient's adaptation, the metrics added to
        their sums. Returns the new priorities of the batch's fragments. Eager."""
        return self.update(state, batch, norm, traced=False)

    @torch.no_grad()
    def traced(self, state: State, batch: Batch, norm: torch.Tensor) -> torch.Tensor:
        """The same update in the form torch.compile traces (services/compiled.py). Which form
        runs is fixed by the entry point, not by `torch.compiler.is_compiling()`: that flag is
        the process's, so an eager update would read it as set while another thread compiles."""
        return self.update(state, batch, norm, traced=True)

    def update(self, state: State, batch: Batch, norm: torch.Tensor,
               traced: bool) -> torch.Tensor:
        if traced:
            # traced as a function of the parameters: one graph holds the forward, the backward
            # and the step
            def total(params):
                total, priorities, metrics = self.forward(state._replace(params=params), batch,
                                                          norm)
                return total, (priorities, metrics)

            grads, (priorities, metrics) = torch.func.grad(total, has_aux=True)(
                tuple(state.params))
            grads = list(grads)
        else:  # eager, autograd's engine is quicker than the transform
            with torch.enable_grad():
                total, priorities, metrics = self.forward(state, batch, norm)
            grads = list(torch.autograd.grad(total, state.params))
        if self.reduce is not None:
            self.reduce(grads, metrics)
        self.apply(state, grads, metrics, traced)
        return priorities

    def forward(self, state: State, b: Batch, norm: torch.Tensor):
        """The loss on the batch: (L with its graph, the new priorities, the metrics but the
        last two of METRICS)."""
        x = self.loss_inputs(state, b, norm)
        total, terms = loss.loss(self.config, state.kl_coef, x.batch, x.targets, x.mean,
                                 x.log_std, x.values)
        with torch.no_grad():
            priorities = self._priorities(torch.abs(x.targets.rhos * x.targets.deltas),
                                          x.rewards, x.discounts)
            metrics = self._metrics(b, x.targets, terms, x.values, x.target_logp)
        return total, priorities, metrics

    def loss_inputs(self, state: State, b: Batch, norm: torch.Tensor) -> LossInputs:
        """The networks on the batch (current normaliser statistics; rewards scaled at learn
        time) and the loss's constants: V-trace targets, advantages, ratios, weights."""
        cfg, layout = self.config, self.layout
        steps, count, obs_dim = b.obs.shape[0] - 1, b.obs.shape[1], b.obs.shape[2]
        obs_mean, obs_inv_std, reward_scale = norm[:obs_dim], norm[obs_dim:-1], norm[-1]

        def normalize(x):
            return policy.normalize(x, obs_mean, obs_inv_std, self.obs_clip, TORCH)

        obs = normalize(b.obs)
        mean, log_std = layout.policy(state.params, obs[:-1])
        # one pass of the value net over the batch and the truncated steps' final observations
        all_values = layout.value(state.params, torch.cat([obs.reshape(-1, obs_dim),
                                                           normalize(b.trunc_obs)]))
        values = all_values[:(steps + 1) * count].reshape(steps + 1, count)
        with torch.no_grad():
            logp = policy.log_prob(mean, log_std, b.actions, TORCH)
            target_logp = logp
            if cfg.clip_anchor == "target":
                t_mean, t_log_std = self.target_layout.policy(state.target, obs[:-1])
                target_logp = policy.log_prob(t_mean, t_log_std, b.actions, TORCH)
            rewards, discounts = self._returns(b, reward_scale,
                                               all_values[(steps + 1) * count:])
            t = loss.targets(cfg, loss.replay_weights(b.weights), b.behaviour_logp, target_logp,
                             rewards, values.detach(), discounts)
        # The KL term sees μ's std under the ceiling: the noise level is the schedule's, not
        # pulled back up by wider behaviour policies from earlier on.
        behaviour = b._replace(behaviour_log_std=torch.minimum(b.behaviour_log_std,
                                                               state.ceiling))
        return LossInputs(mean, log_std, values, t, behaviour, rewards, discounts, target_logp)

    def _returns(self, b: Batch, reward_scale: torch.Tensor, final_values: torch.Tensor):
        """Scaled rewards and discounts γ_t. A truncation bootstraps from the real final
        observation through the reward and cuts the trace there (discount 0), so nothing flows
        across the episode end; a termination does not bootstrap."""
        gamma = self.config.gamma
        rewards = (b.rewards * reward_scale).reshape(-1).index_add(
            0, b.trunc_at, gamma * b.trunc_live * final_values).reshape(b.rewards.shape)
        discounts = gamma * (~(b.terminated | b.truncated)).to(rewards.dtype)
        return rewards, discounts

    def _priorities(self, td_abs: torch.Tensor, rewards: torch.Tensor,
                    discounts: torch.Tensor) -> torch.Tensor:
        """Σ_t |ρ_t δ_t| per fragment (+ κ·mean |G_t|), or per step [B, T], on the current value
        net (DESIGN §2, "Initial priority", as the actors score new fragments)."""
        cfg = self.config
        kappa = cfg.priority_kappa
        returns = discounted_sums(rewards, discounts).abs() if kappa else None
        if cfg.priority_mode == "trajectory":
            return td_abs.sum(0) + (kappa * returns.mean(0) if kappa else 0.0)
        if cfg.priority_mode == "step":
            return (td_abs + (kappa * returns if kappa else 0.0)).T
        return torch.ones_like(td_abs[0])

    def _metrics(self, b: Batch, t: loss.Targets, terms: loss.LossTerms, values: torch.Tensor,
                 target_logp: torch.Tensor) -> torch.Tensor:
        cfg = self.config
        ratio = torch.exp(terms.log_ratio)
        var_vs = t.vs.var()
        explained = torch.where(var_vs > 0, 1.0 - (t.vs - values.detach()[:-1]).var() / var_vs,
                                0.0)
        target_clipped = ((b.behaviour_logp - target_logp >= math.log(cfg.rho_target_bar))
                          .float().mean() if cfg.clip_anchor == "target"
                          else torch.zeros((), device=ratio.device))
        return torch.stack([  # METRICS but the last two, which `apply` adds
            terms.policy, terms.value, terms.entropy, terms.kl,
            ((ratio - 1.0) - terms.log_ratio).mean(),
            ((ratio - 1.0).abs() > cfg.clip_coef).float().mean(), explained, target_clipped])

    def apply(self, state: State, grads: list[torch.Tensor], metrics: torch.Tensor,
              traced: bool) -> None:
        cfg = self.config
        grad_norm = torch.nn.utils.get_total_norm(grads)
        torch._foreach_mul_(grads, torch.clamp(cfg.max_grad_norm / (grad_norm + 1e-6), max=1.0))
        if not traced:  # the clipped gradients where autograd would leave them, to inspect
            for p, g in zip(state.params, grads, strict=True):
                p.grad = g
        # Compiled on the CPU, the single-tensor form, which the compiler fuses with the rest
        # (the fused kernel is opaque to it); eager, fused on the CPU; capturable on a GPU.
        on_cpu = self.device_type == "cpu"
        kernel = ({"foreach": False, "fused": not traced} if on_cpu
                  else {"foreach": True, "fused": False})
        adam(state.params, grads, state.exp_avgs, state.exp_avg_sqs, [], state.steps,
             capturable=not on_cpu, **kernel, amsgrad=False, beta1=ADAM_BETAS[0],
             beta2=ADAM_BETAS[1], lr=state.lr, weight_decay=0.0, eps=cfg.adam_eps,
             maximize=False)
        if self.global_log_std:
            log_std = state.params[self.layout.log_std_at]
            log_std.copy_(torch.minimum(log_std, state.ceiling))
        if cfg.clip_anchor == "target":
            policy_params = [state.params[i] for i in self.policy_indices]
            torch._foreach_lerp_(state.target, policy_params, cfg.tau)
        if cfg.kl_target > 0:
            kl, coef = metrics[3], state.kl_coef
            coef = torch.where(kl > 1.5 * cfg.kl_target, coef * 2.0,
                               torch.where(kl < cfg.kl_target / 1.5, coef * 0.5, coef))
            state.kl_coef.copy_(coef.clamp(1e-6, 1e3))
        state.metric_sums.add_(torch.cat([metrics, grad_norm[None], state.kl_coef[None]]))



@dataclass
class StepResult:
    metrics: dict[str, float]
    priority_keys: np.ndarray  # replay keys of the prioritized samples
    priorities: list = field(default_factory=list)  # float (trajectory) or array (step) each


class Learner:
    """Owns the model, the target policy, the optimiser and the update's other tensors;
    `update` is one gradient update.

    `device`: where the networks, the target policy, the optimiser's state, the KL coefficient,
    the log-std ceiling and the metrics live (the model is moved there). The normalisers'
    moments stay in float64 on the host, merged per inserted fragment; their current affine
    map goes to the device with each update."""

    def __init__(self, model: ActorCritic, config: LossConfig,
                 device: torch.device | str = "cpu"):
        self.device = on = torch.device(device)
        self.model = model.to_device(on)
        self.config = config
        self.target_policy = copy.deepcopy(model.policy).requires_grad_(False)
        self.params = list(model.parameters())
        self._metric_count = 0
        self.updates = 0
        self.rules = Update(
            config, [n for n, _ in model.named_parameters()],
            [n for n, _ in self.target_policy.named_parameters()], model.obs_clip,
            model.policy.policy_std == "global", on.type)
        self.run_update: Callable = self.rules
        # Adam's moments and step counts at zero, as its first step would make them; the
        # torch.optim.Adam that owns them for checkpoints is made when first asked for
        # (`optimizer`): its construction imports TorchDynamo (~1 s), which the first update
        # need not wait for. The log-std ceiling starts at +∞ (free); the caller moves it
        # along its schedule (`log_std_ceiling`).
        self._optimizer: torch.optim.Adam | None = None
        self.state = State(
            self.params, list(self.target_policy.parameters()),
            [torch.zeros_like(p) for p in self.params], [torch.zeros_like(p) for p in self.params],
            [torch.zeros((), device=on) for _ in self.params],
            lr=torch.tensor(float(config.learning_rate), device=on),
            kl_coef=torch.tensor(float(config.kl_coef), device=on),
            ceiling=torch.tensor(math.inf, device=on),
            metric_sums=torch.zeros(len(METRICS), device=on))

    def _optimizer_options(self, lr: torch.Tensor) -> dict:
        """torch.optim.Adam's settings: the learning rate a device tensor (a schedule moves it
        without a compiled update being traced again), fused on the CPU, capturable on an
        accelerator (its step count on the device, so nothing is read back)."""
        options = {"lr": lr, "eps": self.config.adam_eps, "betas": ADAM_BETAS}
        if self.device.type == "cpu":
            return {**options, "fused": True}
        return {**options, "foreach": True, "capturable": True}

    @property
    def optimizer(self) -> torch.optim.Adam:
        """torch.optim.Adam over the parameters, holding the update's own moments, step counts
        and learning rate (the same tensors): its state dict is the checkpoint's."""
        if self._optimizer is None:
            opt = torch.optim.Adam(self.params, **self._optimizer_options(self.state.lr))
            opt.param_groups[0]["lr"] = self.state.lr  # the very tensor a schedule fills
            for i, p in enumerate(self.params):
                opt.state[p] = {"step": self.state.steps[i], "exp_avg": self.state.exp_avgs[i],
                                "exp_avg_sq": self.state.exp_avg_sqs[i]}
            self._optimizer = opt
        return self._optimizer

    def _state_from_optimizer(self) -> None:
        """After the optimiser loaded a state dict: the update works on its new tensors."""
        opt = self.optimizer
        self.state = self.state._replace(
            exp_avgs=[opt.state[p]["exp_avg"] for p in self.params],
            exp_avg_sqs=[opt.state[p]["exp_avg_sq"] for p in self.params],
            steps=[opt.state[p]["step"] for p in self.params], lr=opt.param_groups[0]["lr"])

    def use(self, run_update: Callable) -> None:
        """Run updates with this version of `rules` (a compiled one: the same function,
        traced), called as run_update(state, batch, norm)."""
        self.run_update = run_update

    # -- settings the caller moves between updates (no read-back: in-place fills)
    @property
    def kl_coef(self) -> float:
        return float(self.state.kl_coef)

    @kl_coef.setter
    def kl_coef(self, value: float) -> None:
        self.state.kl_coef.fill_(float(value))

    @property
    def log_std_ceiling(self) -> float | None:
        value = float(self.state.ceiling)
        return None if math.isinf(value) else value

    @log_std_ceiling.setter
    def log_std_ceiling(self, value: float | None) -> None:
        self.state.ceiling.fill_(math.inf if value is None else float(value))

    def set_learning_rate(self, lr: float) -> None:
        self.state.lr.fill_(lr)

    def learning_rate(self) -> float:
        return float(self.state.lr)

    # -- normaliser statistics: merged once per *inserted* fragment, never per sample
    def observe(self, fragment: Fragment) -> None:
        self.model.obs_rms.update(fragment.obs[:-1])
        self.model.ret_rms.update(fragment.disc_returns)

    def normaliser(self) -> torch.Tensor:
        """[2·obs + 1]: the observations' mean and 1/std, then the reward scale, as the
        moments stand now, on the device."""
        mean, inv_std = self.model.obs_affine()
        host = np.concatenate([mean, inv_std, [self.model.reward_scale()]]).astype(np.float32)
        return to_device(host, self.device, pin=self.device.type != "cpu")

    # -- one update
    def step(self, fragments: FragmentBatch, keys: np.ndarray, weights: np.ndarray,
             from_prioritized: np.ndarray, step_weights: np.ndarray | None = None
             ) -> StepResult:
        """One update on `fragments` (B of them, stacked) with this update's metrics and the
        new priorities read back: for tools and tests. `weights` [B] are the replay's
        importance weights; in step mode `step_weights` [B, T] weigh each step instead."""
        self.read_metrics()
        priorities = self.update(place(fragments, weights, step_weights, self.device),
                                 self.normaliser())
        idx = np.flatnonzero(from_prioritized)
        chosen = priorities.cpu().numpy()[idx].astype(np.float64)
        return StepResult(self.read_metrics(), np.asarray(keys)[idx], list(chosen))

    def update(self, batch: Batch, norm: torch.Tensor) -> torch.Tensor:
        """One gradient update on a placed batch with the normalisers' `norm` (`normaliser()`
        once the batch's moments are merged); returns the new priorities of all its fragments
        on the device ([B], or [B, T] per step), for the caller to copy out."""
        priorities = self.run_update(self.state, batch, norm)
        self.updates += 1
        self._metric_count += 1
        return priorities

    def loss_inputs(self, batch: Batch, norm: torch.Tensor) -> LossInputs:
        """What the loss would take on this batch now (for tools and tests)."""
        return self.rules.loss_inputs(self.state, batch, norm)

    def read_metrics(self) -> dict[str, float]:
        """The metrics' means over the updates since the last read (one read-back)."""
        if not self._metric_count:
            return {}
        sums = self.state.metric_sums
        values = (sums / self._metric_count).tolist()
        sums.zero_()
        self._metric_count = 0
        return dict(zip(METRICS, values, strict=True))

    # -- checkpointing (the caller writes the bytes)
    def state_dict(self) -> dict:
        return {
            "model": self.model.state_dict(),
            "target_policy": self.target_policy.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "kl_coef": self.kl_coef,
            "updates": self.updates,
        }

    def load_state_dict(self, state: dict) -> None:
        """A learner's state; the optimiser's is taken in torch.optim.Adam's layout (which
        checkpoints of every version have), its moments, step counts and learning rate kept
        and this learner's own options (ε, device tensors, fused or capturable) put back."""
        self.model.load_state_dict(state["model"])
        self.target_policy.load_state_dict(state["target_policy"])
        saved = state["optimizer"]
        groups = saved["param_groups"]
        if len(groups) != 1 or len(groups[0]["params"]) != len(self.params):
            raise ValueError(f"optimizer state for {[len(g['params']) for g in groups]} "
                             f"parameters, this model has {len(self.params)}")
        if groups[0].get("weight_decay", 0) or groups[0].get("amsgrad", False):
            raise ValueError("optimizer state uses weight decay or AMSGrad, which the learner's "
                             "Adam does not")
        ours = {k: v for k, v in self.optimizer.param_groups[0].items() if k != "params"}
        lr = torch.tensor(float(groups[0]["lr"]), device=self.device)
        self.optimizer.load_state_dict({
            "state": saved["state"],
            "param_groups": [{**ours, **self._optimizer_options(lr),
                              "params": groups[0]["params"]}]})
        self._state_from_optimizer()
        self.kl_coef = float(state["kl_coef"])
        self.updates = int(state["updates"])
