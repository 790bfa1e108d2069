import numpy as np
import pytest

from tests.fakes import ScriptedVectorEnv
from tpdeb.tpdeb_core.fragments import (
    Collector,
    FragmentBatch,
    fragment_priority,
    fragment_return,
    initial_priority,
    stack_fragments,
)
from tpdeb.tpdeb_core.model import ActorCritic
from tpdeb.tpdeb_core.schema import Fragment, array_specs

T = 8


def collect(same_step: bool, vector_steps: int, lengths=(5, 7), terminates=(True, False)):
    envs = ScriptedVectorEnv(lengths, terminates, same_step=same_step)
    collector = Collector(envs, ActorCritic(3, 1).numpy_policy(), T, 0.9,
                          np.array([-1.0], np.float32), np.array([1.0], np.float32), seed=3,
                          same_step_autoreset=same_step)
    fragments = []
    for _ in range(vector_steps):
        fragments += collector.step()
    return collector, fragments


def by_env(fragments, env_index):
    return [f for f in fragments if f.env_index == env_index]


@pytest.mark.parametrize("same_step", [True, False])
def test_fragments_hold_real_steps_and_flags(same_step):
    collector, fragments = collect(same_step, 60)
    assert fragments and all(f.num_steps == T and f.obs.shape == (T + 1, 3) for f in fragments)
    for f in fragments:
        episode, t = f.obs[:-1, 0], f.obs[:-1, 1]
        length = (5, 7)[f.env_index]
        # every recorded step is a real step: times run 0..length-1, never an autoreset step
        assert np.all(t < length)
        np.testing.assert_allclose(f.rewards, 1.0 + 0.1 * t)
        ends = t == length - 1
        if f.env_index == 0:
            np.testing.assert_array_equal(f.terminated, ends)
            assert not f.truncated.any() and len(f.trunc_index) == 0
        else:
            np.testing.assert_array_equal(f.truncated, ends)
            assert not f.terminated.any()
            np.testing.assert_array_equal(f.trunc_index, np.flatnonzero(ends))
            # truncation keeps the real final observation of that episode
            for k, step in enumerate(f.trunc_index):
                np.testing.assert_array_equal(f.trunc_obs[k], [episode[step], length, 1])
        # the bootstrap observation is the one that follows the last step
        nxt = f.obs[-1]
        if ends[-1]:
            assert nxt[1] in (0, length)  # reset obs (SAME_STEP) or final obs (NEXT_STEP)
        else:
            assert nxt[0] == episode[-1] and nxt[1] == t[-1] + 1
    # sequence numbers are unique and in order
    assert [f.seq for f in fragments] == list(range(len(fragments)))
    returns = [r for r, _ in collector.episodes]
    assert returns[0] == pytest.approx(sum(1 + 0.1 * k for k in range(5)))


def test_both_autoreset_modes_record_the_same_transitions():
    _, same = collect(True, 60)
    _, nxt = collect(False, 80)
    for env_index in (0, 1):
        a, b = by_env(same, env_index), by_env(nxt, env_index)
        n = min(len(a), len(b))
        assert n >= 3
        for fa, fb in zip(a[:n], b[:n], strict=True):
            np.testing.assert_array_equal(fa.obs[:-1], fb.obs[:-1])
            np.testing.assert_array_equal(fa.rewards, fb.rewards)
            np.testing.assert_array_equal(fa.terminated, fb.terminated)
            np.testing.assert_array_equal(fa.trunc_obs, fb.trunc_obs)


def test_initial_td_errors_use_the_actor_value_net_and_bootstrap_rules():
    collector, fragments = collect(True, 40)
    policy, gamma = collector.policy, 0.9
    for f in fragments:
        values = policy.values_of(f.obs)
        next_values = values[1:].astype(np.float64)
        if len(f.trunc_index):
            next_values[f.trunc_index] = policy.values_of(f.trunc_obs)
        td = f.rewards * policy.reward_scale() + gamma * (~f.terminated) * next_values - values[:-1]
        np.testing.assert_allclose(f.td_abs, np.abs(td), rtol=1e-4, atol=1e-5)


def test_priority_modes():
    td = np.array([0.5, -0.0, 1.5, 2.0])
    assert fragment_priority(np.abs(td), "trajectory") == pytest.approx(4.0)
    np.testing.assert_allclose(fragment_priority(np.abs(td), "step"), np.abs(td))
    assert fragment_priority(np.abs(td), "none") == 1.0
    rewards, discounts = np.array([1.0, 1.0, 1.0, 1.0]), np.array([0.5, 0.0, 0.5, 0.5])
    np.testing.assert_allclose(fragment_return(rewards, discounts), [1.5, 1.0, 1.5, 1.0])
    with_return = fragment_priority(np.abs(td), "trajectory", 2.0, rewards, discounts)
    assert with_return == pytest.approx(4.0 + 2.0 * 1.25)
    with pytest.raises(ValueError, match="priority_mode"):
        fragment_priority(td, "bogus")


def test_fragments_and_batches_are_what_the_schema_declares():
    """Every array the Collector emits and `stack_fragments` builds has its declared dtype and
    shape (T steps, K truncations, B fragments)."""
    collector, fragments = collect(True, 40)
    sizes = {"T": T, "obs_dim": 3, "act_dim": 1}
    for f in fragments:
        assert type(f) is Fragment
        assert f.reward_scale == collector.policy.reward_scale() and f.incarnation == 0
        for name, spec in array_specs(Fragment).items():
            value = getattr(f, name)
            assert value.dtype.str == spec.dtype, name
            assert value.shape == spec.shape(**sizes, K=len(f.trunc_index)), name
    batch = stack_fragments(fragments[:4])
    assert type(batch) is FragmentBatch
    k = sum(len(f.trunc_index) for f in fragments[:4])
    for name, spec in array_specs(FragmentBatch).items():
        value = getattr(batch, name)
        assert value.dtype.str == spec.dtype, name
        assert value.shape == spec.shape(**sizes, K=k, B=4), name


def test_the_initial_priority_is_read_off_the_fragment():
    _, fragments = collect(True, 20)
    f = fragments[0]
    assert initial_priority(f, "trajectory", 0.0, 0.9) == pytest.approx(float(f.td_abs.sum()))
    with_return = fragment_priority(f.td_abs, "trajectory", 0.5, f.rewards * f.reward_scale,
                                    f.discounts(0.9))
    assert initial_priority(f, "trajectory", 0.5, 0.9) == pytest.approx(with_return)
