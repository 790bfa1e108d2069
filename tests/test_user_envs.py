"""Users' environments: `module:Env-v0` imported from the current directory as `python -m`
would, gymnasium.make's keyword arguments (`env_kwargs`) from flags and files, carried in the run
spec and checked by every peer; each way to get them wrong gets one line."""

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

from tpdeb.services.config import ConfigError, resolve
from tpdeb.services.config.train import TrainConfig
from tpdeb.services.envs import canonical_env_kwargs, make_vector_env, parse_env_kwargs
from tpdeb.services.net.wire import run_spec, spec_mismatch

MODULE = textwrap.dedent('''
    """A user's environments, registered when the module is imported."""
    import gymnasium as gym
    import numpy as np


    class Reach(gym.Env):
        """Move a point toward the origin; `size` sets the start's scale."""

        def __init__(self, size=1.0):
            self.size = size
            self.observation_space = gym.spaces.Box(-np.inf, np.inf, (2,), np.float32)
            self.action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)

        def reset(self, seed=None, options=None):
            super().reset(seed=seed)
            self.x = self.np_random.uniform(-self.size, self.size, 2).astype(np.float32)
            self.t = 0
            return self.x.copy(), {}

        def step(self, action):
            self.x = (self.x + 0.1 * np.clip(action, -1, 1)).astype(np.float32)
            self.t += 1
            return self.x.copy(), -float(np.abs(self.x).sum()), False, self.t >= 50, {}


    class Grid(Reach):
        def __init__(self):
            super().__init__()
            self.action_space = gym.spaces.Discrete(4)


    gym.register(id="Reach-v0", entry_point=Reach)
    gym.register(id="Grid-v0", entry_point=Grid)
''')


@pytest.fixture
def user_dir(tmp_path, monkeypatch):
    """A working directory holding the user's module (and a broken one), cwd set to it, and
    sys.path / sys.modules left as they were afterwards."""
    (tmp_path / "myenvs.py").write_text(MODULE)
    (tmp_path / "brokenenvs.py").write_text("import numpy\nraise RuntimeError('typo in line 2')\n")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "path", list(sys.path))
    yield tmp_path
    for name in ("myenvs", "brokenenvs"):
        sys.modules.pop(name, None)
    for env_id in ("Reach-v0", "Grid-v0"):
        gym.registry.pop(env_id, None)


@pytest.mark.parametrize("text, expected", [
    ("", {}),
    ('{"ctrl_cost_weight": 0.2, "reset_noise_scale": 0}',
     {"ctrl_cost_weight": 0.2, "reset_noise_scale": 0}),
    ("ctrl_cost_weight = 0.2, xml_file = 'a.xml'", {"ctrl_cost_weight": 0.2, "xml_file": "a.xml"}),
    ("{ ctrl_cost_weight = 0.2 }", {"ctrl_cost_weight": 0.2}),
])
def test_env_kwargs_are_json_or_a_toml_inline_table(text, expected):
    assert parse_env_kwargs(text) == expected


@pytest.mark.parametrize("text, message", [
    ("[1, 2]", "must be an object of keyword arguments, not a list"),
    ("ctrl_cost_weight: 0.2", "neither a JSON object nor a TOML inline table"),
])
def test_bad_env_kwargs_are_refused_in_one_line(text, message):
    with pytest.raises(ValueError, match=message):
        parse_env_kwargs(text)
    with pytest.raises(ConfigError, match=message):
        resolve(TrainConfig, ["--env-kwargs", text], "tpdeb-train", "test")


def test_env_kwargs_have_one_text_from_flags_variables_and_files(tmp_path):
    canonical = '{"a":2,"b":"x"}'
    assert canonical_env_kwargs('{"b": "x", "a": 2}') == canonical
    flag = resolve(TrainConfig, ["--env-kwargs", "b = 'x', a = 2"], "tpdeb-train", "test")
    variable = resolve(TrainConfig, [], "tpdeb-train", "test",
                       environ={"TPDEB_ENV_KWARGS": '{"a": 2, "b": "x"}'})
    config = tmp_path / "run.toml"
    config.write_text("[run.env_kwargs]\nb = 'x'\na = 2\n")
    table = resolve(TrainConfig, ["--config", str(config)], "tpdeb-train", "test")
    assert flag.env_kwargs == variable.env_kwargs == table.env_kwargs == canonical


def test_env_kwargs_reach_the_env_and_a_wrong_one_is_named():
    envs = make_vector_env("HalfCheetah-v5", 1, '{"ctrl_cost_weight": 0.3}')
    try:
        assert envs.envs[0].unwrapped._ctrl_cost_weight == 0.3
    finally:
        envs.close()
    with pytest.raises(ConfigError, match=r"env_kwargs \{\"ctrl_cost\": 0.3\} do not fit "
                                          r"'HalfCheetah-v5'.*ctrl_cost"):
        make_vector_env("HalfCheetah-v5", 1, '{"ctrl_cost": 0.3}')


def test_a_users_module_is_imported_from_the_working_directory(user_dir):
    sys.path[:] = [p for p in sys.path if p not in ("", str(user_dir))]
    envs = make_vector_env("myenvs:Reach-v0", 2, "size = 3.0")
    try:
        assert envs.single_observation_space.shape == (2,)
        assert envs.envs[0].unwrapped.size == 3.0
        obs, _ = envs.reset(seed=1)
        assert obs.shape == (2, 2) and np.abs(obs).max() <= 3.0
    finally:
        envs.close()


@pytest.mark.parametrize("env_id, message", [
    ("brokenenvs:Reach-v0", r"module 'brokenenvs' cannot be imported from .* \(RuntimeError: "
                            r"typo in line 2\)"),
    ("nosuchmodule:Reach-v0", r"module 'nosuchmodule' cannot be imported .*ModuleNotFoundError"),
    ("myenvs:Grid-v0", r"has Discrete\(4\) actions: TPDEB trains continuous"),
])
def test_a_module_that_fails_or_an_env_that_does_not_fit_gets_one_line(user_dir, env_id,
                                                                        message):
    with pytest.raises(ConfigError, match=message):
        make_vector_env(env_id, 1)


def test_peers_with_other_env_kwargs_are_refused():
    config = TrainConfig(env_kwargs='{"ctrl_cost_weight": 0.3}')
    spec = run_spec(config, 17, 6, np.full(6, -1.0), np.full(6, 1.0))
    assert spec.env_kwargs == '{"ctrl_cost_weight":0.3}'
    assert spec_mismatch(spec, config.env_id, 17, 6, config.env_kwargs) is None
    problem = spec_mismatch(spec, config.env_id, 17, 6, "")
    assert "env_kwargs {\"ctrl_cost_weight\":0.3} but this process with {}" in problem


def test_tpdeb_train_and_eval_run_a_users_env_from_its_directory(user_dir):
    """The console scripts, run where the module is and without PYTHONPATH, as a user would."""
    bin_dir = Path(sys.executable).parent
    env = {"PATH": f"{bin_dir}:/usr/bin:/bin", "HOME": str(user_dir)}
    train = subprocess.run(
        [str(bin_dir / "tpdeb-train"), "--env-id", "myenvs:Reach-v0", "--env-kwargs",
         '{"size": 2.0}', "--total-timesteps", "1024", "--num-envs", "2", "--run-dir", "run",
         "--preset", "none", "--compile", "off"],  # (a new env's shapes: a cold compile, waited
        cwd=user_dir, env=env, capture_output=True, text=True, timeout=300)  # for at the end)
    assert train.returncode == 0, train.stderr[-2000:]
    saved = (user_dir / "run" / "config.toml").read_text()
    assert 'env_kwargs = "{\\"size\\":2.0}"' in saved
    evaluation = subprocess.run(
        [str(bin_dir / "tpdeb-eval"), "run", "--episodes", "2", "--json"], cwd=user_dir,
        env=env, capture_output=True, text=True, timeout=300)
    assert evaluation.returncode == 0, evaluation.stderr[-2000:]
    result = json.loads(evaluation.stdout.strip().splitlines()[-1])
    assert result["env_id"] == "myenvs:Reach-v0" and result["mean_length"] == 50
