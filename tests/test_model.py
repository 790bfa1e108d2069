import numpy as np
import pytest
import torch
from torch.distributions import Independent, Normal

from tpdeb.services.net.wire import check_params
from tpdeb.tpdeb_core.learner import log_prob
from tpdeb.tpdeb_core.model import (
    ActorCritic,
    RunningMeanStd,
    gaussian_log_prob,
)
from tpdeb.tpdeb_core.moments import batch_moments
from tpdeb.tpdeb_core.numpy_policy import NumpyPolicy, param_shapes


def normal(mean, log_std):
    return Independent(Normal(mean, log_std.exp()), 1)


def test_gaussian_log_probs_match_torch_distributions():
    """torch's (acting in the model) and numpy's (the learner's loss; its entropy and KL are
    held to torch.distributions through the loss in tests/test_learner.py)."""
    g = torch.Generator().manual_seed(0)
    mean_p = torch.randn(32, 6, generator=g)
    log_std_p = torch.randn(32, 6, generator=g) * 0.5
    action = torch.randn(32, 6, generator=g) * 3
    p = normal(mean_p, log_std_p)
    torch.testing.assert_close(gaussian_log_prob(mean_p, log_std_p, action), p.log_prob(action))
    shared = log_std_p[0]  # the learner's log-std is state-independent: one row for all
    np.testing.assert_allclose(
        log_prob(mean_p.numpy(), shared.numpy(), action.numpy()),
        normal(mean_p, shared.expand_as(mean_p)).log_prob(action).numpy(), rtol=1e-5, atol=1e-5)


def test_normaliser_merge_matches_numpy_on_concatenated_data():
    rng = np.random.default_rng(0)
    chunks = [rng.normal(loc=3.0, scale=s, size=(n, 5)) for s, n in [(1, 1), (2, 17), (0.1, 300),
                                                                     (5, 2)]]
    rms = RunningMeanStd(5)
    for chunk in chunks:
        rms.merge(*batch_moments(chunk))
    data = np.concatenate(chunks)
    np.testing.assert_allclose(rms.mean.numpy(), data.mean(0), rtol=1e-12)
    np.testing.assert_allclose(rms.var.numpy(), data.var(0), rtol=1e-10)
    assert rms.count.item() == len(data)
    # merging two normalisers (actor A and actor B) equals one over everything
    a, b = RunningMeanStd(5), RunningMeanStd(5)
    a.update(data[:100])
    b.update(data[100:])
    a.merge(*b.moments())
    np.testing.assert_allclose(a.var.numpy(), data.var(0), rtol=1e-10)


def test_normaliser_state_travels_with_the_model():
    model = ActorCritic(3, 2)
    model.obs_rms.update(np.random.default_rng(0).normal(5.0, 2.0, size=(100, 3)))
    copy = ActorCritic(3, 2)
    copy.load_state_dict(model.state_dict())
    obs = np.ones((4, 3))
    np.testing.assert_array_equal(copy.act_deterministic(obs), model.act_deterministic(obs))
    torch.testing.assert_close(copy.obs_rms.mean, model.obs_rms.mean)


def test_act_logp_is_of_the_raw_sample():
    model = ActorCritic(4, 3)
    out = model.act(np.random.default_rng(0).normal(size=(16, 4)), torch.Generator().manual_seed(1))
    expected = normal(torch.as_tensor(out["mean"]), torch.as_tensor(out["log_std"])).log_prob(
        torch.as_tensor(out["action"]))
    np.testing.assert_allclose(out["logp"], expected.numpy(), rtol=1e-5)


def test_numpy_policy_matches_the_torch_model_to_float32_tolerance():
    torch.manual_seed(0)
    model = ActorCritic(5, 3, (16, 16), init_log_std=-0.3)
    model.obs_rms.update(np.random.default_rng(1).normal(2.0, 3.0, (100, 5)))
    model.ret_rms.update(np.random.default_rng(4).normal(0.0, 7.0, 100))
    with torch.no_grad():
        model.policy.log_std.add_(torch.tensor([0.1, -0.2, 0.3]))
    fast = NumpyPolicy(model.arrays(), model.obs_clip)
    obs = np.random.default_rng(2).normal(2.0, 3.0, (7, 5)).astype(np.float32)
    obs[0, 0] = 1e3  # beyond the observation clip
    out = fast.act(obs, np.random.default_rng(3))
    with torch.no_grad():
        mean, log_std = model.policy(model.norm_obs(torch.as_tensor(obs)))
        logp = gaussian_log_prob(mean, log_std, torch.as_tensor(out["action"]))
    np.testing.assert_allclose(out["mean"], mean.numpy(), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(out["log_std"], log_std.detach().numpy(), rtol=1e-6)
    np.testing.assert_allclose(out["logp"], logp.numpy(), rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(out["value"], model.values_of(obs), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(fast.values_of(obs), model.values_of(obs), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(fast.act_deterministic(obs), model.act_deterministic(obs),
                               rtol=1e-5, atol=1e-6)
    assert fast.reward_scale() == pytest.approx(model.reward_scale(), rel=1e-6)
    with torch.no_grad():  # a copy: it does not follow later changes of the model
        model.value_net[0].bias.add_(1.0)
    assert not np.allclose(fast.values_of(obs), model.values_of(obs))
    np.testing.assert_allclose(model.numpy_policy().values_of(obs), model.values_of(obs),
                               rtol=1e-5, atol=1e-6)


def test_numpy_policy_of_a_fresh_model_does_not_normalise():
    """Before any moments arrive (count 0) the normaliser passes observations through."""
    model = ActorCritic(4, 2)
    obs = np.random.default_rng(0).normal(size=(3, 4)).astype(np.float32)
    np.testing.assert_allclose(model.numpy_policy().values_of(obs), model.values_of(obs),
                               rtol=1e-5, atol=1e-6)
    assert model.numpy_policy().reward_scale() == pytest.approx(1.0, rel=1e-6)


@pytest.mark.parametrize("hidden", [(64, 64), (256, 256), (32, 16, 8)])
def test_param_shapes_are_the_torch_models_state(hidden):
    """Actors check parameters against these shapes without building the torch model."""
    model = ActorCritic(11, 3, hidden)
    state = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    assert param_shapes(11, 3, hidden) == state
    check_params(model_params(model), param_shapes(11, 3, hidden))  # dtypes fit as well


def model_params(model):
    from tpdeb.protocol import Params

    return Params(version=0, arrays=model.arrays())
