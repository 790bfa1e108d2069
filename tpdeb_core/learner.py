"""The TPDEB learner: IMPACT surrogate on V-trace advantages, KL to the behaviour policy, soft
target policy, prioritized-sample weights and new priorities (SPEC §2, "Learner loss").

Pure: a `Learner` takes fragments and replay weights and returns metrics and new priorities.
Where the fragments come from and where parameters go is the caller's business.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field

import numpy as np
import torch

from tpdeb_core.adam import Adam
from tpdeb_core.fragments import (
    BATCH_STEP_FIELDS,
    Fragment,
    FragmentBatch,
    fragment_priority,
)
from tpdeb_core.loss_config import LossConfig
from tpdeb_core.model import ActorCritic, gaussian_entropy, gaussian_kl, gaussian_log_prob
from tpdeb_core.vtrace import vtrace_terms


@dataclass
class Batch:
    """A FragmentBatch as float32 torch tensors (copies: the wire's arrays are read-only)."""

    obs: torch.Tensor  # [T+1, B, obs_dim]
    actions: torch.Tensor
    rewards: torch.Tensor
    terminated: torch.Tensor
    truncated: torch.Tensor
    behaviour_mean: torch.Tensor
    behaviour_log_std: torch.Tensor
    behaviour_logp: torch.Tensor
    trunc_t: torch.Tensor  # [K] time index of each truncated step
    trunc_b: torch.Tensor  # [K] batch index
    trunc_obs: torch.Tensor  # [K, obs_dim]


def collate(batch: FragmentBatch) -> Batch:
    def tensor(array: np.ndarray, dtype=torch.float32) -> torch.Tensor:
        return torch.tensor(array, dtype=dtype)

    return Batch(**{name: tensor(getattr(batch, name)) for name in BATCH_STEP_FIELDS},
                 trunc_t=tensor(batch.trunc_t, torch.long),
                 trunc_b=tensor(batch.trunc_b, torch.long), trunc_obs=tensor(batch.trunc_obs))


def impact_surrogate(
    logp: torch.Tensor,
    behaviour_logp: torch.Tensor,
    target_logp: torch.Tensor | None,
    advantages: torch.Tensor,
    clip_coef: float,
    rho_target_bar: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-step IMPACT loss −min(r·A, clip(r, 1−ε, 1+ε)·A) (SPEC §2 step 2) and log r.

    r_t = is_t · π_θ/μ with is_t = min(μ/π_θ̄, ρ̄_target): the clip is centred on the target
    policy, so the policy moves at most ε away from π_θ̄ per sample however stale μ is.
    Without a target policy (`target_logp` None) it is PPO's clipped surrogate, r_t = π_θ/μ.
    """
    log_ratio = logp - behaviour_logp
    if target_logp is not None:
        log_is = torch.clamp(behaviour_logp - target_logp, max=math.log(rho_target_bar))
        log_ratio = log_ratio + log_is.detach()
    ratio = torch.exp(log_ratio)
    clipped = ratio.clamp(1.0 - clip_coef, 1.0 + clip_coef)
    return -torch.min(ratio * advantages, clipped * advantages), log_ratio


METRIC_NAMES = ("losses/policy_loss", "losses/value_loss", "losses/entropy",
                "losses/kl_behaviour", "losses/approx_kl", "losses/clipfrac",
                "losses/explained_variance", "losses/grad_norm", "losses/target_is_clipfrac")


@dataclass
class StepResult:
    metrics: dict[str, float]
    priority_keys: np.ndarray  # replay keys of the prioritized samples
    priorities: list = field(default_factory=list)  # float (trajectory) or array (step) each


class Learner:
    """Owns the model, the target policy and the optimiser; `step` is one gradient update."""

    def __init__(self, model: ActorCritic, config: LossConfig):
        self.model = model
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
        """One update on `fragments` (B of them, stacked). `weights` [B] are the replay's importance
        weights; in step mode `step_weights` [B, T] weigh each step instead (Σ of the weights
        of the transitions drawn there, 0 where none was).

        Every per-transition term of the loss (surrogate, value, entropy, KL) is the same
        weighted mean Σ w·ℓ / Σ w. Normalising by Σ w rather than by the count keeps the terms
        in proportion whatever the scale of the weights: step-level PER's weights
        (p / p_min)^(−β) can all sit far below 1, and a count-normalised surrogate and value
        loss then vanish beside an unweighted entropy bonus."""
        cfg, model = self.config, self.model
        batch = collate(fragments)
        T, B = batch.rewards.shape
        anchored = cfg.clip_anchor == "target"

        obs = model.norm_obs(batch.obs)  # [T+1, B, obs_dim], current statistics
        mean, log_std = model.policy(obs[:-1])
        logp = gaussian_log_prob(mean, log_std, batch.actions)
        values = model.value(obs)  # [T+1, B]
        with torch.no_grad():
            if anchored:
                t_mean, t_log_std = self.target_policy(obs[:-1])
                target_logp = gaussian_log_prob(t_mean, t_log_std, batch.actions)
            else:  # PPO: V-trace toward the policy being trained
                target_logp = logp.detach()
            # Truncation: bootstrap from the real final observation through the reward and cut
            # the trace there (discount 0), so nothing flows across the episode boundary.
            scale = model.reward_scale()
            rewards = batch.rewards * scale
            continues = (1.0 - batch.terminated) * (1.0 - batch.truncated)
            discounts = cfg.gamma * continues
            if len(batch.trunc_t):
                final_values = model.value(model.norm_obs(batch.trunc_obs))
                not_term = 1.0 - batch.terminated[batch.trunc_t, batch.trunc_b]
                rewards = rewards.index_put(
                    (batch.trunc_t, batch.trunc_b), cfg.gamma * not_term * final_values,
                    accumulate=True)
            vt = vtrace_terms(
                batch.behaviour_logp, target_logp, rewards, values[:-1].detach(),
                values[-1].detach(), discounts, cfg.rho_bar, cfg.c_bar, cfg.rho_pg_bar,
                cfg.vtrace_lambda)
            adv = vt.pg_advantages
            if cfg.norm_adv:
                adv = (adv - adv.mean()) / (adv.std() + 1e-8)

        # Per-element loss weights: PER importance weights per fragment, or per step (with the
        # number of draws that hit it) in step mode. Copies: the inputs may be read-only.
        if step_weights is not None:
            w = torch.tensor(np.asarray(step_weights, np.float32)[:, :T].T)
        else:
            w = torch.tensor(np.asarray(weights, np.float32)).expand(T, B)
        w = w / w.sum().clamp_min(1e-12)

        surrogate, log_ratio = impact_surrogate(
            logp, batch.behaviour_logp, target_logp if anchored else None, adv, cfg.clip_coef,
            cfg.rho_target_bar)
        ratio = torch.exp(log_ratio)
        pg_loss = (surrogate * w).sum()
        value_loss = 0.5 * ((values[:-1] - vt.vs).pow(2) * w).sum()
        entropy = (gaussian_entropy(log_std) * w).sum()
        kl = (gaussian_kl(batch.behaviour_mean, batch.behaviour_log_std, mean, log_std) * w).sum()
        loss = pg_loss + cfg.vf_coef * value_loss - cfg.ent_coef * entropy + self.kl_coef * kl

        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        grad_norm = torch.nn.utils.clip_grad_norm_(self.params, cfg.max_grad_norm, foreach=True)
        self.optimizer.step()
        if anchored:
            self._soft_update_target()
        self.updates += 1

        with torch.no_grad():
            var_vs = vt.vs.var()
            target_clipped = ((batch.behaviour_logp - target_logp >= math.log(cfg.rho_target_bar))
                              .float().mean() if anchored else torch.zeros(()))
            # One conversion for every figure: each .item() is a call of its own.
            figures = torch.stack([
                pg_loss, value_loss, entropy, kl, ((ratio - 1.0) - log_ratio).mean(),
                ((ratio - 1.0).abs() > cfg.clip_coef).float().mean(),
                torch.where(var_vs > 0, 1.0 - (vt.vs - values[:-1]).var() / var_vs, 0.0),
                grad_norm, target_clipped]).tolist()
        if cfg.kl_target > 0:
            self._adapt_kl_coef(figures[3])
        metrics = dict(zip(METRIC_NAMES, figures, strict=True))
        metrics["losses/kl_coef"] = self.kl_coef
        return StepResult(metrics, *self._new_priorities(vt, rewards, discounts, keys,
                                                         from_prioritized))

    def _new_priorities(self, vt, rewards, discounts, keys, from_prioritized):
        """Σ_t |ρ_t δ_t| (or per step) for the prioritized samples, on the current value net."""
        td_abs = (vt.clipped_rhos * vt.deltas).abs().numpy()  # [T, B]
        rewards_np, discounts_np = rewards.numpy(), discounts.numpy()
        idx = np.flatnonzero(from_prioritized)
        priorities = [
            fragment_priority(td_abs[:, b], self.config.priority_mode, self.config.priority_kappa,
                              rewards_np[:, b], discounts_np[:, b])
            for b in idx
        ]
        return np.asarray(keys)[idx], priorities

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
