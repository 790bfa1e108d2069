"""The TPDEB learner (DESIGN §2, "The loss"): one update is the targets (V-trace, advantages,
ratios, weights; `tpdeb_core/loss.py`) and then the update (the loss, its gradient, Adam, the
soft target policy, the KL coefficient).

Pure: a `Learner` takes fragments and replay weights and returns metrics and new priorities.
Where the fragments come from and where parameters go is the caller's business.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np
import torch

from tpdeb.tpdeb_core import closed_form, loss, policy
from tpdeb.tpdeb_core.adam import Adam
from tpdeb.tpdeb_core.fragments import Fragment, FragmentBatch, fragment_priority
from tpdeb.tpdeb_core.loss import LossTerms, Targets, mean_of, sample_std
from tpdeb.tpdeb_core.loss_config import LossConfig, closed_form_refusal
from tpdeb.tpdeb_core.model import ActorCritic
from tpdeb.tpdeb_core.policy import NUMPY


@dataclass
class StepResult:
    metrics: dict[str, float]
    priority_keys: np.ndarray  # replay keys of the prioritized samples
    priorities: list = field(default_factory=list)  # float (trajectory) or array (step) each


@dataclass
class Prepared:
    """One batch through the networks, and the loss's constants: what the update needs."""

    mean: torch.Tensor  # π_θ's mean [T, B, A], with its graph
    log_std: torch.Tensor  # its log-std: the parameter [A] or [T, B, A] from the head
    values: torch.Tensor  # V_φ [T+1, B], with its graph
    logp: np.ndarray  # log π_θ(a_t|s_t), no gradient
    target_logp: np.ndarray  # log π_θ̄(a_t|s_t) (π_θ's when the clip is PPO's)
    rewards: np.ndarray  # scaled, with truncations bootstrapped through them
    discounts: np.ndarray  # γ_t, zero at episode ends
    targets: Targets


class Learner:
    """Owns the model, the target policy and the optimiser; `step` is one gradient update.

    `device`: where the networks, the target policy and the optimiser's state live (the model
    is moved there); each batch goes there once per update, in one transfer of its
    observations. The targets (V-trace) and the closed-form gradient are numpy on the CPU."""

    def __init__(self, model: ActorCritic, config: LossConfig,
                 device: torch.device | str = "cpu"):
        refusal = (closed_form_refusal(config, model.policy.policy_std)
                   if config.loss_impl == "closed_form" else None)
        if refusal:
            raise ValueError(refusal)
        self.device = torch.device(device)
        self.model = model.to_device(self.device)
        self.config = config
        self.target_policy = copy.deepcopy(model.policy).requires_grad_(False)
        # Held once: walking the module tree for them on every update costs more than the
        # soft update itself.
        self.params = list(model.parameters())
        self.policy_params = list(model.policy.parameters())
        self.target_params = list(self.target_policy.parameters())
        self.optimizer = Adam(self.params, lr=config.learning_rate, eps=config.adam_eps)
        self.kl_coef = config.kl_coef
        self.updates = 0
        # The global log-std is held at or below this after every step, and the behaviour
        # policies' log-std is read under it in the KL term (None: free); the caller moves it
        # along its schedule.
        self.log_std_ceiling: float | None = None

    # -- normaliser statistics: merged once per *inserted* fragment, never per sample
    def observe(self, fragment: Fragment) -> None:
        self.model.obs_rms.update(fragment.obs[:-1])
        self.model.ret_rms.update(fragment.disc_returns)

    def set_learning_rate(self, lr: float) -> None:
        for group in self.optimizer.param_groups:
            group["lr"] = lr

    def step(
        self,
        fragments: FragmentBatch,
        keys: np.ndarray,
        weights: np.ndarray,
        from_prioritized: np.ndarray,
        step_weights: np.ndarray | None = None,
    ) -> StepResult:
        """One update on `fragments` (B of them, stacked): the targets, then the update.
        `weights` [B] are the replay's importance weights; in step mode `step_weights` [B, T]
        weigh each step instead (Σ of the weights of the transitions drawn there)."""
        p = self.targets(fragments, weights, step_weights)
        terms, grad_norm = self.update(fragments, p)
        td_abs = np.abs(p.targets.rhos * p.targets.deltas)
        return StepResult(self._metrics(fragments, p, terms, grad_norm),
                          *self._new_priorities(td_abs, p.rewards, p.discounts, keys,
                                                from_prioritized))

    def targets(self, f: FragmentBatch, weights: np.ndarray,
                step_weights: np.ndarray | None = None) -> Prepared:
        """The networks on the batch (current normaliser statistics; rewards scaled at learn
        time) and the loss's constants: V-trace targets, advantages, ratios, weights."""
        obs_mean, obs_inv_std = self.model.obs_affine()
        obs = torch.from_numpy(policy.normalize(f.obs, obs_mean, obs_inv_std,
                                                self.model.obs_clip, NUMPY))  # [T+1, B, obs]
        obs = obs.to(self.device)
        mean, log_std = self.model.policy(obs[:-1])
        values = self.model.value(obs)
        with torch.no_grad():
            logp = policy.log_prob(mean.numpy(force=True), log_std.numpy(force=True),
                                   f.actions, NUMPY)
            target_logp = logp
            if self.config.clip_anchor == "target":
                t_mean, t_log_std = self.target_policy(obs[:-1])
                target_logp = policy.log_prob(t_mean.numpy(force=True),
                                              t_log_std.numpy(force=True), f.actions, NUMPY)
            rewards, discounts = self._returns(f, obs_mean, obs_inv_std)
            v = values.numpy(force=True)
        w = loss.replay_weights(weights, step_weights, f.rewards.shape[0])
        t = loss.targets(self.config, w, np.asarray(f.behaviour_logp, np.float32), target_logp,
                         rewards, v, discounts)
        return Prepared(mean, log_std, values, logp, target_logp, rewards, discounts, t)

    def _returns(self, f: FragmentBatch, obs_mean, obs_inv_std):
        """Scaled rewards and discounts γ_t. A truncation bootstraps from the real final
        observation through the reward and cuts the trace there (discount 0), so nothing flows
        across the episode end; a termination does not bootstrap."""
        gamma = self.config.gamma
        rewards = f.rewards * np.float32(self.model.reward_scale())
        discounts = (gamma * ~(f.terminated | f.truncated)).astype(np.float32)
        if len(f.trunc_t):
            final_obs = policy.normalize(f.trunc_obs, obs_mean, obs_inv_std, self.model.obs_clip,
                                         NUMPY)
            final_values = self.model.value(
                torch.from_numpy(final_obs).to(self.device)).numpy(force=True)
            not_term = ~f.terminated[f.trunc_t, f.trunc_b]
            np.add.at(rewards, (f.trunc_t, f.trunc_b), gamma * not_term * final_values)
        return rewards, discounts

    def update(self, f: FragmentBatch, p: Prepared) -> tuple[LossTerms, float]:
        """The loss and its gradient (autograd, or the closed form where it is chosen), the
        clipped Adam step, the soft target update and the KL coefficient's adaptation."""
        cfg = self.config
        if self.log_std_ceiling is not None:
            # The KL term sees μ's std under the same ceiling: the noise level is the
            # schedule's, not pulled back up by wider behaviour policies from earlier on.
            f = dataclasses.replace(f, behaviour_log_std=np.minimum(
                f.behaviour_log_std, np.float32(self.log_std_ceiling)))
        self.optimizer.zero_grad(set_to_none=True)
        if cfg.loss_impl == "autograd":
            total, terms = loss.loss(cfg, self.kl_coef, f, p.targets, p.mean, p.log_std, p.values)
            total.backward()
        else:
            grads, terms = closed_form.loss_and_gradients(
                cfg, self.kl_coef, f, p.targets, p.mean.numpy(force=True),
                p.log_std.numpy(force=True), p.values.numpy(force=True), p.logp)
            on = self.device
            torch.autograd.backward((p.mean, p.values), (torch.from_numpy(grads.mean).to(on),
                                                         torch.from_numpy(grads.values).to(on)))
            self.model.policy.log_std.grad = torch.from_numpy(grads.log_std).to(on)
        grad_norm = self._clip_gradients(cfg.max_grad_norm)
        self.optimizer.step()
        if self.log_std_ceiling is not None:
            with torch.no_grad():
                self.model.policy.log_std.clamp_(max=self.log_std_ceiling)
        if cfg.clip_anchor == "target":
            self._soft_update_target()
        self.updates += 1
        if cfg.kl_target > 0:
            self._adapt_kl_coef(terms.kl)
        return terms, grad_norm

    def _metrics(self, f: FragmentBatch, p: Prepared, terms: LossTerms,
                 grad_norm: float) -> dict[str, float]:
        cfg, vs = self.config, p.targets.vs
        ratio = np.exp(terms.log_ratio)
        var_vs = sample_std(vs - mean_of(vs)) ** 2
        residual = vs - p.values.numpy(force=True)[:-1]
        explained = (1.0 - sample_std(residual - mean_of(residual)) ** 2 / var_vs if var_vs > 0
                     else 0.0)
        log_is_bound = math.log(cfg.rho_target_bar)
        return {
            "losses/policy_loss": terms.policy, "losses/value_loss": terms.value,
            "losses/entropy": terms.entropy, "losses/kl_behaviour": terms.kl,
            "losses/kl_coef": self.kl_coef,
            "losses/approx_kl": mean_of((ratio - 1.0) - terms.log_ratio),
            "losses/clipfrac": mean_of(np.abs(ratio - 1.0) > cfg.clip_coef),
            "losses/explained_variance": explained, "losses/grad_norm": grad_norm,
            "losses/target_is_clipfrac": mean_of(f.behaviour_logp - p.target_logp >= log_is_bound)
            if cfg.clip_anchor == "target" else 0.0,
        }

    def _new_priorities(self, td_abs, rewards, discounts, keys, from_prioritized):
        """Σ_t |ρ_t δ_t| (or per step) for the prioritized samples, on the current value net."""
        idx = np.flatnonzero(from_prioritized)
        priorities = [
            fragment_priority(td_abs[:, b], self.config.priority_mode, self.config.priority_kappa,
                              rewards[:, b], discounts[:, b])
            for b in idx
        ]
        return np.asarray(keys)[idx], priorities

    @torch.no_grad()
    def _clip_gradients(self, max_norm: float) -> float:
        """Scale the gradients to a global L2 norm of at most `max_norm` (as
        torch.nn.utils.clip_grad_norm_); returns the norm before. The norm is summed in numpy
        over views of the gradients: a dot product per tensor costs less than torch's norm
        kernels' dispatch at this size."""
        grads = [p.grad for p in self.params]
        if self.device.type == "cpu":
            flat = [g.numpy().ravel() for g in grads]
            total = math.sqrt(sum(float(x @ x) for x in flat))
        else:  # one reduction on the device, one number back
            total = float(torch.linalg.vector_norm(torch.stack(torch._foreach_norm(grads))))
        scale = max_norm / (total + 1e-6)
        if scale < 1.0:
            torch._foreach_mul_(grads, scale)
        return total

    @torch.no_grad()
    def _soft_update_target(self) -> None:
        torch._foreach_lerp_(self.target_params, self.policy_params, self.config.tau)

    def _adapt_kl_coef(self, kl: float) -> None:
        if kl > 1.5 * self.config.kl_target:
            self.kl_coef *= 2.0
        elif kl < self.config.kl_target / 1.5:
            self.kl_coef *= 0.5
        self.kl_coef = float(min(max(self.kl_coef, 1e-6), 1e3))

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
        self.model.load_state_dict(state["model"])
        self.target_policy.load_state_dict(state["target_policy"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.kl_coef = float(state["kl_coef"])
        self.updates = int(state["updates"])
