"""Core objects on the wire: fragments and parameters survive the trip, float16 halves the
parameters and an actor acts on them within float16's precision."""

import dataclasses

import numpy as np
import torch

from tests.fakes import ScriptedVectorEnv
from tpdeb.protocol import Params, Trajectory, decode, encode
from tpdeb.services.net.model_wire import params_message
from tpdeb.services.net.wire import check_params
from tpdeb.tpdeb_core.fragments import Collector
from tpdeb.tpdeb_core.model import ActorCritic
from tpdeb.tpdeb_core.policy import NumpyPolicy, param_shapes


def test_fragment_round_trip_through_the_codec_compressed_or_not():
    envs = ScriptedVectorEnv((5, 7), (True, False))
    collector = Collector(envs, ActorCritic(3, 1).numpy_policy(), 8, 0.9,
                          np.array([-1.0], np.float32), np.array([1.0], np.float32), seed=1)
    fragments = []
    while len(fragments) < 4:
        fragments += collector.step()
    for compression in ("none", "zstd"):
        for fragment in fragments:
            back = decode(encode(fragment, compression), Trajectory)
            for f in dataclasses.fields(fragment):  # every field, as the Collector made it
                np.testing.assert_array_equal(getattr(back, f.name), getattr(fragment, f.name))
                if isinstance(getattr(back, f.name), np.ndarray):
                    assert getattr(back, f.name).dtype == getattr(fragment, f.name).dtype


def test_float16_parameters_are_half_the_bytes_and_load_back_closely():
    torch.manual_seed(0)
    model = ActorCritic(17, 6)
    model.obs_rms.update(np.random.default_rng(0).normal(size=(50, 17)))
    full = encode(params_message(model.arrays(), 3))
    half = encode(params_message(model.arrays(), 3, "float16"))
    assert len(half) < 0.6 * len(full)
    received = decode(half, Params)
    check_params(received, param_shapes(17, 6, (64, 64)))  # an actor accepts it
    for name, value in model.state_dict().items():
        got = received.arrays[name]
        assert got.dtype == (np.float16 if value.dtype == torch.float32 else np.float64), name
        np.testing.assert_allclose(got.astype(np.float64), value.numpy(), rtol=1e-3, atol=1e-3)
    # normaliser statistics travel exactly (float64)
    np.testing.assert_array_equal(received.arrays["obs_rms.mean"], model.obs_rms.mean.numpy())
    obs = np.random.default_rng(1).normal(size=(5, 17)).astype(np.float32)
    np.testing.assert_allclose(NumpyPolicy(received.arrays, model.obs_clip).values_of(obs),
                               model.values_of(obs), rtol=1e-2, atol=1e-2)


def test_weights_beyond_float16_range_stay_float32():
    model = ActorCritic(3, 1)
    with torch.no_grad():
        model.value_net[0].weight[0, 0] = 1e6
    arrays = params_message(model.arrays(), 1, "float16").arrays
    assert arrays["value_net.0.weight"].dtype == np.float32
    assert arrays["value_net.2.weight"].dtype == np.float16
