import pytest

from tpdeb.services.config import ConfigError, resolve, to_toml
from tpdeb.services.config.service import ReplayServiceConfig
from tpdeb.services.config.train import TrainConfig


def parse(argv, **kw):
    return resolve(TrainConfig, argv, "tpdeb-train", "test", **kw)


def test_flags_follow_cleanrl_names_and_types():
    cfg = parse(["--env-id", "InvertedPendulum-v5", "--seed", "7", "--total-timesteps", "1e5",
                 "--learning-rate", "3e-4", "--num-envs", "4", "--hidden-sizes", "32", "16",
                 "--norm-adv", "false"])
    assert cfg.env_id == "InvertedPendulum-v5" and cfg.seed == 7
    assert cfg.total_timesteps == 100_000 and cfg.num_envs == 4
    assert cfg.learning_rate == pytest.approx(3e-4)
    assert cfg.hidden_sizes == (32, 16) and cfg.norm_adv is False


def test_precedence_defaults_file_env_flags(tmp_path, monkeypatch):
    path = tmp_path / "c.toml"
    path.write_text('[run]\nseed = 5\nexp_name = "from-file"\n[replay]\nzeta = 0.5\n')
    monkeypatch.setenv("TPDEB_ZETA", "0.3")
    monkeypatch.setenv("TPDEB_GAMMA", "0.95")
    cfg = parse(["--config", str(path), "--gamma", "0.9"])
    assert cfg.seed == 5 and cfg.exp_name == "from-file"  # file over defaults
    assert cfg.zeta == pytest.approx(0.3)  # env over file
    assert cfg.gamma == pytest.approx(0.9)  # flag over env


def test_resolved_config_round_trips_through_toml(tmp_path):
    cfg = parse(["--seed", "3", "--hidden-sizes", "8", "8"])
    path = tmp_path / "config.toml"
    path.write_text(to_toml(cfg))
    assert parse(["--config", str(path)]) == cfg


def test_help_shows_field_docstrings(capsys):
    with pytest.raises(SystemExit):
        parse(["--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "sampled steps per inserted step" in text
    assert "--total-timesteps" in text


@pytest.mark.parametrize("argv, message", [
    (["--zeta", "1.5"], "zeta=1.5"),
    (["--seed", "abc"], "seed='abc' is not a valid int"),
    (["--priority-mode", "bogus"], "priority_mode='bogus'"),
    (["--tau", "0"], "tau=0"),
    (["--uniform-capacity-steps", "10"], "uniform_capacity_steps=10"),
    (["--rate-error-buffer-steps", "5"], "replay ratio settings"),
    (["--learning-starts-fragments", "10000"], "replay ratio settings"),
    (["--replay-ratio", "8", "--max-replay-ratio", "4"], "max_replay_ratio=4.0: must be 0"),
])
def test_bad_settings_are_refused_with_the_value(argv, message):
    with pytest.raises(ConfigError, match=message.replace("(", r"\(")):
        parse(argv)


@pytest.mark.parametrize("flag, text, message", [
    ("--config", "seed = = 1", "not valid TOML"),
    ("--config", "[run]\nsed = 1", r"\[run\]: unknown setting 'sed' \(did you mean 'seed'"),
    ("--config", "seed = 1", r"seed = 1 outside a table: put it under \[run\]"),
    ("--config", "[run]\nzeta = 0.1", r"\[run\]: zeta belongs in \[replay\]"),
    ("--config", "[optim]\nlearning_rate = 0.1", r"no table \[optim\] here; expected \[run\], "),
    ("--preset", "seed = = 3", r"^preset \S+: not valid TOML"),
    ("--preset", "[run]\nseed = 3", r"no table \[run\] here \(a preset holds training settings"),
    ("--preset", "[loss]\nlearning_rat = 3e-4", "unknown setting 'learning_rat'.*'learning_rate'"),
    ("--preset", "[replay]\ngamma = 0.9", r"gamma belongs in \[loss\]"),
    ("--preset", "gamma = 0.9", r"outside a table: put it under \[loss\]"),
    ("--preset", "[loss]\ngamma = 'high'", "gamma='high' is not a valid float"),
])
def test_bad_files_are_refused_in_one_line(tmp_path, flag, text, message):
    bad = tmp_path / "bad.toml"
    bad.write_text(text)
    with pytest.raises(ConfigError, match=message):
        parse([flag, str(bad)])


@pytest.mark.parametrize("flag", ["--config", "--preset"])
def test_a_missing_file_is_named(tmp_path, flag):
    with pytest.raises(ConfigError, match="no such file"):
        parse([flag, str(tmp_path / "missing.toml")])


def test_an_empty_list_flag_clears_the_list():
    from tpdeb.services.config.service import ReplayServiceConfig

    cfg = resolve(ReplayServiceConfig, ["--listen", "", "--connect", "tcp/127.0.0.1:7447"],
                  "tpdeb-replay", "test")
    assert cfg.listen == () and cfg.connect == ("tcp/127.0.0.1:7447",)


def test_the_loss_settings_are_declared_once_and_help_shows_a_services_own_first():
    import dataclasses

    from tpdeb.services.config import build_parser
    from tpdeb.services.config.service import (
        ActorServiceConfig,
        LearnerServiceConfig,
        ReplayServiceConfig,
        RouterConfig,
    )
    from tpdeb.tpdeb_core.loss_config import LossConfig

    loss = {f.name for f in dataclasses.fields(LossConfig)}
    assert loss <= {f.name for f in dataclasses.fields(TrainConfig)}
    owners = [vars(k).get("__annotations__", {}) for k in TrainConfig.__mro__]
    names = [name for own in owners for name in own if name != "SECTION"]
    assert len(names) == len(set(names))  # every group's settings declared once, none repeated
    flags = [action.dest for action in build_parser(LearnerServiceConfig, "p", "")._actions]
    assert flags.index("requests_in_flight") < flags.index("run_id") < flags.index("env_id") \
        < flags.index("learning_rate")
    # each service holds what it uses: the router no training setting, the actor none of the
    # replay's, the loss's or the optimiser's
    training = {f.name for f in dataclasses.fields(TrainConfig)}
    assert not training & {f.name for f in dataclasses.fields(RouterConfig)}
    actor = {f.name for f in dataclasses.fields(ActorServiceConfig)}
    assert actor & training == {"exp_name", "algo", "preset", "env_id", "env_kwargs", "seed",
                                "total_timesteps", "train_for_seconds",
                                "run_dir", "log_interval_s", "num_envs",
                                "trajectory_compression"}
    # the replay: the run, the model, the buffers and the priorities, not the optimiser's
    replay = {f.name for f in dataclasses.fields(ReplayServiceConfig)}
    assert {"zeta", "fragment_len", "gamma", "priority_mode"} <= replay
    assert not replay & {"learning_rate", "adam_eps", "kl_coef", "anneal_lr", "num_envs"}
    learner = {f.name for f in dataclasses.fields(LearnerServiceConfig)}
    assert training - learner == {"num_envs", "trajectory_compression", "eval_interval",
                                  "eval_episodes"}


def test_every_setting_has_one_table_and_files_list_them_in_order():
    import dataclasses

    from tpdeb.services.config import SECTIONS, known_settings, section_of
    from tpdeb.services.config.service import SERVICE_CONFIGS

    known = known_settings()
    assert set(known.values()) == set(SECTIONS) - {"link"}  # the link's: its own file
    for cls in SERVICE_CONFIGS.values():  # a field means the same, and sits in the same table,
        for f in dataclasses.fields(cls):  # in every service that holds it
            assert section_of(cls, f.name) == known[f.name], (cls.__name__, f.name)
    assert section_of(ReplayServiceConfig, "listen") == "net"  # redeclared: the group's table
    text = to_toml(TrainConfig())
    assert [line for line in text.splitlines() if line.startswith("[")] == [
        "[run]", "[actor]", "[model]", "[replay]", "[learner]", "[loss]", "[eval]"]


def test_a_service_reads_a_shared_train_file_and_takes_what_it_uses(tmp_path):
    from tpdeb.services.config.service import ActorServiceConfig

    path = tmp_path / "train.toml"
    path.write_text(to_toml(TrainConfig(num_envs=3, learning_rate=3e-4)))
    actor = resolve(ActorServiceConfig, ["--config", str(path)], "p", "")
    assert actor.num_envs == 3 and not hasattr(actor, "learning_rate")
    path.write_text("[actor]\nnum_envs = 3\n[loss]\nlearning_rat = 0.1\n")  # a typo: refused
    with pytest.raises(ConfigError, match="unknown setting 'learning_rat'"):
        resolve(ActorServiceConfig, ["--config", str(path)], "p", "")
    # the same command line for every service: the actor passes over the learner's flags
    actor = resolve(ActorServiceConfig, ["--fragment-len", "32", "--anneal-lr",
                                         "--hidden-sizes", "8", "8", "--num-envs", "2"], "p", "")
    assert actor.num_envs == 2
    with pytest.raises(SystemExit):  # but not a misspelt one
        resolve(ActorServiceConfig, ["--fragment-lenn", "32"], "p", "")


def test_every_process_reads_back_the_file_it_would_write(tmp_path):
    from tpdeb.services.config.service import SERVICE_CONFIGS
    from tpdeb.services.link import LinkConfig

    for cls in (*SERVICE_CONFIGS.values(), LinkConfig, TrainConfig):
        config = resolve(cls, ["--run-id", "r7"] if cls is not TrainConfig else [], "p", "")
        path = tmp_path / f"{cls.__name__}.toml"
        path.write_text(to_toml(config))
        assert resolve(cls, ["--config", str(path)], "p", "") == config, cls.__name__
    path = tmp_path / "link.toml"
    path.write_text("[link]\nup_bytes_per_s = 1e6\n")
    assert resolve(LinkConfig, ["--config", str(path)], "p", "").up_bytes_per_s == 1e6


def test_a_password_comes_from_a_secret_file_and_no_copy_of_the_config_keeps_it(tmp_path):
    from tpdeb.services.config.service import NetConfig

    secret = tmp_path / "actor_password"
    secret.write_text("s3cret\n")
    config = NetConfig(user="actor-0", password_file=str(secret))
    assert config.secret_password == "s3cret" and "s3cret" not in to_toml(config)
    with pytest.raises(ConfigError, match="both set"):
        NetConfig(user="actor-0", password="x", password_file=str(secret))
    secret.write_text("\n")
    with pytest.raises(ConfigError, match="first line is empty"):
        NetConfig(user="actor-0", password_file=str(secret))
    with pytest.raises(ConfigError, match="cannot read it"):
        NetConfig(user="actor-0", password_file=str(tmp_path / "missing"))


def test_a_removed_setting_is_refused_in_one_line_naming_what_replaced_it(tmp_path):
    """loss_impl is gone (one loss, compiled): a flag, a variable, a file or --set that gives
    it is told so, not merely "unknown"."""
    settings = tmp_path / "old.toml"
    settings.write_text('[loss]\nloss_impl = "closed_form"\n')
    attempts = [(["--loss-impl", "autograd"], {}), ([], {"TPDEB_LOSS_IMPL": "closed_form"}),
                (["--config", str(settings)], {})]
    for argv, environ in attempts:
        with pytest.raises(ConfigError) as refused:
            resolve(TrainConfig, argv, "tpdeb-train", "", environ=environ)
        line = str(refused.value)
        assert "\n" not in line and "loss_impl was removed" in line and "compile" in line
    assert TrainConfig(policy_std="state").policy_std == "state"  # one loss takes both stds


def test_a_replay_ratio_band_reaches_the_limiter():
    fixed = parse([]).rate_limiter().stats()
    assert fixed["max_samples_per_insert"] == fixed["samples_per_insert"] == 16.0
    band = parse(["--max-replay-ratio", "48"]).rate_limiter().stats()
    assert (band["samples_per_insert"], band["max_samples_per_insert"]) == (16.0, 48.0)


def test_shared_memory_is_for_the_replay_the_learner_and_the_router_never_the_actors():
    import json

    from tpdeb.services.config.service import (
        ActorServiceConfig,
        EvaluatorServiceConfig,
        LearnerServiceConfig,
        RouterConfig,
    )
    from tpdeb.services.net.session import zenoh_config

    for cls in (ReplayServiceConfig, LearnerServiceConfig, RouterConfig):
        assert cls().shared_memory is False, cls  # off unless asked for
        assert cls(shared_memory=True).shared_memory is True
    for cls in (ActorServiceConfig, EvaluatorServiceConfig):
        assert not hasattr(cls(), "shared_memory"), cls  # no setting that could turn it on
    for on in (False, True):
        conf = zenoh_config("client", [], ["tcp/127.0.0.1:7447"], shared_memory=on)
        assert json.loads(conf.get_json("transport/shared_memory/enabled")) is on
    assert json.loads(zenoh_config("client", [], []).get_json(
        "transport/shared_memory/enabled")) is False  # off unless asked for
