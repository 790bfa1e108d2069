"""The TPDEB learner: IMPACT surrogate on V-trace advantages, KL to the behaviour policy, soft
target policy, prioritized-sample weights and new priorities (DESIGN §2, "Learner loss").

Pure: a `Learner` takes fragments and replay weights and returns metrics and new priorities.
Where the fragments come from and where parameters go is the caller's business.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field

import numpy as np
import torch

from tpdeb.tpdeb_core.adam import Adam
from tpdeb.tpdeb_core.fragments import Fragment, FragmentBatch, fragment_priority
from tpdeb.tpdeb_core.loss_config import LossConfig
from tpdeb.tpdeb_core.model import ActorCritic
from tpdeb.tpdeb_core.moments import inverse_std
from tpdeb.tpdeb_core.numpy_policy import LOG_2PI
from tpdeb.tpdeb_core.vtrace import vtrace_arrays


@dataclass
class StepResult:
    metrics: dict[str, float]
    priority_keys: np.ndarray  # replay keys of the prioritized samples
    priorities: list = field(default_factory=list)  # float (trajectory) or array (step) each


def log_prob(mean: np.ndarray, log_std: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """log N(a; m, σ) in numpy, summed over the last axis; σ = exp(log_std) is state-independent
    [A]."""
    z = (actions - mean) * np.exp(-log_std)
    z *= z
    return -0.5 * z.sum(-1) - (log_std.sum() + 0.5 * LOG_2PI * log_std.size)


class LossTerms:
    """The loss of one update and its gradient with respect to the networks' outputs.

    With w the per-step weights (Σ w = 1), r = exp(log r) the surrogate's ratio, A the
    advantages, d = a − m, σ⁻² = exp(−2 log σ):
      pg = −Σ w·min(r·A, clip(r, 1−ε, 1+ε)·A) = −Σ w·A·clamp(r, lo, hi), where hi = 1+ε for
           A > 0 (else ∞) and lo = 1−ε for A < 0 (else −∞): the same value and gradient;
      value = ½ Σ w (V − v_s)²;  entropy = Σ_a log σ_a + A/2 (1 + log 2π);
      KL(μ‖π) = Σ w ½ Σ_a [σ_μ²/σ² + (m_μ − m)²/σ² − 1 − 2 (log σ_μ − log σ)];
      loss = pg + c_v·value − c_ent·entropy + λ_kl·KL.
    ∂log r/∂m = d σ⁻², ∂log r/∂log σ = d² σ⁻² − 1 (per action dimension), ∂r/∂log r = r.
    """

    def __init__(self, cfg: LossConfig, kl_coef: float, f: FragmentBatch, w: np.ndarray,
                 mean: np.ndarray, log_std: np.ndarray, values: np.ndarray, vs: np.ndarray,
                 adv: np.ndarray, log_ratio: np.ndarray):
        act_dim = log_std.size
        inv_var = np.exp(-2.0 * log_std)
        d = f.actions - mean
        self.log_ratio = log_ratio
        self.ratio = r = np.exp(log_ratio)
        clip = cfg.clip_coef
        positive = adv > 0
        lo = np.where(positive, -np.inf, 1.0 - clip)
        hi = np.where(positive, 1.0 + clip, np.inf)
        weighted_adv = w * adv
        self.pg_loss = -float((weighted_adv * np.clip(r, lo, hi)).sum())
        # d pg / d log r: zero where the clamp holds r (torch.clamp's gradient passes at its
        # bounds, as here)
        g_logp = -weighted_adv * ((r >= lo) & (r <= hi)) * r  # [T, B]
        v_error = values[:-1] - vs
        self.value_loss = 0.5 * float((w * v_error * v_error).sum())
        self.entropy = float(log_std.sum() + 0.5 * (1.0 + LOG_2PI) * act_dim)
        w3 = w[..., None]
        mu_gap = f.behaviour_mean - mean  # [T, B, A]
        spread = (w3 * (np.exp(2.0 * f.behaviour_log_std) + mu_gap * mu_gap)).sum((0, 1))
        mu_log_std = float((w3 * f.behaviour_log_std).sum())
        self.kl = 0.5 * float((inv_var * spread).sum() - act_dim
                              - 2.0 * (mu_log_std - log_std.sum()))
        g_pg = g_logp[..., None] * d  # [T, B, A], times σ⁻² below
        self.grad_mean = ((g_pg - kl_coef * w3 * mu_gap) * inv_var).astype(np.float32)
        self.grad_log_std = ((g_pg * d).sum((0, 1)) * inv_var - g_logp.sum() - cfg.ent_coef
                             + kl_coef * (1.0 - inv_var * spread)).astype(np.float32)
        self.grad_values = np.zeros_like(values, dtype=np.float32)
        self.grad_values[:-1] = cfg.vf_coef * w * v_error


def mean_of(x: np.ndarray) -> float:
    """The mean of all elements (np.mean's Python layers cost ~15 µs a call, measured in a
    profile of Learner.step; a reduction alone a few)."""
    return float(np.add.reduce(x, axis=None)) / x.size


def sample_std(centred: np.ndarray) -> float:
    """The unbiased standard deviation of already centred values (for a [64, 8] batch: a dot
    product, 0.6 µs, where np.std takes 7.5 µs)."""
    flat = centred.ravel()
    return math.sqrt(float(flat @ flat) / max(flat.size - 1, 1))


def _layers(net: torch.nn.Sequential) -> list[tuple[torch.Tensor, torch.Tensor]]:
    return [(m.weight, m.bias) for m in net if isinstance(m, torch.nn.Linear)]


def _mlp(layers, x: torch.Tensor) -> torch.Tensor:
    """The tanh MLP of `tpdeb_core.model.mlp` on its held weights: the same function without
    nn.Module's call machinery (three calls per network per update add up at this size)."""
    last = len(layers) - 1
    for i, (weight, bias) in enumerate(layers):
        x = torch.nn.functional.linear(x, weight, bias)
        if i < last:
            x = torch.tanh(x)
    return x


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
        self.mean_layers = _layers(model.policy.mean)
        self.value_layers = _layers(model.value_net)
        self.target_layers = _layers(self.target_policy.mean)
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
        """One update on `fragments` (B of them, stacked). `weights` [B] are the replay's
        importance weights; in step mode `step_weights` [B, T] weigh each step instead (Σ of the
        weights of the transitions drawn there, 0 where none was).

        Every per-transition term of the loss (surrogate, value, entropy, KL) is the same
        weighted mean Σ w·ℓ / Σ w. Normalising by Σ w rather than by the count keeps the terms
        in proportion whatever the scale of the weights: step-level PER's weights
        (p / p_min)^(−β) can all sit far below 1, and a count-normalised surrogate and value
        loss then vanish beside an unweighted entropy bonus.

        Only the networks run in torch. The loss is a function of their outputs — the policy
        mean [T, B, A], the values [T+1, B] and the state-independent log-std [A] — whose
        gradient with respect to those outputs has a closed form (`LossTerms`); it is computed
        in numpy and handed to autograd for the networks' backward pass. At these sizes each
        torch operation costs more in dispatch than in arithmetic, so the ~45 elementwise ops
        of the loss and their backward nodes cost more than the few numpy expressions that
        replace them. tests/test_learner.py holds it to the loss written plainly in torch."""
        cfg, f = self.config, fragments
        T, B = f.rewards.shape
        anchored = cfg.clip_anchor == "target"

        # -- inputs (current normaliser statistics; rewards scaled at learn time)
        obs_mean, obs_inv_std = self._obs_affine()
        obs_np = (f.obs - obs_mean) * obs_inv_std
        np.clip(obs_np, -self.model.obs_clip, self.model.obs_clip, out=obs_np)
        obs = torch.from_numpy(obs_np)  # [T+1, B, obs_dim]
        if step_weights is not None:
            w = np.asarray(step_weights, np.float32)[:, :T].T.copy()
        else:
            w = np.broadcast_to(np.asarray(weights, np.float32), (T, B)).copy()
        w /= max(float(w.sum()), 1e-12)

        # -- the networks (the only part autograd sees)
        mean_t = _mlp(self.mean_layers, obs[:-1])  # [T, B, A]
        values_t = _mlp(self.value_layers, obs).squeeze(-1)  # [T+1, B]
        with torch.no_grad():
            mean, values = mean_t.detach().numpy(), values_t.detach().numpy()
            log_std = self.model.policy.log_std.detach().numpy()
            logp = log_prob(mean, log_std, f.actions)
            if anchored:
                t_mean = _mlp(self.target_layers, obs[:-1]).numpy()
                t_logp = log_prob(t_mean, self.target_policy.log_std.numpy(), f.actions)
            else:  # PPO: V-trace toward the policy being trained
                t_logp = logp
            rewards = f.rewards * np.float32(self.model.reward_scale())
            discounts = (cfg.gamma * ~(f.terminated | f.truncated)).astype(np.float32)
            if len(f.trunc_t):
                # Truncation: bootstrap from the real final observation through the reward and
                # cut the trace there (discount 0), so nothing flows across the episode end.
                final_obs = np.clip((f.trunc_obs - obs_mean) * obs_inv_std,
                                    -self.model.obs_clip, self.model.obs_clip)
                final_values = _mlp(self.value_layers, torch.from_numpy(final_obs))
                not_term = ~f.terminated[f.trunc_t, f.trunc_b]
                np.add.at(rewards, (f.trunc_t, f.trunc_b),
                          cfg.gamma * not_term * final_values.squeeze(-1).numpy())

        # -- V-trace targets and advantages
        b_logp = np.asarray(f.behaviour_logp, np.float32)
        vs, adv, rhos, deltas = vtrace_arrays(
            b_logp, t_logp, rewards, values[:-1], values[-1], discounts, cfg.rho_bar, cfg.c_bar,
            cfg.rho_pg_bar, cfg.vtrace_lambda)
        if cfg.norm_adv:
            adv = adv - mean_of(adv)
            adv /= sample_std(adv) + 1e-8
        # IMPACT: r = is · π_θ/μ with is = min(μ/π_θ̄, ρ̄_target), the clip centred on the target
        # policy; PPO: r = π_θ/μ.
        log_is = (np.minimum(b_logp - t_logp, math.log(cfg.rho_target_bar)) if anchored
                  else 0.0)
        terms = LossTerms(cfg, self.kl_coef, f, w, mean, log_std, values, vs, adv,
                          logp - b_logp + log_is)

        # -- backward through the networks, the optimiser, the target
        self.optimizer.zero_grad(set_to_none=True)
        torch.autograd.backward((mean_t, values_t), (torch.from_numpy(terms.grad_mean),
                                                     torch.from_numpy(terms.grad_values)))
        self.model.policy.log_std.grad = torch.from_numpy(terms.grad_log_std)
        grad_norm = self._clip_gradients(cfg.max_grad_norm)
        self.optimizer.step()
        if anchored:
            self._soft_update_target()
        self.updates += 1
        if cfg.kl_target > 0:
            self._adapt_kl_coef(terms.kl)

        var_vs = sample_std(vs - mean_of(vs)) ** 2
        residual = vs - values[:-1]
        explained = (1.0 - sample_std(residual - mean_of(residual)) ** 2 / var_vs if var_vs > 0
                     else 0.0)
        metrics = {
            "losses/policy_loss": terms.pg_loss, "losses/value_loss": terms.value_loss,
            "losses/entropy": terms.entropy, "losses/kl_behaviour": terms.kl,
            "losses/kl_coef": self.kl_coef,
            "losses/approx_kl": mean_of((terms.ratio - 1.0) - terms.log_ratio),
            "losses/clipfrac": mean_of(np.abs(terms.ratio - 1.0) > cfg.clip_coef),
            "losses/explained_variance": explained, "losses/grad_norm": grad_norm,
            "losses/target_is_clipfrac": mean_of(b_logp - t_logp >= math.log(cfg.rho_target_bar))
            if anchored else 0.0,
        }
        td_abs = np.abs(rhos * deltas)
        return StepResult(metrics, *self._new_priorities(td_abs, rewards, discounts, keys,
                                                         from_prioritized))

    def _obs_affine(self) -> tuple[np.ndarray, np.ndarray]:
        """The observation normaliser as float32 (mean, 1/std) (its current statistics)."""
        rms = self.model.obs_rms
        return (rms.mean.numpy().astype(np.float32),
                inverse_std(float(rms.count), rms.m2.numpy(), rms.epsilon).astype(np.float32))

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
        flat = [g.numpy().ravel() for g in grads]
        total = math.sqrt(sum(float(x @ x) for x in flat))
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
