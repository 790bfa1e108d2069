"""The learner's loss settings (DESIGN §2, "Learner loss"), apart from the learner itself so that
processes that only read a run's configuration (router, link, launcher) need no torch."""

from __future__ import annotations

from dataclasses import dataclass

from tpdeb.tpdeb_core.replay import PRIORITY_MODES

CLIP_ANCHORS = ("target", "behaviour")


@dataclass
class LossConfig:
    gamma: float = 0.99
    rho_bar: float = 1.0
    c_bar: float = 1.0
    rho_pg_bar: float = 1.0
    rho_target_bar: float = 2.0
    clip_coef: float = 0.2
    kl_coef: float = 0.01
    kl_target: float = 0.0  # > 0: adapt kl_coef toward this KL(μ‖π_θ); 0: fixed coefficient
    vf_coef: float = 0.5
    ent_coef: float = 0.0
    max_grad_norm: float = 0.5
    tau: float = 0.05
    learning_rate: float = 1e-3
    adam_eps: float = 1e-5
    norm_adv: bool = True
    priority_mode: str = "trajectory"
    priority_kappa: float = 0.0
    # "target": IMPACT's surrogate, the ratio to π_θ̄ (TPDEB, IMPACT); "behaviour": PPO's ratio
    # π_θ/μ, V-trace toward the current policy, no target policy (PPO+PER)
    clip_anchor: str = "target"
    vtrace_lambda: float = 1.0  # λ in the V-trace traces c_t = λ·min(c̄, π/μ) (1: plain V-trace)

    def __post_init__(self):
        if self.priority_mode not in PRIORITY_MODES:
            raise ValueError(f"priority_mode={self.priority_mode!r}: use one of {PRIORITY_MODES}")
        if not 0.0 < self.tau <= 1.0:
            raise ValueError(f"tau={self.tau}: the soft target rate must be in (0, 1]")
        if self.clip_anchor not in CLIP_ANCHORS:
            raise ValueError(f"clip_anchor={self.clip_anchor!r}: use one of {CLIP_ANCHORS}")
        if not 0.0 <= self.vtrace_lambda <= 1.0:
            raise ValueError(f"vtrace_lambda={self.vtrace_lambda}: must be in [0, 1]")
        if not 0.0 < self.gamma <= 1.0:
            raise ValueError(f"gamma={self.gamma}: must be in (0, 1]")
