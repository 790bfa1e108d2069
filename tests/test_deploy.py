"""The launch files of deploy/: the Docker Compose file (validated by Debian's docker-compose, and
its services run here as the engine would start them: same commands, same variables, the
hostnames and volumes mapped onto this machine) and the image's Dockerfile."""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from tests.procs import ROOT, free_port

COMPOSE = ROOT / "deploy" / "docker-compose.yml"
ENV = "InvertedPendulum-v5"
_VARIABLE = re.compile(r"\$\{(\w+)(?::-([^}]*))?\}")


def compose_services(variables: dict[str, str]) -> dict:
    """The compose file's services with ${VAR:-default} substituted from `variables` (the
    shell's, as the engine does) and the YAML anchors merged."""
    text = _VARIABLE.sub(lambda m: variables.get(m[1], m[2] or ""), COMPOSE.read_text())
    return yaml.safe_load(text)["services"]


def test_the_compose_file_is_valid_for_docker_compose():
    if shutil.which("docker-compose") is None:
        pytest.skip("needs Debian's docker-compose (apt-get install docker-compose)")
    done = subprocess.run(["docker-compose", "-f", str(COMPOSE), "config", "-q"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr


def test_compose_starts_in_order_with_healthchecks_secrets_and_a_fixed_run_dir():
    services = compose_services({})
    order = {name: list(s.get("depends_on", {})) for name, s in services.items()}
    assert order == {"secrets": [], "router": ["secrets"], "replay": ["router"],
                     "replay-1": ["router"], "learner": ["replay"], "learner-1": ["replay"],
                     "actor": ["learner"]}
    for name, service in services.items():
        if name != "secrets":  # replay-1 and learner-1 are a replay's and a learner's
            role = name.split("-")[0]
            assert service["healthcheck"]["test"] == ["CMD", "tpdeb-health", role]
            assert "TPDEB_PASSWORD" not in service["environment"]  # files, not variables
    env = {name: s.get("environment", {}) for name, s in services.items()}
    # the second shard and rank only in the `scale` profile, each told which it is
    assert [n for n, s in services.items() if "profiles" in s] == ["replay-1", "learner-1"]
    assert (env["replay"]["TPDEB_SHARD"], env["replay-1"]["TPDEB_SHARD"]) == ("0", "1")
    assert (env["learner"]["TPDEB_RANK"], env["learner-1"]["TPDEB_RANK"]) == ("0", "1")
    assert str(env["actor"]["TPDEB_REPLAY_SHARDS"]) == str(env["learner-1"]["TPDEB_LEARNERS"]) \
        == "1"
    assert env["actor"]["TPDEB_ACTOR_ID"] == "auto"  # --scale needs no hand-made ids
    assert env["learner"]["TPDEB_RUN_DIR"] == env["replay"]["TPDEB_RUN_DIR"] == "/runs/compose"
    assert all(e.get("TPDEB_CONNECT", "tls/").startswith("tls/") for e in env.values())


def mapped(value, port: int, volumes: dict[str, Path], host: str):
    """A launch file's value as this machine runs it: the router's host name and the listen
    address on loopback, each volume's mount point (/secrets, /runs, …) a directory here."""
    if isinstance(value, list):
        return [mapped(v, port, volumes, host) for v in value]
    text = str(value).replace(f"{host}:7447", f"127.0.0.1:{port}")
    text = text.replace("0.0.0.0:7447", f"127.0.0.1:{port}").replace(f"{host},", "")
    return re.sub(r"(?<![\w/])/(secrets|runs|auth)\b", lambda m: str(volumes[m[1]]), text)


class Stack:
    """Processes started as an engine starts containers: a command and exactly its
    environment (this machine's, less any TPDEB_* variable, plus the container's)."""

    def __init__(self, procs, tmp: Path, host: str):
        self.procs, self.tmp, self.host, self.port = procs, tmp, host, free_port()
        self.base = {k: v for k, v in os.environ.items() if not k.startswith("TPDEB_")}
        self.bin = Path(sys.executable).parent

    def volumes(self, runs: str = "runs") -> dict[str, Path]:
        """Where the mount points live here (`runs`: the run directory's volume)."""
        return {"secrets": self.tmp / "secrets", "auth": self.tmp / "auth",
                "runs": self.tmp / runs}

    def env(self, env: dict, runs: str = "runs") -> dict:
        return {**self.base, **{k: mapped(v, self.port, self.volumes(runs), self.host)
                                for k, v in env.items()}}

    def start(self, name: str, command: list[str], env: dict, runs: str = "runs"):
        argv = mapped(command, self.port, self.volumes(runs), self.host)
        return self.procs.spawn_command([self.resolve(argv[0]), *argv[1:]], name, env)

    def resolve(self, command: str) -> str:
        local = self.bin / command
        return str(local) if local.exists() else shutil.which(command)

    def healthy(self, test: list[str], env: dict, timeout_s: float = 90.0) -> None:
        """Run the healthcheck until it passes, as the engine does before dependants start."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            done = subprocess.run([self.resolve(test[0]), *test[1:], "--timeout-s", "2"],
                                  env=env, capture_output=True, text=True, timeout=60)
            if done.returncode == 0:
                return
            time.sleep(0.5)
        raise AssertionError(f"{' '.join(test)} never passed: {done.stderr}")


def actor_ids(procs, actors) -> list[str]:
    return sorted(re.search(r"actor (\d+): \d+ × ", procs.output(a)).group(1) for a in actors)


def logged_bytes(replay_dir: Path) -> int:
    """The bytes in a replay server's log segments (one rotated away meanwhile counts 0)."""
    total = 0
    for segment in replay_dir.glob("wal-*.log"):
        with contextlib.suppress(FileNotFoundError):
            total += segment.stat().st_size
    return total


def test_the_compose_services_run_as_the_engine_would_start_them(procs, tmp_path):
    """Each service's command and environment from the compose file (two actors, as with
    --scale actor=2), started in its depends_on order, each waited for by its own healthcheck:
    the actors get distinct ids, a replay server killed and started again (as the engine
    restarts it) restores its fragments from the fixed run directory, and the run finishes."""
    services = compose_services({"TPDEB_ENV_ID": ENV, "TPDEB_TOTAL_TIMESTEPS": "40000",
                                 "TPDEB_NUM_ENVS": "2"})
    stack = Stack(procs, tmp_path, "router")
    envs = {name: stack.env(s.get("environment", {})) for name, s in services.items()}
    started = {}
    for name in ("secrets", "router", "replay", "learner"):
        started[name] = stack.start(name, services[name]["command"], envs[name])
        if name == "secrets":
            assert started[name].wait(60) == 0, procs.output(started[name])
        else:
            stack.healthy(services[name]["healthcheck"]["test"][1:], envs[name])
    actors = [stack.start(f"actor-{i}", services["actor"]["command"], envs["actor"])
              for i in range(2)]
    learner = started["learner"]
    # killed early in the run (a few thousand of its 40,000 steps logged), so that the run cannot
    # end before the restarted server's healthcheck has seen it up: the actors wait for acks
    # while it is down, so what is left after the restart is what was left at the kill
    logged = tmp_path / "runs" / "compose" / "replay"
    deadline = time.monotonic() + 120
    while logged_bytes(logged) < 150_000:
        assert time.monotonic() < deadline and learner.poll() is None, procs.output(learner)
        time.sleep(0.1)
    started["replay"].kill()
    started["replay"].wait(10)
    replay = stack.start("replay-restarted", services["replay"]["command"], envs["replay"])
    stack.healthy(services["replay"]["healthcheck"]["test"][1:], envs["replay"])
    assert learner.wait(240) == 0, procs.output(learner)
    assert "restored" in procs.output(replay), procs.output(replay)
    assert actor_ids(procs, actors) == ["0", "1"]
    assert list((tmp_path / "runs" / "compose" / "checkpoints").glob("final_*.pt"))
    assert "with TLS, user/password, access control" in procs.output(started["router"])


def test_the_dockerfile_pins_cpu_torch_runs_unprivileged_and_installs_every_command():
    text = (ROOT / "deploy" / "Dockerfile").read_text()
    makefile = (ROOT / "Makefile").read_text()
    pin = re.search(r"^TORCH_SPEC \?= (\S+)", makefile, re.M)[1]
    assert f"ARG TORCH_SPEC={pin}" in text  # one pin: a build argument changes it
    assert "download.pytorch.org/whl/cpu" in text and "python3 -m venv /opt/venv" in text
    assert re.search(r"^USER tpdeb$", text, re.M) and "useradd" in text
    assert "pip install ." in text
    ignored = (ROOT / ".dockerignore").read_text().split()
    assert {".venv", "runs", ".git"} <= set(ignored)


# -- Kubernetes

K8S = ROOT / "deploy" / "k8s"
K8S_VERSION = "1.31.0"  # the schema the manifests are held to (kubernetes-validate bundles it)


def manifests() -> list[Path]:
    return sorted(p for p in K8S.glob("*.yaml") if p.name != "kustomization.yaml")


def validate(*paths: Path) -> subprocess.CompletedProcess:
    tool = Path(sys.executable).parent / "kubernetes-validate"
    return subprocess.run([str(tool), "--strict", "--kubernetes-version", K8S_VERSION,
                           *map(str, paths)], capture_output=True, text=True, timeout=120)


def test_the_kubernetes_manifests_validate_offline_and_a_broken_one_does_not(tmp_path):
    done = validate(*manifests())
    assert done.returncode == 0, done.stdout + done.stderr
    broken = tmp_path / "actor.yaml"
    broken.write_text((K8S / "actor.yaml").read_text().replace("serviceName:", "serviceNam:"))
    assert validate(broken).returncode != 0


def k8s_objects() -> dict[str, dict]:
    found = {}
    for path in manifests():
        for doc in yaml.safe_load_all(path.read_text()):
            found[f"{doc['kind']}/{doc['metadata']['name']}"] = doc
    return found


def test_kustomize_lists_every_manifest_and_every_secret_tpdeb_certs_writes(tmp_path):
    kustomization = yaml.safe_load((K8S / "kustomization.yaml").read_text())
    assert sorted(kustomization["resources"]) == sorted(p.name for p in manifests())
    from tpdeb.services.net import certs

    assert certs.main([str(tmp_path / "secrets"), "--hosts", "tpdeb-router,localhost,127.0.0.1",
                       "--users", "replay,learner,actor"]) == 0
    files = kustomization["secretGenerator"][0]["files"]
    assert sorted(Path(f).name for f in files) == sorted(p.name for p in
                                                         (tmp_path / "secrets").iterdir()
                                                         if p.name != "ca.key")
    objects = k8s_objects()
    actors = objects["StatefulSet/tpdeb-actor"]["spec"]
    assert actors["serviceName"] == "tpdeb-actor" and "Service/tpdeb-actor" in objects
    config = objects["ConfigMap/tpdeb-config"]["data"]
    for role, count in (("replay", "TPDEB_REPLAY_SHARDS"), ("learner", "TPDEB_LEARNERS")):
        # a shard or a rank per pod ordinal, a volume each, as many as the run is told of
        spec = objects[f"StatefulSet/tpdeb-{role}"]["spec"]
        assert f"Service/{spec['serviceName']}" in objects
        assert str(spec["replicas"]) == config[count]
        (claim,) = spec["volumeClaimTemplates"]
        mounts = spec["template"]["spec"]["containers"][0]["volumeMounts"]
        assert {"name": claim["metadata"]["name"], "mountPath": "/runs"} in mounts
    group = objects["Service/tpdeb-learner"]["spec"]
    assert group["publishNotReadyAddresses"] and group["ports"][0]["port"] == 29500
    assert config["TPDEB_GROUP_ENDPOINT"] == "tpdeb-learner-0.tpdeb-learner:29500"


def pod_env(container: dict, config: dict, ordinal: int) -> dict[str, str]:
    env = dict(config) if container.get("envFrom") else {}
    for item in container.get("env", []):
        if "valueFrom" in item:  # the StatefulSet's pod-index label
            assert "pod-index" in item["valueFrom"]["fieldRef"]["fieldPath"]
            env[item["name"]] = str(ordinal)
        else:
            env[item["name"]] = item["value"]
    return env


def test_the_kubernetes_pods_run_as_the_cluster_would_start_them(procs, tmp_path):
    """Each pod's containers from the manifests — init container, command, ConfigMap and env,
    the actor id from the ordinal, a volume per claim — started in the order their probes
    allow, each waited for by its readiness probe: the run finishes with actors 0 and 1."""
    objects = k8s_objects()
    config = {**objects["ConfigMap/tpdeb-config"]["data"], "TPDEB_ENV_ID": ENV,
              "TPDEB_TOTAL_TIMESTEPS": "20000", "TPDEB_NUM_ENVS": "2"}
    from tpdeb.services.net import certs

    stack = Stack(procs, tmp_path, "tpdeb-router")
    assert certs.main([str(tmp_path / "secrets"), "--hosts", "tpdeb-router,localhost,127.0.0.1",
                       "--users", "replay,learner,actor"]) == 0
    (tmp_path / "auth").mkdir()

    def run_pod(kind: str, ordinal: int = 0, ready: bool = True):
        pod = objects[kind]["spec"]["template"]["spec"]
        name = kind.split("/")[1]
        runs = f"runs-{name}"  # each workload its own persistent volume
        for init in pod.get("initContainers", []):
            proc = stack.start(f"{name}-init", init["command"], stack.env({}, runs), runs)
            assert proc.wait(30) == 0, procs.output(proc)
        container = pod["containers"][0]
        env = stack.env({k: v for k, v in pod_env(container, config, ordinal).items()}, runs)
        proc = stack.start(f"{name}-{ordinal}", container["command"], env, runs)
        if ready:
            stack.healthy(container["readinessProbe"]["exec"]["command"], env)
        return proc

    router = run_pod("Deployment/tpdeb-router")
    run_pod("StatefulSet/tpdeb-replay")
    learner = run_pod("StatefulSet/tpdeb-learner")
    # podManagementPolicy Parallel: the actors start together
    actors = [run_pod("StatefulSet/tpdeb-actor", i, ready=False) for i in range(2)]
    assert learner.wait(240) == 0, procs.output(learner)
    assert actor_ids(procs, actors) == ["0", "1"]
    assert list((tmp_path / "runs-tpdeb-learner" / "k8s" / "checkpoints").glob("final_*.pt"))
    assert (tmp_path / "runs-tpdeb-replay" / "k8s" / "replay").is_dir()
    assert "with TLS, user/password, access control" in procs.output(router)
