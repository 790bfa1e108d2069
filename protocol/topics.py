"""The run's topology, declared once: every topic with its message, who produces it, who
consumes it and its quality of service (DESIGN §3). The services declare their publishers,
subscribers, queryables and tokens from this table, and the router's access-control grants are
derived from it, so the three cannot disagree.

Roles: `replay`, `learner`, `actor` (one per actor id), `monitor` (a watching session such as the
launcher's), `link` (the link shim's stats), `evaluator` (evaluation while training). QoS is
named here in words (this package does not import Zenoh); `tpdeb.services.net.session.qos` turns
it into Zenoh's options.
"""

from __future__ import annotations

from dataclasses import dataclass

from tpdeb.protocol import messages as m
from tpdeb.protocol.keys import ANY_SHARD, SHARDED, Keys

ROLES = ("replay", "learner", "actor", "monitor", "link", "evaluator")


@dataclass(frozen=True)
class Topic:
    """One topic of a run.

    kind: `put` (publish/subscribe), `query` (producers answer, consumers ask) or `token`
    (liveliness: producers hold one each, consumers watch).
    messages: the message types it carries (a query's request, then its reply).
    own_key: the topic has one key per producer (`traj/{actor}`, `stats/{role}/{id}`); a
    producer uses its own, consumers hear them all through the wildcard. `ack/{actor}` is the
    other way round: the replay puts on every actor's, each actor hears its own.
    watch: for tokens, what a consumer role watches: {role: "all" or a producer role}.
    """

    name: str
    kind: str
    messages: tuple[type, ...]
    producers: tuple[str, ...]
    consumers: tuple[str, ...]
    priority: str = "data"  # Zenoh priority: interactive_high, data_high, data, data_low
    congestion: str = "drop"  # Zenoh congestion control: drop or block
    express: bool = False
    own_key: bool = False
    watch: tuple[tuple[str, str], ...] = ()
    why: str = ""


TOPICS: tuple[Topic, ...] = (
    Topic("traj", "put", (m.Trajectory,), ("actor",), ("replay",), congestion="block",
          own_key=True, why="never dropped: back-pressure, resent until acknowledged"),
    Topic("ack", "put", (m.Ack,), ("replay",), ("actor",), priority="data_high",
          why="small and unblocks an actor: ahead of bulk data on a thin link. Not express: "
              "a pass's acks share a batch; one batch each overflowed the queue under a "
              "crowd, and a dropped ack holds its fragment until the resend"),
    Topic("sample", "query", (m.SampleRequest, m.SampleReply), ("replay",), ("learner",),
          why="several in flight, so a batch is usually waiting when an update ends"),
    Topic("priorities", "put", (m.PriorityUpdate,), ("learner",), ("replay",)),
    Topic("params_latest", "query", (m.Params,), ("learner",), ("actor", "monitor", "evaluator"),
          why="long poll: answered once a version above the asker's exists"),
    Topic("params", "put", (m.Params,), ("learner",), (), priority="data_low",
          why="for monitors; latest wins, put only when someone subscribes"),
    Topic("spec", "query", (m.RunSpec,), ("replay",), ("learner", "actor", "monitor", "evaluator"),
          why="peers refuse a run whose spec differs from theirs (env id and keyword "
              "arguments, dims)"),
    Topic("join", "query", (m.JoinRequest, m.JoinReply), ("replay",), ("actor",),
          why="--actor-id auto: the lowest id no actor of the run holds"),
    Topic("control", "put", (m.Control,), ("learner",), ("replay", "actor", "monitor", "evaluator"),
          priority="interactive_high", congestion="block", why="the stop broadcast"),
    Topic("stats", "put", (m.Stats,), ("replay", "learner", "actor", "link", "evaluator"),
          ("learner", "monitor", "evaluator"), own_key=True,
          why="the evaluator hears the learner's global step and reports its figures"),
    Topic("alive", "token", (), ("replay", "learner", "actor", "evaluator"),
          ("actor", "learner", "monitor"), own_key=True,
          watch=(("actor", "replay"), ("learner", "replay"), ("monitor", "all")),
          why="an actor resends its outbox when the replay (re)appears; the learner leaves a "
              "replay shard that is gone out of its batches"),
)
BY_NAME = {topic.name: topic for topic in TOPICS}


# The ident of a pool: every producer of a role under one user (actors with ids from the
# replay server or a StatefulSet's ordinal, all as user `actor`).
ANY = "*"


def produced_key(keys: Keys, topic: Topic, role: str, ident: int | str = 0) -> str:
    """The key a producer (`role`, `ident`; ANY: any ident) declares for `topic`."""
    if not topic.own_key:
        return all_keys(keys, topic)
    if topic.name == "traj":
        return keys.traj_all if ident == ANY else keys.traj(ident)
    if ident == ANY:
        return keys.of_role(topic.name, role)
    return getattr(keys, topic.name)(role, ident)  # stats/{role}/{id}, alive/{role}/{id}


def all_keys(keys: Keys, topic: Topic) -> str:
    """The key expression that covers every key of `topic`."""
    wildcard = {"traj": keys.traj_all, "ack": keys.ack_all, "stats": keys.stats_all,
                "alive": keys.alive_all}
    return wildcard.get(topic.name) or getattr(keys, topic.name)


def heard_key(keys: Keys, topic: Topic, role: str, ident: int | str = 0) -> str:
    """What a consumer (`role`, `ident`) subscribes to, asks or watches for `topic`."""
    if topic.name == "ack":  # each actor hears its own acks only (a pool: all of them)
        return keys.ack_all if ident == ANY else keys.ack(ident)
    if topic.kind == "token":  # every token of the watched role (replay shards: one each)
        watched = dict(topic.watch)[role]
        return all_keys(keys, topic) if watched == "all" else keys.of_role(topic.name, watched)
    return all_keys(keys, topic)


def grants(keys: Keys, role: str, ident: int | str = 0) -> list[tuple[str, str, str]]:
    """(message, flow, key expression) triples of one role: what it may send into the router
    (`ingress`) and what the router may hand it (`egress`), from TOPICS alone."""
    out: list[tuple[str, str, str]] = []
    for topic in TOPICS:
        # a replay shard's topics: the unsharded run's keys and every shard's
        for k in ((keys, keys.of_shard(ANY_SHARD)) if topic.name in SHARDED else (keys,)):
            if role in topic.producers:
                out += _producer_grants(topic, produced_key(k, topic, role, ident),
                                        all_keys(k, topic))
            if role in topic.consumers:
                out += _consumer_grants(topic, heard_key(k, topic, role, ident))
    return out


def _producer_grants(topic: Topic, key: str, heard_by: str) -> list[tuple[str, str, str]]:
    if topic.kind == "put":
        # A publisher sends only while it knows of a matching subscriber: the router must pass
        # it the subscriptions that hear it (its own key's, and the wildcard's).
        return [("put", "ingress", key)] + [("declare_subscriber", "egress", k)
                                            for k in dict.fromkeys((key, heard_by))]
    if topic.kind == "query":
        return [("declare_queryable", "ingress", key), ("query", "egress", key),
                ("reply", "ingress", key)]
    # A holder may also ask whether its own token is live (tpdeb-health, as the service's user).
    return [("liveliness_token", "ingress", key), ("liveliness_query", "ingress", key),
            ("reply", "egress", key), ("liveliness_token", "egress", key)]


def _consumer_grants(topic: Topic, key: str) -> list[tuple[str, str, str]]:
    if topic.kind == "put":
        return [("declare_subscriber", "ingress", key), ("put", "egress", key)]
    if topic.kind == "query":
        return [("query", "ingress", key), ("reply", "egress", key),
                ("declare_queryable", "egress", key)]  # who answers
    return [("declare_liveliness_subscriber", "ingress", key),
            ("liveliness_token", "egress", key),
            ("liveliness_query", "ingress", key),  # the history of live tokens
            ("reply", "egress", key)]


def table_markdown() -> str:
    """TOPICS as the table of DESIGN §3 (a test keeps the two equal). For a query the
    producers answer and the consumers ask; for a token the producers hold one each."""
    rows = ["| key | kind | messages | producers → consumers | QoS | why |",
            "|---|---|---|---|---|---|"]
    for t in TOPICS:
        key = {"traj": "traj/{actor}", "ack": "ack/{actor}", "stats": "stats/{role}/{id}",
               "alive": "alive/{role}/{id}", "params_latest": "params/latest"}.get(t.name, t.name)
        qos = ", ".join(q for q in (t.priority if t.priority != "data" else "",
                                    t.congestion if t.congestion != "drop" else "",
                                    "express" if t.express else "") if q) or "default"
        flow = f"{', '.join(t.producers)} → {', '.join(t.consumers) or 'monitors'}"
        messages = " → ".join(m.MESSAGE_NAMES[c] for c in t.messages) or "liveliness token"
        rows.append(f"| `{key}` | {t.kind} | {messages} | {flow} | {qos} | {t.why} |")
    return "\n".join(rows)
