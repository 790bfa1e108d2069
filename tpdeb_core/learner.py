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

from tpdeb_core.fragments import Fragment, fragment_priority
from tpdeb_core.loss_config import LossConfig
from tpdeb_core.model import ActorCritic, gaussian_entropy, gaussian_kl, gaussian_log_prob
from tpdeb_core.vtrace import vtrace_terms


@dataclass
class Batch:
    """Fragments stacked time-major: [T(+1), B, ...] tensors."""

    obs: torch.Tensor
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


def collate(fragments: list[Fragment]) -> Batch:
    def stack(name: str, dtype=torch.float32) -> torch.Tensor:
        arr = np.stack([getattr(f, name) for f in fragments], axis=1)
        return torch.as_tensor(arr).to(dtype)

    trunc_b = np.concatenate([np.full(len(f.trunc_index), b) for b, f in enumerate(fragments)])
    return Batch(
        obs=stack("obs"),
        actions=stack("actions"),
        rewards=stack("rewards"),
        terminated=stack("terminated"),
        truncated=stack("truncated"),
        behaviour_mean=stack("behaviour_mean"),
        behaviour_log_std=stack("behaviour_log_std"),
        behaviour_logp=stack("behaviour_logp"),
        trunc_t=torch.as_tensor(np.concatenate([f.trunc_index for f in fragments])).long(),
        trunc_b=torch.as_tensor(trunc_b).long(),
        trunc_obs=torch.as_tensor(np.concatenate([f.trunc_obs for f in fragments])).float(),
    )


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
        self.optimizer = torch.optim.Adam(
            model.parameters(), lr=config.learning_rate, eps=config.adam_eps)
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
        fragments: list[Fragment],
        keys: np.ndarray,
        weights: np.ndarray,
        from_prioritized: np.ndarray,
        step_weights: np.ndarray | None = None,
    ) -> StepResult:
        """One update on `fragments` ([B] of them). `weights` [B] are the replay's importance
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
        grad_norm = torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.max_grad_norm)
        self.optimizer.step()
        if anchored:
            self._soft_update_target()
        self.updates += 1
        if cfg.kl_target > 0:
            self._adapt_kl_coef(kl.item())

        with torch.no_grad():
            approx_kl = ((ratio - 1.0) - log_ratio).mean().item()
            clipfrac = ((ratio - 1.0).abs() > cfg.clip_coef).float().mean().item()
            var_vs = vt.vs.var()
            explained = (1.0 - (vt.vs - values[:-1]).var() / var_vs).item() if var_vs > 0 else 0.0
        metrics = {
            "losses/policy_loss": pg_loss.item(),
            "losses/value_loss": value_loss.item(),
            "losses/entropy": entropy.item(),
            "losses/kl_behaviour": kl.item(),
            "losses/kl_coef": self.kl_coef,
            "losses/approx_kl": approx_kl,
            "losses/clipfrac": clipfrac,
            "losses/explained_variance": explained,
            "losses/grad_norm": float(grad_norm),
            "losses/target_is_clipfrac": (batch.behaviour_logp - target_logp
                                          >= math.log(cfg.rho_target_bar)).float().mean().item()
            if anchored else 0.0,
        }
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
        tau = self.config.tau
        for target, source in zip(
            self.target_policy.parameters(), self.model.policy.parameters(), strict=True
        ):
            target.lerp_(source, tau)

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
