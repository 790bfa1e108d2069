"""The loss as written (`tpdeb_core/loss.py`, differentiated by autograd) held to its gradient
derived by hand, term by term, over the settings that change it; a term added in a test reaches
the parameters through autograd; and an update reads nothing back to the host."""

import dataclasses
import itertools

import numpy as np
import pytest
import torch

from tpdeb.tpdeb_core import learner as learner_module
from tpdeb.tpdeb_core import loss, policy
from tpdeb.tpdeb_core.fragments import FragmentBatch
from tpdeb.tpdeb_core.learner import Learner, place
from tpdeb.tpdeb_core.loss_config import LossConfig
from tpdeb.tpdeb_core.model import ActorCritic
from tpdeb.tpdeb_core.policy import NUMPY

T, B, OBS, ACT = 8, 6, 3, 2
ENDS = ("none", "terminated", "truncated", "both")


def make_batch(ends: str, seed: int = 0) -> FragmentBatch:
    """B random fragments whose behaviour policy is a Gaussian that differs from the learner's,
    with the episode ends asked for."""
    rng = np.random.default_rng(seed)
    f32 = lambda *shape, scale=1.0: (rng.normal(size=shape) * scale).astype(np.float32)  # noqa: E731
    terminated = np.zeros((T, B), bool)
    truncated = np.zeros((T, B), bool)
    if ends in ("terminated", "both"):
        terminated[[2, 5], [0, 3]] = True
    if ends in ("truncated", "both"):
        truncated[[3, 6, 7], [1, 3, 5]] = True
        terminated[6, 3] = ends == "both"  # terminated and truncated at once: no bootstrap
    trunc_t, trunc_b = (x.astype(np.int32) for x in np.nonzero(truncated))
    mean, log_std = f32(T, B, ACT, scale=0.3), f32(T, B, ACT, scale=0.2) - 0.3
    actions = (mean + np.exp(log_std) * f32(T, B, ACT)).astype(np.float32)
    return FragmentBatch(
        obs=f32(T + 1, B, OBS, scale=2.0), actions=actions, rewards=f32(T, B),
        terminated=terminated, truncated=truncated, behaviour_mean=mean,
        behaviour_log_std=log_std,
        behaviour_logp=policy.log_prob(mean, log_std, actions, NUMPY).astype(np.float32),
        trunc_t=trunc_t, trunc_b=trunc_b, trunc_obs=f32(len(trunc_t), OBS),
        policy_version=np.zeros(B, np.int64))


def learner(config_class=LossConfig, policy_std="global", **settings) -> Learner:
    torch.manual_seed(1)
    model = ActorCritic(OBS, ACT, (16, 16), init_log_std=-0.2, policy_std=policy_std)
    model.obs_rms.update(np.random.default_rng(2).normal(0.5, 2.0, size=(50, OBS)))
    model.ret_rms.update(np.random.default_rng(3).normal(0, 3, size=50))
    learner = Learner(model, config_class(kl_coef=0.3, ent_coef=0.01, vtrace_lambda=0.95,
                                          **settings))
    with torch.no_grad():  # π_θ̄ ≠ π_θ: the target's ratios and clip are exercised
        for p in learner.target_policy.parameters():
            p.add_(0.2 * torch.randn_like(p))
    return learner


def hand_gradients(cfg, kl_coef, batch, t, mean, log_std, values):
    """∂L/∂(mean [T, B, A], values [T+1, B], global log-std [A]) derived by hand, in numpy.
    With d = a − m, σ⁻² = exp(−2 log σ) and r = exp(log r): pg = −Σ w·A·clamp(r, lo, hi) where
    hi = 1+ε for A > 0 (else ∞) and lo = 1−ε for A < 0 (else −∞); value = ½ Σ w (V − v)²;
    entropy = Σ_a log σ_a + A/2 (1 + log 2π); KL(μ‖π) = Σ w ½ Σ_a [σ_μ²/σ² + (m_μ − m)²/σ² − 1
    − 2 (log σ_μ − log σ)]; ∂log r/∂m = d σ⁻², ∂log r/∂log σ = d² σ⁻² − 1."""
    w, adv = t.weights, t.advantages
    inv_var = np.exp(-2.0 * log_std)
    d = batch.actions - mean
    logp = policy.log_prob(mean, log_std, batch.actions, NUMPY)
    r = np.exp(logp - batch.behaviour_logp + t.log_is)
    positive = adv > 0
    lo = np.where(positive, -np.inf, 1.0 - cfg.clip_coef)
    hi = np.where(positive, 1.0 + cfg.clip_coef, np.inf)
    g_logp = -w * adv * ((r >= lo) & (r <= hi)) * r  # zero where the clamp holds r
    w3 = w[..., None]
    mu_gap = batch.behaviour_mean - mean
    spread = (w3 * (np.exp(2.0 * batch.behaviour_log_std) + mu_gap * mu_gap)).sum((0, 1))
    g_pg = g_logp[..., None] * d
    grad_values = np.zeros_like(values)
    grad_values[:-1] = cfg.vf_coef * w * (values[:-1] - t.vs)
    return ((g_pg - kl_coef * w3 * mu_gap) * inv_var, grad_values,
            (g_pg * d).sum((0, 1)) * inv_var - g_logp.sum() - cfg.ent_coef
            + kl_coef * (1.0 - inv_var * spread))


CASES = list(itertools.product(("target", "behaviour"), ("trajectory", "step"), (True, False),
                               ENDS))


@pytest.mark.parametrize("anchor,weighting,norm_adv,ends", CASES)
def test_the_loss_gradient_equals_the_hand_derived_one(anchor, weighting, norm_adv, ends):
    """The networks' outputs through `forward` with the loss's gradient taken by autograd
    against the closed form above, for every term, weighting and episode end."""
    rng = np.random.default_rng(4)
    weights = rng.uniform(0.2, 1.0, B).astype(np.float32)
    step_weights = None
    if weighting == "step":  # Σ of the draws' weights per step; zero where none was drawn
        step_weights = (rng.uniform(0.0, 2.0, (B, T)) * (rng.random((B, T)) < 0.7)).astype(
            np.float32)
    # no norm clip: the log-std's gradient is the parameter's own, read after the step
    x = learner(clip_anchor=anchor, norm_adv=norm_adv, priority_mode=weighting,
                max_grad_norm=1e9)
    batch = make_batch(ends)
    seen = {}
    real_loss = loss.loss

    def spy(cfg, kl_coef, b, t, mean, log_std, values):
        for name, tensor in (("mean", mean), ("log_std", log_std), ("values", values)):
            tensor.retain_grad()
            seen[name] = tensor
            seen[name + " before"] = tensor.detach().clone()  # the step moves a parameter
        seen["batch"], seen["targets"] = b, t
        return real_loss(cfg, kl_coef, b, t, mean, log_std, values)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(loss, "loss", spy)
        x.step(batch, np.arange(B), weights, np.ones(B, bool), step_weights)
    b, t = seen["batch"], seen["targets"]
    arr = lambda v: v.detach().numpy() if isinstance(v, torch.Tensor) else v  # noqa: E731
    host = type("HostBatch", (), {k: arr(getattr(b, k)) for k in b._fields})
    targets = dataclasses.replace(t, **{f.name: arr(getattr(t, f.name))
                                         for f in dataclasses.fields(t)})
    expected = hand_gradients(x.config, 0.3, host, targets, arr(seen["mean before"]),
                              arr(seen["log_std before"]), arr(seen["values before"]))
    for name, want in zip(("mean", "values", "log_std"), expected, strict=True):
        np.testing.assert_allclose(seen[name].grad.numpy(), want, rtol=2e-4, atol=1e-6,
                                   err_msg=name)


@dataclasses.dataclass
class WithValueClip(LossConfig):
    value_clip: float = 0.0  # a setting of a term added to the loss


def test_a_term_added_to_the_loss_reaches_the_parameters_through_autograd():
    """What adding a regulariser takes: a setting and the term in `loss.loss` (here a wrapper in
    this test, a line in loss.py in the product); nothing else learns of it."""
    real_loss = loss.loss

    def with_term(cfg, kl_coef, batch, t, mean, log_std, values):
        total, terms = real_loss(cfg, kl_coef, batch, t, mean, log_std, values)
        return total + cfg.value_clip * (values ** 2).sum(), terms

    batch = make_batch("both")
    grads = {}
    for coef in (0.0, 0.5):
        x = learner(WithValueClip, value_clip=coef, max_grad_norm=1e9)  # no rescaling
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(loss, "loss", with_term)
            x.step(batch, np.arange(B), np.ones(B, np.float32), np.zeros(B, bool))
        grads[coef] = {n: p.grad.clone() for n, p in x.model.named_parameters()}
    moved = {n for n in grads[0.0] if not torch.allclose(grads[0.0][n], grads[0.5][n])}
    assert moved and all(n.startswith("value_net.") for n in moved)


def test_an_update_reads_nothing_back_to_the_host(monkeypatch):
    """The update as the service runs it (a placed batch): no .item(), .cpu(), .numpy(),
    .tolist(), float() or bool() of a tensor anywhere inside it, so on an accelerator it never
    waits for the device."""
    for ends, mode, kappa in (("both", "trajectory", 0.5), ("truncated", "step", 0.0)):
        x = learner(priority_mode=mode, priority_kappa=kappa, kl_target=0.01)
        x.log_std_ceiling = -0.5
        batch = place(make_batch(ends), np.ones(B, np.float32), None, x.device)
        norm = x.normaliser()
        x.update(batch, norm)  # a first update outside: the optimiser's state is made
        calls: list[str] = []

        def refuse(name, calls=calls):
            def host_read(*args, **kwargs):
                calls.append(name)
                raise AssertionError(f"the update read a tensor back: Tensor.{name}")
            return host_read

        with monkeypatch.context() as patch:
            for name in ("item", "cpu", "numpy", "tolist", "__float__", "__bool__", "__int__"):
                patch.setattr(torch.Tensor, name, refuse(name))
            priorities = x.update(batch, norm)
        assert not calls
        assert priorities.shape == ((B,) if mode == "trajectory" else (B, T))
        assert set(x.read_metrics()) == set(learner_module.METRICS)
