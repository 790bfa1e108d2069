"""The learner's device: `auto` takes a GPU only where torch sees one, an explicit `cuda` where
there is none is refused in one line, a bad setting at configuration; on the CPU the update is
the one it always was, and checkpoints written on one device load on another."""

import numpy as np
import pytest
import torch

from tests.test_checkpoint import close, service_for
from tests.test_learner import fragments_and_model
from tpdeb.services.config import ConfigError, resolve
from tpdeb.services.config.train import TrainConfig
from tpdeb.services.device import check_device_setting, resolve_device
from tpdeb.services.evaluate import EvalError, load_policy
from tpdeb.services.store.checkpoint import FINAL
from tpdeb.tpdeb_core.fragments import stack_fragments
from tpdeb.tpdeb_core.learner import Learner
from tpdeb.tpdeb_core.loss_config import LossConfig


@pytest.mark.parametrize("value", ["auto", "cpu", "cuda", "cuda:0", "cuda:12"])
def test_device_settings_are_checked_without_torch(value):
    assert check_device_setting(value) is None


@pytest.mark.parametrize("value", ["gpu", "cuda:", "cuda:x", "CPU", "mps", ""])
def test_a_bad_device_setting_is_refused_at_configuration(value):
    with pytest.raises(ConfigError, match=f"device={value!r}: must be auto, cpu, cuda or "
                                          "cuda:N"):
        resolve(TrainConfig, ["--device", value], "tpdeb-train", "test")


def test_auto_is_the_cpu_where_torch_sees_no_gpu(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("auto") == torch.device("cpu")
    assert resolve_device("cpu") == torch.device("cpu")
    with pytest.raises(ConfigError, match="device='cuda': torch sees no CUDA device on this "
                                          "machine"):
        resolve_device("cuda")


def test_auto_takes_the_first_gpu_and_a_missing_index_is_refused(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    assert resolve_device("auto") == resolve_device("cuda") == torch.device("cuda:0")
    assert resolve_device("cuda:1") == torch.device("cuda:1")
    with pytest.raises(ConfigError, match=r"this machine has 2 CUDA devices \(cuda:0 to cuda:1\)"):
        resolve_device("cuda:2")


def test_the_learner_on_an_explicit_cpu_device_computes_the_same_update():
    """The device path changes nothing on the CPU: the same parameters after three updates."""
    learners = []
    for device in (None, "cpu"):
        fragments, model = fragments_and_model(n=6, seed=4)
        learner = (Learner(model, LossConfig()) if device is None
                   else Learner(model, LossConfig(), device))
        for fragment in fragments:
            learner.observe(fragment)
        for _ in range(3):
            learner.step(stack_fragments(fragments), np.arange(6), np.ones(6, np.float32),
                         np.array([True, False] * 3))
        learners.append(learner)
    default, explicit = learners
    assert explicit.device == default.device == torch.device("cpu")
    for a, b in zip(default.params, explicit.params, strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    step = explicit.optimizer.state[explicit.params[0]]["step"]
    assert step.device.type == "cpu" and int(step) == default.updates == 3


def test_the_learner_service_announces_its_device_and_eval_refuses_a_missing_gpu(
        tmp_path, monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    service, _ = service_for(tmp_path, device="auto")
    assert service.device == torch.device("cpu")
    service.learner.updates = 1  # a final checkpoint is written only after an update
    service.save_checkpoint(FINAL)
    close(service)
    (checkpoint,) = (tmp_path / "checkpoints").glob("final_*.pt")
    model, env_id, _ = load_policy(checkpoint, None, "auto")
    assert model.device == torch.device("cpu")
    assert model.act_deterministic(np.zeros((2, 4), np.float32)).shape == (2, 1)
    with pytest.raises(EvalError, match="device='cuda': torch sees no CUDA device"):
        load_policy(checkpoint, None, "cuda")
    with pytest.raises(ConfigError, match="device='cuda': torch sees no CUDA device"):
        service_for(tmp_path / "other", device="cuda")


@pytest.mark.skipif(torch.cuda.is_available(), reason="the machine has a GPU")
def test_the_learner_refuses_a_missing_gpu_before_it_waits_for_a_router():
    """`tpdeb-learner --device cuda` on a machine without one: one line at once, exit 2, not a
    minute's wait for a router that is not there."""
    import subprocess
    import sys
    import time

    started = time.monotonic()
    done = subprocess.run(
        [sys.executable, "-m", "tpdeb.services.learner", "--device", "cuda", "--env-id",
         "InvertedPendulum-v5", "--run-id", "x", "--connect", "tcp/127.0.0.1:1"],
        capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and time.monotonic() - started < 30
    (line,) = done.stderr.strip().splitlines()
    assert "device='cuda'" in line and "no CUDA device" in line
