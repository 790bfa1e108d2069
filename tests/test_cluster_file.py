"""The cluster file: defaults, overrides, and one clear error per mistake (no processes)."""

import os
from pathlib import Path

import pytest

from tpdeb.services.cluster import Cluster, parse_args
from tpdeb.services.config import ConfigError, resolve, to_toml
from tpdeb.services.config.service import SERVICE_CONFIGS
from tpdeb.services.launcher.plan import child_environment, make_plan
from tpdeb.services.launcher.restart import RestartPolicy, RestartSettings

ROOT = Path(__file__).resolve().parents[1]


def plan_for(tmp_path, text: str | None = None, *flags: str):
    args = list(flags)
    if text is not None:
        path = tmp_path / "cluster.toml"
        path.write_text(text)
        args += ["--cluster-file", str(path)]
    return make_plan(parse_args([*args, "--run-dir", str(tmp_path / "run")]))


def test_default_file_starts_router_replay_learner_then_two_actors(tmp_path):
    plan = plan_for(tmp_path)
    assert [s.role for s in plan.services] == ["router", "replay", "learner", "actor", "evaluator"]
    assert all(s.restart == RestartPolicy("on-failure") for s in plan.services)
    assert plan.restarts == RestartSettings(backoff_s=1.0, reset_after_s=60.0, max_restarts=5,
                                            window_s=120.0, max_backoff_s=30.0)
    assert actors(plan).replicas == 2 and plan.train.num_envs == 4
    assert plan.train.env_id == "HalfCheetah-v5"
    assert plan.endpoint.startswith("tcp/127.0.0.1:") and not plan.endpoint.endswith("auto")


def actors(plan):
    (spec,) = [s for s in plan.services if s.role == "actor"]
    return spec


def test_the_evaluator_is_optional_and_off_with_evaluation(tmp_path):
    assert "evaluator" not in [s.role for s in plan_for(tmp_path, None, "--eval-interval",
                                                        "0").services]
    without = BASE[:BASE.index("[services.evaluator]")]
    assert [s.role for s in plan_for(tmp_path, without).services] == [
        "router", "replay", "learner", "actor"]


def test_the_shells_training_variables_rank_below_flags_and_reach_no_child(tmp_path,
                                                                          monkeypatch):
    """`TPDEB_SEED=3 tpdeb-cluster --seed 5` trains on seed 5 everywhere: the launcher resolves
    the variables once (over the file, under the flags) into train.toml and leaves them out of
    its children's environment, where they would outrank that file."""
    monkeypatch.setenv("TPDEB_SEED", "3")
    monkeypatch.setenv("TPDEB_LEARNING_RATE", "1e-4")
    monkeypatch.setenv("TPDEB_STATS_INTERVAL_S", "2")  # not a training setting: passed on
    plan = plan_for(tmp_path, None, "--seed", "5")
    assert plan.train.seed == 5 and plan.train.learning_rate == 1e-4
    env = child_environment(dict(os.environ), {"OMP_NUM_THREADS": "1"})
    assert "TPDEB_SEED" not in env and "TPDEB_LEARNING_RATE" not in env
    assert env["TPDEB_STATS_INTERVAL_S"] == "2" and env["OMP_NUM_THREADS"] == "1"


def test_each_child_runs_by_its_configuration_resolved_whole(tmp_path, monkeypatch):
    """The launcher resolves every child's configuration once — train.toml, the flags it sets,
    the service's `args` and `env`, the shell's variables — into config/{name}.toml; the child
    starts with that file alone and no TPDEB_* setting but its password, so a flag always wins
    and the run dir records what runs."""
    monkeypatch.setenv("TPDEB_SEED", "3")
    monkeypatch.setenv("TPDEB_STATS_INTERVAL_S", "2")
    text = BASE.replace('depends_on = ["router"]\nrestart = "on-failure"\nargs = []\nenv = {}',
                        'depends_on = ["router"]\nrestart = "on-failure"\n'
                        'args = ["--snapshot-interval-s", "7"]\nenv = {TPDEB_KEEP_SNAPSHOTS = "4"}')
    cluster = Cluster(plan_for(tmp_path, text, "--seed", "5", "--auth"))
    cluster.write_run_dir()
    names = [slot.name for slot in cluster.slots]
    assert names == ["router", "replay", "learner", "actor-0", "actor-1", "evaluator"]
    configs = {}
    for slot in cluster.slots:
        path = cluster.run_dir / "config" / f"{slot.name}.toml"
        assert slot.argv[1:] == ["--config", str(path)]
        assert {k for k in slot.env if k.startswith("TPDEB_")} <= {"TPDEB_PASSWORD"}
        assert slot.stats_interval_s == 2.0
        cls = SERVICE_CONFIGS[slot.role]
        configs[slot.name] = resolve(cls, ["--config", str(path)], slot.name, "", slot.env)
        assert to_toml(configs[slot.name]) == path.read_text()  # it reads back as written
    replay, learner = configs["replay"], configs["learner"]
    assert (replay.snapshot_interval_s, replay.keep_snapshots) == (7.0, 4)
    assert replay.seed == learner.seed == configs["actor-1"].seed == 5
    assert configs["actor-1"].actor_id == "1" and configs["actor-1"].user == "actor-1"
    assert learner.secret_password
    assert learner.secret_password not in (cluster.run_dir / "config" / "learner.toml").read_text()
    assert configs["router"].auth_file and not hasattr(configs["router"], "seed")


def test_a_bad_service_setting_stops_the_launch_naming_it(tmp_path):
    text = BASE.replace('depends_on = ["learner"]\nrestart = "on-failure"\nargs = []',
                        'depends_on = ["learner"]\nrestart = "on-failure"\n'
                        'args = ["--resend-after-s", "0"]')
    cluster = Cluster(plan_for(tmp_path, text))
    with pytest.raises(ConfigError, match="resend_after_s=0.0: must be > 0"):
        cluster.write_run_dir()
    text = BASE.replace('depends_on = ["learner"]\nrestart = "on-failure"\nargs = []',
                        'depends_on = ["learner"]\nrestart = "on-failure"\n'
                        'args = ["--resend-after", "3"]')
    with pytest.raises(ConfigError, match=r"\[services.actor\] args.*--resend-after"):
        Cluster(plan_for(tmp_path, text)).write_run_dir()


def test_a_bad_training_variable_is_named(tmp_path, monkeypatch):
    monkeypatch.setenv("TPDEB_SEED", "three")
    with pytest.raises(ConfigError, match="TPDEB_SEED: seed='three' is not a valid int"):
        plan_for(tmp_path)


def test_flags_override_the_file(tmp_path):
    plan = plan_for(tmp_path, None, "--env-id", "Hopper-v5", "--seed", "7", "--actors", "3",
                    "--set", "learning_rate=3e-4", "--total-timesteps", "5000")
    assert (plan.train.env_id, plan.train.seed, plan.train.total_timesteps) == (
        "Hopper-v5", 7, 5000)
    assert plan.train.learning_rate == 3e-4 and actors(plan).replicas == 3


BASE = (ROOT / "deploy" / "local.toml").read_text()


def test_restart_policies_and_limits_are_read(tmp_path):
    text = (BASE.replace('restart = "on-failure"\nargs = []\nenv = {}\n\n[services.replay]',
                         'restart = "always"\nargs = []\nenv = {}\n\n[services.replay]')
            .replace('depends_on = ["learner"]\nrestart = "on-failure"',
                     'depends_on = ["learner"]\nrestart = "on-failure:3"')
            .replace('depends_on = ["replay"]\nrestart = "on-failure"',
                     'depends_on = ["replay"]\nrestart = "no"')
            .replace("restart_backoff_s = 1", "restart_backoff_s = 0.25")
            .replace("max_restarts = 5", "max_restarts = 2"))
    plan = plan_for(tmp_path, text)
    policies = {s.role: str(s.restart) for s in plan.services}
    assert policies == {"router": "always", "replay": "on-failure", "learner": "no",
                        "actor": "on-failure:3", "evaluator": "on-failure:3"}
    assert (plan.restarts.backoff_s, plan.restarts.max_restarts) == (0.25, 2)


def test_a_file_without_restart_settings_gets_the_defaults(tmp_path):
    lines = [line for line in BASE.splitlines()
             if not line.startswith(("restart", "max_restarts", "crash_loop"))]
    plan = plan_for(tmp_path, "\n".join(lines))
    assert all(str(s.restart) == "on-failure" for s in plan.services)
    assert plan.restarts == RestartSettings()


def test_the_router_starts_first_whatever_the_file_order(tmp_path):
    section = BASE[BASE.index("[services.router]"):BASE.index("[services.replay]")]
    plan = plan_for(tmp_path, BASE.replace(section, "") + "\n" + section)
    assert [s.role for s in plan.services] == ["router", "replay", "learner", "actor", "evaluator"]


def test_a_bad_restart_policy_names_the_value_and_the_choices(tmp_path):
    text = BASE.replace('depends_on = ["learner"]\nrestart = "on-failure"',
                        'depends_on = ["learner"]\nrestart = "unless-stopped"')
    with pytest.raises(ConfigError) as info:
        plan_for(tmp_path, text)
    message = str(info.value)
    assert "[services.actor]" in message and "'unless-stopped'" in message
    for choice in ('"no"', '"on-failure"', '"on-failure:N"', '"always"'):
        assert choice in message


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
    (BASE.replace('restart = "on-failure"', 'restart = "on-failure:x"', 1), [],
     "restart='on-failure:x' is not a restart policy"),
    (BASE.replace('restart = "on-failure"', "restart = false", 1), [],
     "restart=False is not a restart policy"),
    (BASE.replace("max_restarts = 5", "max_restarts = -1"), [], r"max_restarts=-1: expected an"),
    (BASE.replace("max_restarts = 5", "max_restarts = 2.5"), [], r"max_restarts=2.5"),
    (BASE.replace("restart_backoff_s = 1", "restart_backoff_s = 0"), [],
     r"restart_backoff_s=0: expected a number of seconds > 0"),
    (BASE.replace("crash_loop_window_s = 120", 'crash_loop_window_s = "2m"'), [],
     "crash_loop_window_s='2m'"),
    (BASE.replace("[services.router]", "[services.zenohd]"), [], "unknown service 'zenohd'"),
    (BASE.replace('[services.router]\ncommand = "tpdeb-router"\n',
                  '[services.router]\ncommand = "tpdeb-router"\ndepends_on = ["replay"]\n'),
     [], "the router starts first"),
])
def test_mistakes_are_refused_with_the_reason(tmp_path, text, flags, message):
    with pytest.raises(ConfigError, match=message):
        plan_for(tmp_path, text, *flags)
