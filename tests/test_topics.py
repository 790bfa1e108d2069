"""The topic table: the one declaration of who sends what, from which the access-control grants
and the services' QoS come."""

from pathlib import Path

import pytest

from tpdeb.protocol import Keys
from tpdeb.protocol.keys import ANY_SHARD
from tpdeb.protocol.topics import BY_NAME, ROLES, TOPICS, grants, table_markdown
from tpdeb.services.net.session import qos

ROOT = Path(__file__).resolve().parents[1]
KEYS = Keys("run1")


def allowed(role: str, ident: int, message: str, flow: str) -> set[str]:
    return {k for m, f, k in grants(KEYS, role, ident) if (m, f) == (message, flow)}


def test_every_topic_names_a_key_roles_and_its_messages():
    for topic in TOPICS:
        assert hasattr(KEYS, topic.name), topic.name
        assert topic.kind in ("put", "query", "token")
        assert set(topic.producers) | set(topic.consumers) <= set(ROLES)
        assert topic.producers, topic.name
        assert bool(topic.messages) == (topic.kind != "token")


def test_an_actor_may_put_only_its_own_fragments_and_hear_only_its_own_acks():
    shards = KEYS.of_shard(ANY_SHARD)  # the same on any replay shard
    assert allowed("actor", 3, "put", "ingress") == {KEYS.traj(3), shards.traj(3),
                                                     KEYS.stats("actor", 3)}
    assert allowed("actor", 3, "declare_subscriber", "ingress") == {KEYS.ack(3), shards.ack(3),
                                                                    KEYS.control}
    assert KEYS.traj(4) not in {k for _, _, k in grants(KEYS, "actor", 3)}


def test_only_the_learner_answers_for_parameters_and_only_the_replay_for_samples():
    answering = {role: allowed(role, 0, "declare_queryable", "ingress") for role in ROLES}
    assert [r for r, keys in answering.items() if KEYS.params_latest in keys] == ["learner"]
    assert [r for r, keys in answering.items() if KEYS.sample in keys] == ["replay"]
    assert allowed("link", 0, "put", "ingress") == {KEYS.stats("link", 0)}


@pytest.mark.parametrize("name, expected", [
    ("traj", ("DATA", "BLOCK", False)), ("ack", ("DATA_HIGH", "DROP", False)),
    ("control", ("INTERACTIVE_HIGH", "BLOCK", False)), ("params", ("DATA_LOW", "DROP", False)),
])
def test_the_services_qos_is_the_tables(name, expected):
    import zenoh

    options = qos(name)
    assert (options["priority"], options["congestion_control"], options["express"]) == (
        getattr(zenoh.Priority, expected[0]), getattr(zenoh.CongestionControl, expected[1]),
        expected[2])
    assert BY_NAME[name].congestion == expected[1].lower()


def test_the_design_documents_the_table_as_declared():
    assert table_markdown() in (ROOT / "docs" / "DESIGN.md").read_text()
