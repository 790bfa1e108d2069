"""One way to give settings, for every command that trains or serves: each setting by its flag,
by `--set key=value`, in a settings file by `--config` and as a TPDEB_* variable; the cluster file
by `--cluster-file`. A name that is no setting is refused in one line with the closest one, and
every setting is checked before anything starts: no run dir, no process."""

import dataclasses
import sys
from pathlib import Path

import pytest

from tpdeb.services import cluster, serial
from tpdeb.services.config import ConfigError, resolve, to_toml
from tpdeb.services.config.service import SERVICE_CONFIGS, LearnerServiceConfig
from tpdeb.services.config.train import TrainConfig
from tpdeb.services.launcher.plan import DEFAULT_FILE, make_plan

ENV = "InvertedPendulum-v5"


def plan(*argv: str):
    return make_plan(cluster.parse_args(list(argv)))


def one_line(capsys) -> str:
    captured = capsys.readouterr()
    lines = (captured.err + captured.out).strip().splitlines()
    assert len(lines) == 1, lines
    return lines[0]


@pytest.mark.parametrize("command", ["tpdeb-train", "tpdeb-learner", "tpdeb-cluster"])
def test_a_setting_is_given_the_same_ways_to_every_command(command, tmp_path, monkeypatch):
    file = tmp_path / "settings.toml"
    file.write_text("[loss]\nvtrace_lambda = 0.7\n[replay]\nzeta = 0.4\n")
    monkeypatch.setenv("TPDEB_GAMMA", "0.95")
    argv = ["--config", str(file), "--set", "learning_rate=1e-3", "--algo", "tpdeb",
            "--device", "cpu", "--env-id", ENV, "--set", "zeta=0.3"]
    if command == "tpdeb-cluster":
        config = plan(*argv).train
    else:
        cls = TrainConfig if command == "tpdeb-train" else LearnerServiceConfig
        config = resolve(cls, argv, command, "")
    assert (config.learning_rate, config.vtrace_lambda, config.gamma, config.zeta) == (
        pytest.approx(1e-3), pytest.approx(0.7), pytest.approx(0.95), pytest.approx(0.3))
    assert (config.algo, config.device, config.env_id) == ("tpdeb", "cpu", ENV)


def test_every_training_setting_is_a_flag_of_the_cluster():
    names = {f.name for f in dataclasses.fields(TrainConfig)}
    options = cluster.parse_args([])  # the flags parse; the values given are only those set
    assert not names & set(vars(options))
    train = plan("--algo", "impact", "--device", "cpu", "--vf-coef", "0.25",
                 "--eval-interval", "60s").train
    assert (train.algo, train.device, train.vf_coef, train.eval_every()) == (
        "impact", "cpu", 0.25, (0, 60.0))


@pytest.mark.parametrize("argv, fix", [
    (["--set", "learnin_rate=1e-3"], "did you mean 'learning_rate'"),
    (["--learnin-rate", "1e-3"], "did you mean '--learning-rate'"),
    (["--set", "learning_rate"], "expected KEY=VALUE"),
])
@pytest.mark.parametrize("main", [serial.main, cluster.main], ids=["train", "cluster"])
def test_a_name_that_is_no_setting_is_one_line_with_the_closest(main, argv, fix, capsys):
    assert exit_status(main, argv) == 2
    line = one_line(capsys)
    assert "error:" in line and fix in line, line


def exit_status(main, argv) -> int:
    """What a command's main returns, or the status argparse exits with."""
    try:
        return main(argv)
    except SystemExit as exit:
        return exit.code


@pytest.mark.parametrize("main", [serial.main, cluster.main], ids=["train", "cluster"])
def test_a_tpdeb_variable_that_names_no_setting_is_refused(main, monkeypatch, capsys):
    monkeypatch.setenv("TPDEB_LEARNIN_RATE", "1e-3")
    assert main(["--env-id", ENV]) == 2
    assert "did you mean 'TPDEB_LEARNING_RATE'" in one_line(capsys)


def test_the_deploy_files_own_variables_stay_legal(monkeypatch):
    for name in ("TPDEB_IMAGE", "TPDEB_ROUTER_HOST", "TPDEB_ACTORS_PER_NODE", "TPDEB_PASSWORD"):
        monkeypatch.setenv(name, "x")
    assert resolve(TrainConfig, ["--env-id", ENV], "p", "").env_id == ENV


def test_the_cluster_file_and_a_settings_file_each_have_their_flag(tmp_path, capsys):
    assert cluster.main(["--config", str(DEFAULT_FILE)]) == 2
    line = one_line(capsys)
    assert "is a cluster file" in line and "takes it as --cluster-file" in line
    settings = tmp_path / "train.toml"
    settings.write_text(to_toml(TrainConfig(env_id=ENV, seed=4)))
    assert cluster.main(["--cluster-file", str(settings)]) == 2
    assert "is a settings file" in one_line(capsys)
    # a run's recorded settings, given back with --config, on top of the default cluster file
    assert plan("--config", str(settings)).train.seed == 4
    with pytest.raises(ConfigError, match="is a cluster file"):
        resolve(TrainConfig, ["--config", str(DEFAULT_FILE)], "p", "")


@pytest.mark.parametrize("argv, message", [
    (["--set", "device=cuda"], "torch sees no CUDA device"),
    (["--seed", "-1"], "seed=-1: must be an integer in [0, 2^31)"),
    (["--env-id", "NoSuchEnv-v0"], "not a registered gymnasium environment"),
    (["--run-dir", "{file}/run"], "is a file, not a directory"),
    (["--run-dir", "/proc/tpdeb-run"], "cannot write there"),
])
@pytest.mark.parametrize("main", [serial.main, cluster.main], ids=["train", "cluster"])
def test_every_setting_is_checked_before_anything_starts(main, argv, message, tmp_path, capsys,
                                                          monkeypatch):
    if "cuda" in " ".join(argv):
        import torch

        if torch.cuda.is_available():
            pytest.skip("this machine has a GPU")
    monkeypatch.chdir(tmp_path)
    (tmp_path / "file").write_text("")
    argv = [a.replace("{file}", str(tmp_path / "file")) for a in argv]
    assert main(["--env-id", ENV, *argv] if "--env-id" not in argv else argv) == 2
    assert message in one_line(capsys)
    assert not (tmp_path / "runs").exists()  # no run dir was made


def test_a_service_that_refuses_its_configuration_stops_the_cluster_at_once(tmp_path):
    """Exit status 2 is a setting the service refuses: a restart would refuse it again."""
    import subprocess
    import time

    cluster_file = tmp_path / "cluster.toml"
    cluster_file.write_text(DEFAULT_FILE.read_text().replace(
        '[services.learner]\ncommand = "tpdeb-learner"\nreplicas = 1\ndepends_on = ["replay"]\n'
        'restart = "on-failure"\nargs = []',
        '[services.learner]\ncommand = "tpdeb-learner"\nreplicas = 1\ndepends_on = ["replay"]\n'
        f'restart = "on-failure"\nargs = ["--resume", "{tmp_path}/no-such.pt"]'))
    assert "no-such.pt" in cluster_file.read_text()
    started = time.monotonic()
    proc = subprocess.run(
        [sys.executable, "-m", "tpdeb.services.cluster", "--cluster-file", str(cluster_file),
         "--env-id", ENV, "--run-dir", str(tmp_path / "run"), "--actors", "1",
         "--eval-interval", "0"], capture_output=True, text=True, timeout=180,
        cwd=Path(__file__).resolve().parents[1])
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert "learner refused its configuration (exit status 2)" in proc.stdout
    assert "--resume" in proc.stdout and "no such checkpoint file" in proc.stdout
    assert "restarting" not in proc.stdout
    assert time.monotonic() - started < 60


def test_every_service_takes_set_and_refuses_a_typo_in_one_line(capsys):
    for role, cls in SERVICE_CONFIGS.items():
        with pytest.raises(ConfigError, match="did you mean"):
            resolve(cls, ["--set", "run_idd=x"], role, "")
    assert resolve(SERVICE_CONFIGS["actor"], ["--set", "zeta=0.5", "--set", "num_envs=3"],
                   "actor", "").num_envs == 3  # another service's setting is passed over


def test_every_flag_on_a_readme_command_line_is_one_that_command_takes():
    """A README command copied as it stands gets what it says: each of its flags exists."""
    import re

    from tpdeb.services import evaluate
    from tpdeb.services.config import build_parser

    def options(parser):
        return set(parser._option_string_actions)

    parsers = {
        "tpdeb-train": options(build_parser(TrainConfig, "tpdeb-train", "")),
        "tpdeb-cluster": options(cluster.build_parser()),
        "tpdeb-eval": options(evaluate.build_parser()),
        **{f"tpdeb-{role}": options(build_parser(cls, role, ""))
           for role, cls in SERVICE_CONFIGS.items()},
    }
    text = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    checked = 0
    for block in re.findall(r"```bash\n(.*?)```", text, re.S):
        for line in block.replace("\\\n", " ").splitlines():
            words = line.split("#")[0].split()
            command = next((Path(w).name for w in words if Path(w).name in parsers), None)
            if command is None:
                continue
            flags = [w.strip("[]").split("=")[0] for w in words if w.lstrip("[").startswith("--")]
            for flag in flags:
                assert flag in parsers[command], f"{command} {flag}: {line.strip()}"
                checked += 1
    assert checked > 20

