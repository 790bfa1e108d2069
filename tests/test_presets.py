"""Task presets and the algorithm switch: chosen by env id, announced, overridden by the usual
layers; baselines fix what defines them and refuse contradicting settings."""

import dataclasses
import re
import subprocess
import sys
from pathlib import Path

import pytest

from tpdeb.services.config import ConfigError, resolve
from tpdeb.services.config.presets import ALGORITHMS, PRESETS_DIR, load_preset, shown
from tpdeb.services.config.service import ActorServiceConfig, LearnerServiceConfig
from tpdeb.services.config.train import RunSettings, TrainConfig

ROOT = Path(__file__).resolve().parents[1]
TASKS = ("HalfCheetah-v5", "Hopper-v5", "Walker2d-v5", "Ant-v5", "Humanoid-v5", "Swimmer-v5")
SETTING = re.compile(r"^([a-z_]+)\s*=")


def parse(argv, cls=TrainConfig):
    return resolve(cls, argv, "tpdeb-train", "test")


# What Hopper's preset file says: the tests check the layering, not the tuned numbers.
HOPPER = load_preset(TrainConfig, PRESETS_DIR / "Hopper-v5.toml")


def preset_settings(path: Path) -> list[tuple[str, str]]:
    """(setting, the comment lines just above it) for each setting in a preset file."""
    found, comment = [], []
    for line in path.read_text().splitlines():
        if line.startswith("#"):
            comment.append(line)
        elif SETTING.match(line):
            found.append((SETTING.match(line)[1], " ".join(comment)))
            comment = []
        elif not line.strip():
            comment = []
    return found


@pytest.mark.parametrize("env_id", TASKS)
def test_every_task_has_a_preset_whose_values_are_settings_with_a_reason(env_id):
    path = PRESETS_DIR / f"{env_id}.toml"
    settings = preset_settings(path)
    assert settings, f"{path} sets nothing"
    names = ({f.name for f in dataclasses.fields(TrainConfig)}
             - {f.name for f in dataclasses.fields(RunSettings)})
    for name, reason in settings:
        assert name in names, f"{path}: {name} is not a training setting"
        assert len(reason) > 20, f"{path}: {name} has no reason above it"
    config = parse(["--env-id", env_id])
    assert config.preset == str(path.resolve())


@pytest.mark.parametrize("path", sorted((PRESETS_DIR / "race").glob("*.toml")),
                         ids=lambda p: p.stem)
def test_a_race_preset_is_its_tasks_preset_with_measured_changes(path):
    # the file replaces the task's preset (--preset FILE): it repeats the per-step values, and
    # every value it changes carries its measurement
    race = load_preset(TrainConfig, path)
    step = load_preset(TrainConfig, PRESETS_DIR / path.name)
    changed = {k for k in race if race[k] != step.get(k)}
    assert changed, f"{path} is its task's preset unchanged"
    assert set(step) <= set(race), f"{path} leaves out {set(step) - set(race)}"
    reasons = dict(preset_settings(path))
    for name in changed:
        assert len(reasons[name]) > 20, f"{path}: {name} has no measurement above it"
    config = parse(["--env-id", path.stem, "--preset", str(path)])
    assert all(getattr(config, k) == tuple(v) if isinstance(v, list) else getattr(config, k) == v
               for k, v in race.items())


def test_larger_networks_for_ant_and_humanoid():
    for env_id in ("Ant-v5", "Humanoid-v5"):
        assert min(parse(["--env-id", env_id]).hidden_sizes) > 64


def test_preset_is_below_file_env_and_flags(tmp_path, monkeypatch):
    preset = parse(["--env-id", "Hopper-v5"])
    plain = parse(["--env-id", "Hopper-v5", "--preset", "none"])
    assert preset.vtrace_lambda == HOPPER["vtrace_lambda"] != plain.vtrace_lambda
    assert plain.vtrace_lambda == TrainConfig.vtrace_lambda
    assert plain.preset == "none"
    file = tmp_path / "c.toml"
    file.write_text("[loss]\nvtrace_lambda = 0.7\n")
    assert parse(["--env-id", "Hopper-v5", "--config", str(file)]).vtrace_lambda == 0.7
    monkeypatch.setenv("TPDEB_VTRACE_LAMBDA", "0.8")
    assert parse(["--env-id", "Hopper-v5", "--config", str(file)]).vtrace_lambda == 0.8
    assert parse(["--env-id", "Hopper-v5", "--vtrace-lambda", "0.9"]).vtrace_lambda == 0.9


def test_the_env_id_from_a_file_or_the_environment_picks_the_preset(tmp_path, monkeypatch):
    file = tmp_path / "c.toml"
    file.write_text('[run]\nenv_id = "Swimmer-v5"\n')
    assert parse(["--config", str(file)]).preset.endswith("Swimmer-v5.toml")
    monkeypatch.setenv("TPDEB_ENV_ID", "Hopper-v5")
    assert parse([], LearnerServiceConfig).preset.endswith("Hopper-v5.toml")


def test_a_task_without_a_preset_runs_the_defaults():
    config = parse(["--env-id", "InvertedPendulum-v5"])
    assert config.preset == "none" and config.gamma == TrainConfig.gamma


def test_impact_and_ppo_per_fix_what_defines_them():
    # Hopper's preset asks for an adaptive KL term; IMPACT has none, the rest of the preset holds.
    hopper = parse(["--env-id", "Hopper-v5"])
    impact = parse(["--env-id", "Hopper-v5", "--algo", "impact"])
    assert hopper.kl_target > 0
    assert (impact.zeta, impact.kl_coef, impact.kl_target) == (0.0, 0.0, 0.0)
    assert impact.clip_anchor == "target" and impact.vtrace_lambda == hopper.vtrace_lambda
    ppo = parse(["--algo", "ppo-per", "--batch-fragments", "6"])
    assert (ppo.zeta, ppo.priority_mode, ppo.replay_retention, ppo.clip_anchor) == (
        1.0, "step", "fifo", "behaviour")
    assert ppo.prioritized_capacity == 18 and ppo.kl_coef == 0.0  # three batches, no KL
    tpdeb = parse([])
    assert tpdeb.zeta > 0 and tpdeb.kl_coef > 0 and tpdeb.priority_mode == "trajectory"


def test_a_setting_that_contradicts_the_algorithm_is_refused():
    with pytest.raises(ConfigError, match="algo=impact fixes kl_coef=0.0"):
        parse(["--algo", "impact", "--kl-coef", "0.01"])
    with pytest.raises(ConfigError, match="algo=ppo-per fixes clip_anchor"):
        parse(["--algo", "ppo-per", "--clip-anchor", "target"])
    with pytest.raises(ConfigError, match="algo"):
        parse(["--algo", "sac"])
    # Repeating what the algorithm fixes is fine: a resolved config reads back.
    assert parse(["--algo", "impact", "--zeta", "0"]).zeta == 0.0


def test_every_algorithm_runs_through_every_service_config():
    for algo in ALGORITHMS:
        for cls in (ActorServiceConfig, LearnerServiceConfig):
            assert parse(["--algo", algo, "--env-id", "Ant-v5"], cls).algo == algo


def test_tpdeb_train_announces_the_preset(tmp_path):
    cmd = [sys.executable, "-m", "tpdeb.services.serial", "--env-id", "Hopper-v5",
           "--total-timesteps", "64", "--num-envs", "1", "--run-dir", str(tmp_path / "run")]
    out = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert "preset: deploy/presets/Hopper-v5.toml" in out.stdout
    written = (tmp_path / "run" / "config.toml").read_text()
    assert f"kl_target = {HOPPER['kl_target']}" in written and "Hopper-v5.toml" in written


def test_the_cluster_applies_the_preset_below_its_file_and_flags(tmp_path):
    from tpdeb.services.cluster import parse_args
    from tpdeb.services.launcher.plan import make_plan

    def plan(*flags):
        return make_plan(parse_args([*flags, "--run-dir", str(tmp_path / "run")])).train

    assert plan("--env-id", "Hopper-v5").kl_target == HOPPER["kl_target"] != TrainConfig.kl_target
    assert plan("--env-id", "Hopper-v5", "--set", "kl_target=0.02").kl_target == 0.02
    assert plan("--env-id", "Hopper-v5", "--set", "preset=none").kl_target == TrainConfig.kl_target
    impact = plan("--env-id", "Ant-v5", "--set", "algo=impact")
    assert impact.zeta == 0.0 and impact.hidden_sizes == parse(["--env-id", "Ant-v5"]).hidden_sizes
    with pytest.raises(ConfigError, match="algo=impact fixes"):
        plan("--set", "algo=impact", "--set", "kl_coef=0.1")


def test_a_wall_clock_budget_picks_the_race_preset_where_the_task_has_one():
    race = sorted((PRESETS_DIR / "race").glob("*.toml"))
    assert race, "no race presets"
    raced = race[0].stem
    clocked = parse(["--env-id", raced, "--train-for-seconds", "900"])
    assert clocked.preset == str(race[0].resolve())
    assert parse(["--env-id", raced]).preset == str((PRESETS_DIR / f"{raced}.toml").resolve())
    # a task without a race preset keeps its preset; an explicit choice outranks the rule
    plain = next(t for t in TASKS if not (PRESETS_DIR / "race" / f"{t}.toml").is_file())
    assert (parse(["--env-id", plain, "--train-for-seconds", "900"]).preset
            == str((PRESETS_DIR / f"{plain}.toml").resolve()))
    assert parse(["--env-id", raced, "--train-for-seconds", "900", "--preset", "none"]).preset \
        == "none"
    # every service of the run resolves the same file from the same settings
    for cls in (ActorServiceConfig, LearnerServiceConfig):
        assert parse(["--env-id", raced, "--train-for-seconds", "900"], cls).preset \
            == clocked.preset
    assert "race preset" in shown(clocked.preset)
