"""The learner service's parameter long poll, in process on the in-memory transport: a query
for a version the learner does not have yet waits for the next update, one for an older version
is answered at once, and parameters are encoded only when someone takes them."""

from __future__ import annotations

import threading

import pytest

from tests.test_checkpoint import close, config_for, spec_for
from tpdeb.protocol import Keys, Params, decode
from tpdeb.services import learner as learner_module
from tpdeb.services.learner import LearnerService
from tpdeb.services.net.memory import MemoryBus
from tpdeb.services.process import StopSignal


@pytest.fixture
def service(tmp_path):
    bus = MemoryBus()
    service = LearnerService(config_for(tmp_path), spec_for(), bus.session(), StopSignal())
    yield service, bus
    close(service)


def ask(bus: MemoryBus, after: int | None, out: list) -> threading.Thread:
    """An actor's long poll for a version above `after`, in its own thread."""
    selector = Keys("t").params_latest + ("" if after is None else f"?after={after}")

    def poll() -> None:
        for reply in bus.session().get(selector, timeout=5.0):
            out.append(decode(reply.ok.payload.to_bytes(), Params).version)

    thread = threading.Thread(target=poll)
    thread.start()
    return thread


def test_a_newcomer_gets_the_current_version_at_once(service):
    service, bus = service
    service.publish_params(eager=True)
    got: list[int] = []
    ask(bus, None, got).join(timeout=5)
    assert got == [service.param_version()]


def test_asking_for_a_newer_version_waits_for_the_next_update(service):
    service, bus = service
    service.publish_params(eager=True)
    first = service.param_version()
    got: list[int] = []
    thread = ask(bus, first, got)
    thread.join(timeout=0.3)
    assert thread.is_alive() and not got  # nothing newer yet: the query waits
    service.learner.updates += 1
    service.publish_params()
    thread.join(timeout=5)
    assert got == [first + 1]


def test_parameters_are_encoded_only_when_a_query_takes_them(service, monkeypatch):
    service, bus = service
    encoded: list[int] = []
    real = learner_module.params_message

    def counting(arrays, version, dtype):
        encoded.append(version)
        return real(arrays, version, dtype)

    monkeypatch.setattr(learner_module, "params_message", counting)
    service.publish_params(eager=True)
    for _ in range(20):  # updates nobody asked for (no subscriber on `params` either)
        service.learner.updates += 1
        service.publish_params()
    assert encoded == [service.param_version() - 20]
    got: list[int] = []
    thread = ask(bus, service.param_version() - 1, got)
    while thread.is_alive():  # the loop answers between updates
        service.serve_params()
        thread.join(timeout=0.01)
    assert got == [service.param_version()] and encoded[-1] == service.param_version()
    assert len(encoded) == 2
