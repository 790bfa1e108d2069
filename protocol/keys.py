"""Every Zenoh key expression of one run (DESIGN §3), built here and nowhere else; who puts,
asks and hears each is declared in `tpdeb.protocol.topics`."""

from __future__ import annotations

import re

SCHEMA_VERSION = 8  # 2: fragments and acks carry the actor's incarnation; 3: sample replies carry
# per-step weights (step-level PER); 4: and no longer the number of transitions drawn (the loss
# normalises by the weights' sum); 5: a sample reply carries its fragments stacked (Batch);
# 6: one fragment schema (tpdeb_core/schema.py): fragments no longer carry the actor's values,
# acks the ingested count, parameters their source; the run spec names the policy's std;
# 7: the run spec carries the env's keyword arguments; 8: sample requests may carry the B_p
# rows of a batch split over replay shards, replies what the replay holds

RUN_ID_RULE = r"[A-Za-z0-9_.-]{1,64}"
NAME_RULE = r"[A-Za-z0-9_.-]+"  # role and ident chunks: no '/', '*', '$', '?', '#' (Zenoh syntax)
MAX_ACTOR_ID = 2**31 - 1
_DECIMAL = re.compile(r"0|[1-9][0-9]{0,9}")  # one spelling per id, so parse(format(n)) == n


def check_actor_id(actor_id) -> int:
    """The actor id as an int in [0, 2**31); ValueError with the bad value otherwise."""
    if isinstance(actor_id, bool) or not hasattr(actor_id, "__index__"):
        raise ValueError(f"actor_id {actor_id!r} must be an int in [0, {MAX_ACTOR_ID}]")
    value = actor_id.__index__()  # accepts numpy integers, which services often hold
    if not 0 <= value <= MAX_ACTOR_ID:
        raise ValueError(f"actor_id {value} must be an int in [0, {MAX_ACTOR_ID}]")
    return value


def _chunk(what: str, value) -> str:
    text = str(value)
    if not re.fullmatch(NAME_RULE, text):
        raise ValueError(f"{what} {value!r} must match {NAME_RULE}")
    return text


SHARDED = ("traj", "ack", "sample", "priorities")  # the topics a replay shard has its own of
ANY_SHARD = "*"


class Keys:
    """Every Zenoh key expression of one run, under tpdeb/{run_id}/…

    `shard`: the keys of one replay shard (`replay_shards` > 1): its fragments, acks, samples and
    priorities under tpdeb/{run_id}/shard/{k}/…, every other topic the run's; ANY_SHARD: every
    shard's (an access rule's wildcard). None: an unsharded run's (one replay)."""

    def __init__(self, run_id: str, shard: int | str | None = None):
        if not isinstance(run_id, str) or not re.fullmatch(RUN_ID_RULE, run_id):
            raise ValueError(f"run_id {run_id!r} is invalid: it must match {RUN_ID_RULE} "
                             "(letters, digits, '_', '.', '-'; 1 to 64 characters)")
        if shard is not None and shard != ANY_SHARD and (
                isinstance(shard, bool) or not isinstance(shard, int) or shard < 0):
            raise ValueError(f"shard {shard!r} must be an int >= 0, {ANY_SHARD!r} or None")
        self.run_id, self.shard = run_id, shard
        self.prefix = p = f"tpdeb/{run_id}"
        self.shard_prefix = s = p if shard is None else f"{p}/shard/{shard}"
        self.traj_all = f"{s}/traj/*"
        self.ack_all = f"{s}/ack/*"
        self.params = f"{p}/params"
        self.params_latest = f"{p}/params/latest"
        self.sample = f"{s}/sample"
        self.priorities = f"{s}/priorities"
        self.spec = f"{p}/spec"
        self.control = f"{p}/control"
        self.join = f"{p}/join"
        self.stats_all = f"{p}/stats/**"
        self.alive_all = f"{p}/alive/**"

    def __repr__(self) -> str:
        return f"Keys({self.run_id!r})" if self.shard is None else \
            f"Keys({self.run_id!r}, shard={self.shard!r})"

    def of_shard(self, shard: int | str | None) -> Keys:
        """The same run's keys for one replay shard (None: unsharded)."""
        return Keys(self.run_id, shard)

    def traj(self, actor_id: int) -> str:
        return f"{self.shard_prefix}/traj/{check_actor_id(actor_id)}"

    def ack(self, actor_id: int) -> str:
        return f"{self.shard_prefix}/ack/{check_actor_id(actor_id)}"

    def stats(self, role: str, ident: str | int) -> str:
        return f"{self.prefix}/stats/{_chunk('role', role)}/{_chunk('ident', ident)}"

    def alive(self, role: str, ident: str | int) -> str:
        return f"{self.prefix}/alive/{_chunk('role', role)}/{_chunk('ident', ident)}"

    def of_role(self, topic: str, role: str) -> str:
        """Every key of `topic` (stats, alive) one role's producers use, whatever their ident."""
        return f"{self.prefix}/{_chunk('topic', topic)}/{_chunk('role', role)}/*"

    def actor_id_of(self, key: str) -> int | None:
        """The actor id in this run's …/traj/{n} or …/ack/{n}; None for any other key."""
        key = str(key)  # a Zenoh KeyExpr prints as its text
        for topic in ("traj", "ack"):
            head = f"{self.shard_prefix}/{topic}/"
            if key.startswith(head) and _DECIMAL.fullmatch(key[len(head):]):
                value = int(key[len(head):])
                return value if value <= MAX_ACTOR_ID else None
        return None
