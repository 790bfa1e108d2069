"""The closed-form fast path held to the loss as written (`tpdeb_core/loss.py`, autograd): every
loss term and every parameter gradient, over each configuration the fast path accepts."""

import copy
import dataclasses
import itertools

import numpy as np
import pytest
import torch

from tpdeb.tpdeb_core import policy
from tpdeb.tpdeb_core.fragments import FragmentBatch
from tpdeb.tpdeb_core.learner import Learner
from tpdeb.tpdeb_core.loss_config import CLOSED_FORM_SETTINGS, LossConfig, closed_form_refusal
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


def learner(impl: str, **settings) -> Learner:
    torch.manual_seed(1)
    model = ActorCritic(OBS, ACT, (16, 16), init_log_std=-0.2)
    model.obs_rms.update(np.random.default_rng(2).normal(0.5, 2.0, size=(50, OBS)))
    model.ret_rms.update(np.random.default_rng(3).normal(0, 3, size=50))
    learner = Learner(model, LossConfig(loss_impl=impl, kl_coef=0.3, ent_coef=0.01,
                                        vtrace_lambda=0.95, **settings))
    with torch.no_grad():  # π_θ̄ ≠ π_θ: the target's ratios and clip are exercised
        for p in learner.target_policy.parameters():
            p.add_(0.2 * torch.randn_like(p))
    return learner


CASES = list(itertools.product(("target", "behaviour"), ("trajectory", "step"), (True, False),
                               ENDS))


@pytest.mark.parametrize("anchor,weighting,norm_adv,ends", CASES)
def test_the_closed_form_equals_the_autograd_loss(anchor, weighting, norm_adv, ends):
    batch = make_batch(ends)
    rng = np.random.default_rng(4)
    weights = rng.uniform(0.2, 1.0, B).astype(np.float32)
    step_weights = None
    if weighting == "step":  # Σ of the draws' weights per step; zero where none was drawn
        step_weights = (rng.uniform(0.0, 2.0, (B, T)) * (rng.random((B, T)) < 0.7)).astype(
            np.float32)
    settings = dict(clip_anchor=anchor, norm_adv=norm_adv, priority_mode=weighting)
    autograd, fast = learner("autograd", **settings), learner("closed_form", **settings)
    fast.model.load_state_dict(autograd.model.state_dict())
    fast.target_policy.load_state_dict(autograd.target_policy.state_dict())
    results = [x.step(batch, np.arange(B), weights, np.ones(B, bool), step_weights)
               for x in (autograd, fast)]
    expected, mine = (r.metrics for r in results)
    assert expected["losses/clipfrac"] > 0  # the clip was exercised
    for name, value in expected.items():
        assert mine[name] == pytest.approx(value, rel=1e-4, abs=1e-6), name
    for (name, theirs), ours in zip(autograd.model.named_parameters(), fast.model.parameters(),
                                    strict=True):
        torch.testing.assert_close(ours.grad, theirs.grad, rtol=1e-4, atol=1e-6, msg=name)
        torch.testing.assert_close(ours, theirs, rtol=1e-5, atol=1e-6, msg=name)
    for a, b in zip(results[0].priorities, results[1].priorities, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-5)


def test_the_closed_form_refuses_what_it_does_not_implement():
    model = ActorCritic(OBS, ACT, policy_std="state")
    with pytest.raises(ValueError, match="loss_impl=closed_form .* policy_std='state': set "
                                         "loss_impl=autograd"):
        Learner(model, LossConfig(loss_impl="closed_form"))
    Learner(copy.deepcopy(model), LossConfig(loss_impl="autograd"))  # the definition takes it
    with pytest.raises(ValueError, match="loss_impl='fast'"):
        LossConfig(loss_impl="fast")
    assert closed_form_refusal(LossConfig(), "global") is None


@dataclasses.dataclass
class WithValueClip(LossConfig):
    value_clip: float = 0.0  # a loss setting the closed form has not been taught


def test_a_loss_setting_the_closed_form_was_not_taught_is_refused_unless_at_its_default():
    assert closed_form_refusal(WithValueClip(), "global") is None  # off: the same loss
    with pytest.raises(ValueError, match="does not implement value_clip=0.2: set "
                                         "loss_impl=autograd"):
        Learner(ActorCritic(OBS, ACT), WithValueClip(value_clip=0.2))
    assert {f.name for f in dataclasses.fields(LossConfig)} >= CLOSED_FORM_SETTINGS
