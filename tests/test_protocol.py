"""protocol: round-trips of every message, key expressions, and hostile inputs (DESIGN §3)."""

import dataclasses
import os
import pickle

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tpdeb.protocol import (
    ERROR_KINDS,
    MESSAGE_TYPES,
    SCHEMA_VERSION,
    Ack,
    Batch,
    Control,
    DecodeError,
    JoinReply,
    JoinRequest,
    Keys,
    Moments,
    Params,
    PriorityUpdate,
    RunSpec,
    SampleReply,
    SampleRequest,
    Stats,
    Trajectory,
    check_params_shapes,
    decode,
    encode,
)
from tpdeb.protocol.schema import field_rules
from tpdeb.tpdeb_core.fragments import Fragment, FragmentBatch, stack_fragments
from tpdeb.tpdeb_core.schema import array_specs

T, OBS_DIM, ACT_DIM = 4, 3, 2
RUN_SPEC = RunSpec("Hopper-v5", OBS_DIM, ACT_DIM, T, [64, 64], 0.99, 10.0, 0.0, "global",
                   "trajectory", 0.0, np.full(ACT_DIM, -1, np.float32),
                   np.ones(ACT_DIM, np.float32))
ALL_TYPES = tuple(MESSAGE_TYPES.values())
FUZZ_EXAMPLES = int(os.environ.get("TPDEB_FUZZ_EXAMPLES", "300"))
FUZZ = settings(max_examples=FUZZ_EXAMPLES, deadline=None,
                suppress_health_check=[HealthCheck.too_slow])
# Tests run once per message type share the suite's budget between the types, but get the full
# count each in a bench run (bench/fuzz.py sets TPDEB_FUZZ_EXAMPLES): every decoder gets 10^4.
FUZZ_PER_TYPE = settings(FUZZ, max_examples=FUZZ_EXAMPLES if "TPDEB_FUZZ_EXAMPLES" in os.environ
                         else max(10, FUZZ_EXAMPLES // len(MESSAGE_TYPES)))
FIELD_FUZZ_TYPES = ["RunSpec", "Trajectory", "Params", "SampleReply", "Stats",
                    "PriorityUpdate.step"]


def make_traj(seed: int = 0, steps: int = T, obs_dim: int = OBS_DIM) -> Trajectory:
    rng = np.random.default_rng(seed)

    def f32(*shape):
        return rng.standard_normal(shape).astype(np.float32)

    truncated = np.zeros(steps, bool)
    truncated[1] = True
    terminated = np.zeros(steps, bool)
    terminated[-1] = True
    return Trajectory(
        actor_id=3, seq=seed, env_index=1, policy_version=7, reward_scale=0.5,
        obs=f32(steps + 1, obs_dim), actions=f32(steps, ACT_DIM), rewards=f32(steps),
        terminated=terminated, truncated=truncated, behaviour_mean=f32(steps, ACT_DIM),
        behaviour_log_std=f32(steps, ACT_DIM), behaviour_logp=f32(steps),
        trunc_index=np.array([1], np.int32), trunc_obs=f32(1, obs_dim),
        disc_returns=f32(steps), td_abs=np.abs(f32(steps)))


def make_moments(shape) -> Moments:
    return Moments(12.0, np.arange(np.prod(shape), dtype=np.float64).reshape(shape),
                   np.ones(shape, np.float64))


def make_batch(*fragments: Trajectory) -> Batch:
    return stack_fragments(fragments)


def make_reply() -> SampleReply:
    return SampleReply(
        request_id=9, ready=True, keys=np.array([5, 11], np.int64),
        weights=np.array([0.5, 1.0], np.float32), from_prioritized=np.array([True, False]),
        step_weights=np.array([[0.0, 0.5, 1.5, 0.0], [1.0] * T], np.float32),
        batch=make_batch(make_traj(1), make_traj(2)), inserted_steps=640,
        obs_moments=make_moments((OBS_DIM,)), ret_moments=make_moments(()))


MESSAGES = {
    "RunSpec": RUN_SPEC,
    "Trajectory": make_traj(),
    "Ack": Ack(3, np.array([0, 1, 2], np.int64), 17),  # incarnation 17
    "Params": Params(4, {"pi.weight": np.ones((2, 3), np.float32), "log_std": np.zeros(2),
                         "norm.count": np.array(5, np.int64)}),
    "SampleRequest": SampleRequest(1, 8, 0.4),
    "SampleReply": make_reply(),
    "Batch": make_batch(make_traj(1), make_traj(2), make_traj(3)),
    "SampleReply.not_ready": SampleReply.not_ready(2, "rate limiter", inserted_steps=64),
    "Moments": make_moments((OBS_DIM,)),
    "PriorityUpdate": PriorityUpdate(np.array([5, 11], np.int64), np.array([0.1, 2.0])),
    "PriorityUpdate.step": PriorityUpdate(np.array([5, 11], np.int64), np.ones((2, T))),
    "Stats": Stats("actor", "3", {"charts/SPS": 812.5, "env_steps": 1024, "env_id": "Hopper-v5"},
                   np.array([10.5, 3.0]), np.array([100, 30], np.int64)),
    "Control": Control("stop", "user pressed Ctrl-C"),
    "JoinRequest": JoinRequest(2**62 + 5),
    "JoinReply": JoinReply(7, 2**62 + 5),
}


def assert_same(a, b, where="msg"):
    """Equal values, types and dtypes, recursively through nested messages."""
    assert type(a) is type(b), where
    if dataclasses.is_dataclass(a):
        for f in dataclasses.fields(a):
            assert_same(getattr(a, f.name), getattr(b, f.name), f"{where}.{f.name}")
    elif isinstance(a, np.ndarray):
        assert (a.dtype, a.shape) == (b.dtype, b.shape), where
        np.testing.assert_array_equal(a, b, err_msg=where)
    elif isinstance(a, list | dict):
        assert len(a) == len(b), where
        for key in (range(len(a)) if isinstance(a, list) else a):
            assert_same(a[key], b[key], f"{where}[{key!r}]")
    else:
        assert a == b, where


def arrays_of(msg):
    for f in dataclasses.fields(msg):
        value = getattr(msg, f.name)
        values = value.values() if isinstance(value, dict) else (
            value if isinstance(value, list) else [value])
        for v in values:
            if isinstance(v, np.ndarray):
                yield v
            elif dataclasses.is_dataclass(v):
                yield from arrays_of(v)


# ------------------------------------------------------------------------------ round trips


@pytest.mark.parametrize("name", MESSAGES)
def test_round_trip_every_message(name):
    msg = MESSAGES[name]
    out = decode(encode(msg), type(msg), spec=RUN_SPEC)
    assert_same(msg, out)
    for arr in arrays_of(out):  # views over the unpacked bytes: no copy, read-only
        assert arr.base is not None and not arr.flags.writeable


def test_round_trip_details():
    reply = decode(encode(MESSAGES["SampleReply"]), SampleReply, spec=RUN_SPEC)
    assert reply.batch.rewards.shape == (T, 2) and reply.ret_moments.mean.shape == ()
    params = decode(encode(MESSAGES["Params"]), Params)
    assert params.arrays["norm.count"].shape == () and params.arrays["norm.count"] == 5
    step = decode(encode(MESSAGES["PriorityUpdate.step"]), PriorityUpdate)
    assert step.priorities.shape == (2, T)
    assert decode(encode(RUN_SPEC), RunSpec).hidden_sizes == [64, 64]
    assert isinstance(decode(encode(Control("stop")), (Ack, Control)), Control)


def test_fragments_and_batches_travel_as_the_cores_own_classes():
    """One schema: the wire's Trajectory and Batch are the core's Fragment and FragmentBatch,
    their array rules are the core's declarations, and what is decoded is stacked and trained
    on as it is."""
    assert Trajectory is Fragment and Batch is FragmentBatch
    for cls in (Fragment, FragmentBatch):
        rules = dict(field_rules(cls))
        for name, spec in array_specs(cls).items():
            assert (rules[name].dtypes, rules[name].shapes, rules[name].ge) == (
                spec.dtype, spec.dims, spec.ge), name
    fragments = [decode(encode(make_traj(i)), Trajectory, spec=RUN_SPEC) for i in range(3)]
    assert all(type(f) is Fragment for f in fragments)
    reply = decode(encode(dataclasses.replace(make_reply(), batch=stack_fragments(fragments[:2]))),
                   SampleReply, spec=RUN_SPEC)
    assert type(reply.batch) is FragmentBatch and reply.batch.obs.shape == (T + 1, 2, OBS_DIM)


def test_nothing_travels_that_nobody_reads():
    assert "values" not in {f.name for f in dataclasses.fields(Trajectory)}
    assert "ingested" not in {f.name for f in dataclasses.fields(Ack)}
    assert "source" not in {f.name for f in dataclasses.fields(Params)}


def test_a_fragment_of_the_previous_schema_is_refused_as_another_version():
    """Version 5 carried the actor's value estimates; such a fragment names its version and
    is refused for it, not for its extra field."""
    old = envelope(make_traj())
    old["v"] = SCHEMA_VERSION - 1
    old["body"]["values"] = envelope(make_traj())["body"]["obs"]
    with pytest.raises(DecodeError) as err:
        decode(msgpack.packb(old, use_bin_type=True), Trajectory)
    assert err.value.kind == "version" and f"version {SCHEMA_VERSION - 1}" in err.value.detail


def test_encode_normalises_layout_and_refuses_unwired_dtypes():
    big_endian = np.arange(6, dtype=">f4").reshape(2, 3)
    strided = np.arange(12, dtype=np.float64).reshape(3, 4)[:, ::2]
    out = decode(encode(Params(1, {"a": big_endian, "b": strided})), Params)
    assert out.arrays["a"].dtype.str == "<f4" and np.array_equal(out.arrays["a"], big_endian)
    assert np.array_equal(out.arrays["b"], strided)
    stats = Stats("learner", "0", {"loss": np.float32(0.25), "updates": np.int64(3)})
    assert decode(encode(stats), Stats).values == {"loss": 0.25, "updates": 3}
    with pytest.raises(ValueError, match="complex64"):
        encode(Params(1, {"a": np.zeros(2, np.complex64)}))
    with pytest.raises(TypeError):
        encode({"v": 1})


def test_check_params_shapes():
    params = MESSAGES["Params"]
    expected = {"pi.weight": (2, 3), "log_std": (2,), "norm.count": ()}
    check_params_shapes(params, expected)
    with pytest.raises(DecodeError, match="missing") as err:
        check_params_shapes(params, {**expected, "vf.bias": (1,)})
    assert err.value.kind == "shape"
    with pytest.raises(DecodeError, match="pi.weight"):
        check_params_shapes(params, {**expected, "pi.weight": (3, 2)})


def test_decode_error_is_a_value_error_with_kind_and_detail():
    err = DecodeError("shape", "Trajectory.obs: obs_dim=4")
    assert isinstance(err, ValueError) and str(err) == "shape: Trajectory.obs: obs_dim=4"
    copy = pickle.loads(pickle.dumps(err))
    assert (copy.kind, copy.detail) == ("shape", "Trajectory.obs: obs_dim=4")


# ------------------------------------------------------------------------------------ keys


def test_key_expressions():
    k = Keys("run-1.a_b")
    assert k.prefix == "tpdeb/run-1.a_b" and k.run_id == "run-1.a_b"
    p = k.prefix
    assert (k.traj(3), k.traj_all, k.ack(3), k.ack_all) == (
        f"{p}/traj/3", f"{p}/traj/*", f"{p}/ack/3", f"{p}/ack/*")
    assert (k.params, k.params_latest, k.sample, k.priorities, k.spec, k.control) == (
        f"{p}/params", f"{p}/params/latest", f"{p}/sample", f"{p}/priorities", f"{p}/spec",
        f"{p}/control")
    assert (k.stats("actor", 2), k.stats_all, k.alive("replay", "main"), k.alive_all) == (
        f"{p}/stats/actor/2", f"{p}/stats/**", f"{p}/alive/replay/main", f"{p}/alive/**")
    assert k.traj(np.int64(5)) == f"{p}/traj/5"


@pytest.mark.parametrize("run_id", ["", "a/b", "x" * 65, "a*", "r$1", "ä", "a b", None, 7])
def test_bad_run_ids_are_refused_with_the_value(run_id):
    with pytest.raises(ValueError, match="run_id") as err:
        Keys(run_id)
    assert repr(run_id) in str(err.value) and "[A-Za-z0-9_.-]{1,64}" in str(err.value)


@pytest.mark.parametrize("actor_id", [-1, 2**31, True, 1.5, "3"])
def test_bad_actor_ids_are_refused(actor_id):
    with pytest.raises(ValueError, match="actor_id"):
        Keys("r").traj(actor_id)


@pytest.mark.parametrize("role, ident", [("a/b", 1), ("actor", "*"), ("", 1), ("x", "")])
def test_bad_roles_and_idents_are_refused(role, ident):
    with pytest.raises(ValueError):
        Keys("r").stats(role, ident)


def test_actor_id_of():
    k = Keys("r1")
    assert k.actor_id_of(k.traj(0)) == 0 and k.actor_id_of(k.ack(2**31 - 1)) == 2**31 - 1
    other = Keys("r2")
    for key in (other.traj(3), other.ack(3), "tpdeb/r1/traj/007", "tpdeb/r1/traj/*",
                "tpdeb/r1/traj/3/x", "tpdeb/r1/traj/", "tpdeb/r1/traj/2147483648", k.params,
                "tpdeb/r1/stats/actor/3", "tpdeb/r1/traj/-1", "tpdeb/r10/traj/3"):
        assert k.actor_id_of(key) is None, key


# ------------------------------------------------------------------------ hostile inputs


def nd(dtype: str, shape, data: bytes) -> dict:
    return {"__nd__": True, "dtype": dtype, "shape": list(shape), "data": data}


def envelope(msg) -> dict:
    return msgpack.unpackb(encode(msg), raw=False)


def tampered(msg, *, top=None, **body) -> bytes:
    """`msg` encoded, then with envelope entries and body fields replaced by raw wire values."""
    wire = envelope(msg)
    wire.update(top or {})
    wire["body"].update(body)
    return msgpack.packb(wire, use_bin_type=True)


def without(field: str) -> bytes:
    wire = envelope(make_traj())
    del wire["body"][field]
    return msgpack.packb(wire, use_bin_type=True)


TRAJ = make_traj()
R = TRAJ.rewards
BAD_INPUTS = [  # (kind, bytes, expected types, decode keyword arguments)
    ("size", encode(TRAJ), Trajectory, {"max_bytes": 100}),
    ("msgpack", encode(TRAJ)[:-7], Trajectory, {}),
    ("msgpack", encode(TRAJ) + b"\xc0", Trajectory, {}),
    ("msgpack", msgpack.packb([1, 2]), Trajectory, {}),
    ("msgpack", b"\xc7\x01\x05x", Trajectory, {}),  # an ext type
    ("version", tampered(TRAJ, top={"v": 99}), Trajectory, {}),
    ("version", tampered(TRAJ, top={"v": True}), Trajectory, {}),
    ("version", tampered(RUN_SPEC, schema_version=99), RunSpec, {}),
    ("type", tampered(TRAJ, top={"type": "Nope"}), Trajectory, {}),
    ("type", encode(Control("stop")), (Trajectory, Ack), {}),
    ("field", without("seq"), Trajectory, {}),
    ("field", tampered(TRAJ, extra=1), Trajectory, {}),
    ("field", tampered(TRAJ, top={"extra": 1}), Trajectory, {}),
    ("field", tampered(TRAJ, seq=True), Trajectory, {}),
    ("field", tampered(TRAJ, seq="3"), Trajectory, {}),
    ("field", tampered(TRAJ, rewards=[1.0, 2.0, 3.0, 4.0]), Trajectory, {}),
    ("field", tampered(MESSAGES["SampleReply"], batch={"obs": 1}), SampleReply, {}),
    ("dtype", tampered(TRAJ, rewards=nd("<f8", [T], R.astype("<f8").tobytes())), Trajectory, {}),
    ("dtype", tampered(TRAJ, rewards=nd("<f2", [T], R.astype("<f2").tobytes())), Trajectory, {}),
    ("dtype", tampered(TRAJ, rewards=nd(">f4", [T], R.astype(">f4").tobytes())), Trajectory, {}),
    ("shape", encode(make_traj(obs_dim=OBS_DIM + 1)), Trajectory, {"spec": RUN_SPEC}),
    ("shape", encode(make_traj(steps=T + 1)), Trajectory, {"spec": RUN_SPEC}),
    ("shape", tampered(TRAJ, rewards=nd("<f4", [T - 1], R[:-1].tobytes())), Trajectory, {}),
    ("shape", tampered(TRAJ, rewards=nd("<f4", [T * 1000], R.tobytes())), Trajectory, {}),
    ("shape", tampered(TRAJ, rewards=nd("<f4", [-1], b"")), Trajectory, {}),
    ("shape", tampered(TRAJ, rewards=nd("<f4", [T, 1], R.tobytes())), Trajectory, {}),
    ("shape", tampered(MESSAGES["PriorityUpdate.step"]), PriorityUpdate,
     {"spec": dataclasses.replace(RUN_SPEC, fragment_len=T + 1)}),
    ("nonfinite", encode(dataclasses.replace(TRAJ, rewards=np.array([0, np.nan, 0, 0],
                                                                    np.float32))), Trajectory, {}),
    ("nonfinite", tampered(TRAJ, reward_scale=float("inf")), Trajectory, {}),
    ("value", tampered(TRAJ, seq=-1), Trajectory, {}),
    ("value", tampered(TRAJ, trunc_index=nd("<i4", [1], np.int32(T).tobytes())), Trajectory, {}),
    ("value", tampered(TRAJ, trunc_index=nd("<i4", [1], np.int32(0).tobytes())), Trajectory, {}),
    ("value", tampered(TRAJ, truncated=nd("|b1", [T], bytes([0, 2, 0, 0]))), Trajectory, {}),
    ("value", tampered(TRAJ, td_abs=nd("<f4", [T], (-R.__abs__() - 1).tobytes())), Trajectory, {}),
    ("value", encode(SampleRequest(1, 0, 0.5)), SampleRequest, {}),
    ("value", encode(SampleRequest(1, 4097, 0.5)), SampleRequest, {}),
    ("value", encode(Control("restart")), Control, {}),
    ("value", encode(PriorityUpdate(np.array([1]), np.array([-0.5]))), PriorityUpdate, {}),
    ("value", tampered(MESSAGES["SampleReply"], ready=False), SampleReply, {}),
]


@pytest.mark.parametrize("kind, data, expected, kwargs", BAD_INPUTS,
                         ids=[f"{case[0]}-{i}" for i, case in enumerate(BAD_INPUTS)])
def test_each_bad_input_gives_its_error_kind(kind, data, expected, kwargs):
    with pytest.raises(DecodeError) as err:
        decode(data, expected, **kwargs)
    assert err.value.kind == kind, err.value
    assert str(err.value) == f"{kind}: {err.value.detail}"


def test_every_error_kind_is_exercised():
    assert {case[0] for case in BAD_INPUTS} == set(ERROR_KINDS)


def test_error_messages_name_what_went_wrong():
    with pytest.raises(DecodeError) as err:
        decode(tampered(TRAJ, top={"v": 99}), Trajectory)
    assert "99" in err.value.detail and str(SCHEMA_VERSION) in err.value.detail
    with pytest.raises(DecodeError, match="obs_dim=4, but obs_dim=3 from the run spec"):
        decode(encode(make_traj(obs_dim=OBS_DIM + 1)), Trajectory, spec=RUN_SPEC)
    with pytest.raises(DecodeError, match=r"SampleReply\.batch\.rewards"):
        bad = dataclasses.replace(make_traj(2), rewards=np.full(T, np.inf, np.float32))
        decode(encode(dataclasses.replace(make_reply(), batch=make_batch(make_traj(1), bad))),
               SampleReply)


def test_a_batch_must_fit_its_reply_and_name_real_truncations():
    three = dataclasses.replace(make_reply(), batch=make_batch(*(make_traj(i) for i in range(3))))
    with pytest.raises(DecodeError, match="holds 3 fragments, keys 2") as err:
        decode(encode(three), SampleReply)
    assert err.value.kind == "shape"
    longer = dataclasses.replace(make_reply(), step_weights=np.ones((2, T + 1), np.float32))
    with pytest.raises(DecodeError, match="step_weights") as err:
        decode(encode(longer), SampleReply)
    batch = make_batch(make_traj(1), make_traj(2))
    for field_name, value in (("trunc_b", np.array([0, 2], np.int32)),
                              ("trunc_t", np.array([0, 1], np.int32))):  # step 0 is not truncated
        with pytest.raises(DecodeError) as err:
            decode(encode(dataclasses.replace(batch, **{field_name: value})), Batch)
        assert err.value.kind == "value"
    assert decode(encode(batch), Batch, spec=RUN_SPEC).obs.shape == (T + 1, 2, OBS_DIM)


# ------------------------------------------------------------------------------- fuzzing


def decode_or_error(data: bytes, expected=ALL_TYPES, spec=None):
    """The decoded message or the DecodeError; anything else fails the test."""
    try:
        return decode(data, expected, spec=spec)
    except DecodeError as e:
        assert e.kind in ERROR_KINDS
        assert "internal error" not in e.detail, e  # the codec's safety net must never be needed
        return e


@FUZZ
@given(st.binary(max_size=512))
def test_arbitrary_bytes_never_raise_anything_else(data):
    decode_or_error(data)


TRAJ_BYTES = encode(TRAJ)
edits = st.lists(st.tuples(st.sampled_from(["flip", "insert", "delete"]),
                           st.integers(0, len(TRAJ_BYTES) - 1), st.integers(0, 255)),
                 min_size=1, max_size=6)


@FUZZ
@given(edits, st.booleans())
def test_mutated_trajectory_is_refused_or_valid(changes, with_spec):
    data = bytearray(TRAJ_BYTES)
    for op, pos, byte in changes:
        pos %= max(len(data), 1)
        if op == "flip":
            data[pos] ^= 1 << (byte % 8)
        elif op == "insert":
            data.insert(pos, byte)
        elif data:
            del data[pos]
    out = decode_or_error(bytes(data), Trajectory, RUN_SPEC if with_spec else None)
    if not isinstance(out, DecodeError):  # whatever got through is whole and valid
        assert isinstance(out, Trajectory)
        assert_same(out, decode(encode(out), Trajectory, spec=RUN_SPEC if with_spec else None))


leaves = (st.none() | st.booleans() | st.integers(-(2**63), 2**64 - 1) | st.floats()
          | st.text(max_size=12) | st.binary(max_size=24))
array_maps = st.fixed_dictionaries({
    "__nd__": st.just(True) | leaves,
    "dtype": st.sampled_from(["<f4", "<f8", "<i4", "<i8", "|b1", "|u1", ">f4", "<c8"]) | leaves,
    "shape": st.lists(st.integers(-2, 6), max_size=3) | leaves,
    "data": st.binary(max_size=48),
})
trees = st.recursive(
    leaves | array_maps,
    lambda kids: st.lists(kids, max_size=4) | st.dictionaries(st.text(max_size=8), kids,
                                                              max_size=4),
    max_leaves=16)


@pytest.mark.parametrize("type_name", sorted(MESSAGE_TYPES))
@FUZZ_PER_TYPE
@given(body=trees)
def test_arbitrary_body_in_a_valid_envelope_is_refused(type_name, body):
    data = msgpack.packb({"v": SCHEMA_VERSION, "type": type_name, "body": body},
                         use_bin_type=True)
    assert isinstance(decode_or_error(data), DecodeError)


@pytest.mark.parametrize("name", FIELD_FUZZ_TYPES)
@FUZZ_PER_TYPE
@given(data=st.data())
def test_arbitrary_field_value_is_refused_or_valid(name, data):
    msg = MESSAGES[name]
    field = data.draw(st.sampled_from([f.name for f in dataclasses.fields(msg)]))
    out = decode_or_error(tampered(msg, **{field: data.draw(trees)}), type(msg), RUN_SPEC)
    if not isinstance(out, DecodeError):
        assert_same(out, decode(encode(out), type(msg), spec=RUN_SPEC))


def test_compressed_messages_round_trip_and_are_smaller():
    traj = MESSAGES["Trajectory"]
    plain, packed = encode(traj), encode(traj, "zstd")
    assert len(packed) < len(plain)
    out = decode(packed, Trajectory)
    for name in ("obs", "actions", "rewards", "trunc_index", "td_abs"):
        assert np.array_equal(getattr(out, name), getattr(traj, name)), name
    with pytest.raises(ValueError, match="compression"):
        encode(traj, "gzip")


def test_compressed_bodies_cannot_inflate_past_the_limit_or_smuggle_garbage():
    import zstandard

    bomb = msgpack.packb({"v": SCHEMA_VERSION, "type": "Trajectory",
                          "zbody": zstandard.ZstdCompressor().compress(b"\0" * 10_000_000)})
    assert len(bomb) < 10_000
    with pytest.raises(DecodeError) as err:
        decode(bomb, Trajectory, max_bytes=1_000_000)
    assert err.value.kind == "size"
    junk = msgpack.packb({"v": SCHEMA_VERSION, "type": "Trajectory", "zbody": b"not zstd"})
    with pytest.raises(DecodeError) as err:
        decode(junk, Trajectory)
    assert err.value.kind == "msgpack"
    both = msgpack.packb({"v": SCHEMA_VERSION, "type": "Ack", "body": {}, "zbody": b""})
    with pytest.raises(DecodeError) as err:
        decode(both, Ack)
    assert err.value.kind == "field"
