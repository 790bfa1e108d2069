"""The compiled update (`compile = auto`): prepared in the background while the learner service
trains eagerly, switched to between two updates, and the same update as the eager one. One
compile for the whole file (its cache is the user's, as in a real run)."""

from __future__ import annotations

import copy
import logging

import numpy as np
import pytest
import torch

from tests.test_checkpoint import close, service_for, spec_for
from tests.test_learner import fragments_and_model
from tpdeb.protocol import PriorityUpdate, SampleReply, decode
from tpdeb.services.compiled import BackgroundCompile
from tpdeb.tpdeb_core.fragments import stack_fragments
from tpdeb.tpdeb_core.learner import Learner, place
from tpdeb.tpdeb_core.loss_config import LossConfig


def reply(fragments, seed: int) -> SampleReply:
    rng = np.random.default_rng(seed)
    picked = [fragments[i] for i in rng.choice(len(fragments), 6, replace=False)]
    return SampleReply(request_id=seed, ready=True, keys=np.arange(6, dtype=np.int64) + 6 * seed,
                       weights=rng.uniform(0.3, 1.0, 6).astype(np.float32),
                       from_prioritized=np.array([True, False] * 3),
                       step_weights=None, batch=stack_fragments(picked),
                       inserted_steps=100 * seed, obs_moments=None, ret_moments=None)


@pytest.mark.timeout(600)
def test_the_service_switches_to_the_compiled_update_and_it_computes_the_eager_one(
        tmp_path, caplog):
    fragments, _ = fragments_and_model(n=12, seed=5)
    # ε = 1: Adam's step in proportion to the gradient, so that rounding differences stay as
    # small in the parameters as in the gradients (at ε = 1e-5 a near-zero gradient element
    # steps ±lr on its sign alone)
    service, _ = service_for(tmp_path, spec=spec_for(obs_dim=3, act_dim=1), compile="auto",
                             kl_target=0.01, anneal_lr=True, total_timesteps=10_000, adam_eps=1.0)
    try:
        for fragment in fragments:
            service.learner.observe(fragment)
        eager_twin = copy.deepcopy(service.learner)  # the same learner, kept eager
        sent = []
        service.priorities_publisher.put = sent.append
        caplog.set_level(logging.INFO, logger="tpdeb-learner")
        seed = 0
        while not service.compiled:  # trains eagerly while the update compiles
            seed += 1
            service.train_on(reply(fragments, seed))
            service.compiler.done.wait(0.05)
            assert seed < 10_000
        assert service.compiler.error is None
        assert any("update compiled in" in r.message for r in caplog.records)
        for learner in (eager_twin, service.learner):  # both from the same point on
            learner.load_state_dict(service.learner.state_dict())
            learner.read_metrics()
        counts = torch._dynamo.utils.counters["stats"]["unique_graphs"]
        for step in range(4):
            batch = reply(fragments, 1000 + step)
            service.global_step = eager_twin_step = 1000 * step  # the schedules move alike
            service.train_on(batch)
            service.global_step = eager_twin_step
            eager_twin.set_learning_rate(service.learner.learning_rate())
            eager_twin.update(place(batch.batch, batch.weights, None, eager_twin.device),
                              eager_twin.normaliser())
        # the graph traced on the compiler's copy ran the service's own learner
        assert torch._dynamo.utils.counters["stats"]["unique_graphs"] == counts
        for a, b in zip(service.learner.params, eager_twin.params, strict=True):
            torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)
        assert service.learner.kl_coef == pytest.approx(eager_twin.kl_coef)
        compiled_metrics, eager_metrics = (x.read_metrics() for x in (service.learner,
                                                                      eager_twin))
        for name, value in eager_metrics.items():
            assert compiled_metrics[name] == pytest.approx(value, rel=1e-3, abs=1e-5), name
        assert len(sent) == seed + 4  # every update's priorities went out
    finally:
        close(service)


def test_a_compile_that_fails_leaves_the_learner_eager_saying_why(caplog, monkeypatch):
    fragments, model = fragments_and_model(n=6, seed=1)
    learner = Learner(model, LossConfig())
    compiler = BackgroundCompile(learner)

    def broken(*args):
        raise RuntimeError("no C++ compiler here\nmore lines")

    monkeypatch.setattr(compiler, "update", broken)
    batch = place(stack_fragments(fragments), np.ones(6, np.float32), None, learner.device)
    compiler.start(batch, learner.normaliser())
    compiler.done.wait(30)
    caplog.set_level(logging.WARNING, logger="tpdeb-learner")
    assert not compiler.install()
    (line,) = [r.message for r in caplog.records]
    assert "RuntimeError: no C++ compiler here" in line and "eager" in line
    assert learner.run_update is learner.rules
    learner.update(batch, learner.normaliser())  # and it trains


def test_on_an_accelerator_the_priorities_leave_one_update_later_without_a_wait(
        tmp_path, monkeypatch):
    """Off the CPU the service copies a batch's priorities out without waiting and sends them
    after the next update (then the copy is done); the last batch's go at the end. Run on the
    CPU with the deferral a GPU learner takes and its events stubbed."""
    recorded = []

    class Event:
        def record(self):
            recorded.append("record")

        def synchronize(self):
            recorded.append("synchronize")

    fragments, _ = fragments_and_model(n=12, seed=5)
    service, _ = service_for(tmp_path, spec=spec_for(obs_dim=3, act_dim=1))
    try:
        monkeypatch.setattr(torch.cuda, "Event", Event)
        service.defer_priorities = True
        sent = []
        service.priorities_publisher.put = sent.append
        service.train_on(reply(fragments, 1))
        assert not sent and recorded == ["record"]  # copied, not yet sent
        service.train_on(reply(fragments, 2))
        assert len(sent) == 1 and recorded == ["record", "record", "synchronize"]
        first = decode(sent[0], PriorityUpdate)
        np.testing.assert_array_equal(first.keys, [6, 8, 10])  # batch 1's prioritized keys
        service.send_priorities(None)  # as `finish` does
        assert len(sent) == 2 and decode(sent[1], PriorityUpdate).keys.tolist() == [12, 14, 16]
    finally:
        close(service)
