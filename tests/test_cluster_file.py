"""The cluster file: defaults, overrides, and one clear error per mistake (no processes)."""

from pathlib import Path

import pytest

from services.cluster import make_plan, parse_args
from services.config import ConfigError

ROOT = Path(__file__).resolve().parents[1]


def plan_for(tmp_path, text: str | None = None, *flags: str):
    args = list(flags)
    if text is not None:
        path = tmp_path / "cluster.toml"
        path.write_text(text)
        args += ["--config", str(path)]
    return make_plan(parse_args([*args, "--run-dir", str(tmp_path / "run")]))


def test_default_file_starts_replay_learner_then_two_actors(tmp_path):
    plan = plan_for(tmp_path)
    assert [s.role for s in plan.services] == ["replay", "learner", "actor"]
    assert plan.services[-1].replicas == 2 and plan.train.num_envs == 4
    assert plan.train.env_id == "HalfCheetah-v5"
    assert plan.endpoint.startswith("tcp/127.0.0.1:") and not plan.endpoint.endswith("auto")


def test_flags_override_the_file(tmp_path):
    plan = plan_for(tmp_path, None, "--env-id", "Hopper-v5", "--seed", "7", "--actors", "3",
                    "--set", "learning_rate=3e-4", "--total-timesteps", "5000")
    assert (plan.train.env_id, plan.train.seed, plan.train.total_timesteps) == (
        "Hopper-v5", 7, 5000)
    assert plan.train.learning_rate == 3e-4 and plan.services[-1].replicas == 3


BASE = (ROOT / "deploy" / "local.toml").read_text()


@pytest.mark.parametrize("text, flags, message", [
    (BASE + "\n[extra]\n", [], "unknown section"),
    (BASE.replace("stop_timeout_s = 20", "stop_timeout = 20"), [], "unknown key"),
    (BASE.replace('depends_on = ["replay"]', 'depends_on = ["actor"]'), [], "cycle"),
    (BASE.replace('depends_on = ["replay"]', 'depends_on = ["db"]'), [], "unknown service"),
    (BASE.replace("[services.actor]", "[services.worker]"), [], "unknown service"),
    (BASE, ["--actors", "0"], "replicas=0"),
    (BASE, ["--set", "learning_rat=1"], "learning_rat"),
    (BASE, ["--set", "zeta=2"], "zeta=2.0"),
    (BASE, ["--set", "nonsense"], "KEY=VALUE"),
])
def test_mistakes_are_refused_with_the_reason(tmp_path, text, flags, message):
    with pytest.raises(ConfigError, match=message):
        plan_for(tmp_path, text, *flags)
