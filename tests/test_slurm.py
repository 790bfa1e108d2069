"""deploy/slurm/tpdeb.sbatch on a real one-node Slurm: munged, slurmctld and slurmd started
here as root on this machine (their own ports, socket and state directory; stopped by pid when
the test ends), the batch script submitted with sbatch. The run learns to its end; a second
job, requeued while it trains, resumes in its run dir (learner checkpoint, replay snapshot),
and stopped with scancel stops cleanly (final checkpoint, replay snapshot)."""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.procs import ROOT, free_port

SBATCH = ROOT / "deploy" / "slurm" / "tpdeb.sbatch"
DAEMONS = ("munged", "slurmctld", "slurmd")
CLIENTS = ("sbatch", "squeue", "scancel", "scontrol", "srun", "sinfo")


def unavailable() -> str | None:
    if os.geteuid() != 0:
        return "needs root to run slurmctld and slurmd"
    missing = [tool for tool in (*DAEMONS, *CLIENTS) if shutil.which(tool) is None]
    if missing:
        return f"needs Slurm and munge (apt-get install slurm-wlm munge): {', '.join(missing)}"
    return None


SLURM_CONF = """\
ClusterName=tpdebtest
SlurmctldHost={host}(127.0.0.1)
SlurmctldPort={ctld_port}
SlurmdPort={d_port}
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket={dir}/munge/munge.sock
SlurmUser=root
SlurmdUser=root
StateSaveLocation={dir}/state
SlurmdSpoolDir={dir}/spool
SlurmctldPidFile={dir}/slurmctld.pid
SlurmdPidFile={dir}/slurmd.pid
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU
MpiDefault=none
ReturnToService=2
SchedulerType=sched/builtin
JobCompType=jobcomp/none
AccountingStorageType=accounting_storage/none
KillWait=30
NodeName={host} NodeAddr=127.0.0.1 CPUs={cpus} State=UNKNOWN
PartitionName=debug Nodes={host} Default=YES MaxTime=INFINITE State=UP OverSubscribe=YES
"""


@pytest.fixture
def slurm(tmp_path):
    """A one-node Slurm of this test's own; yields the environment its clients need."""
    why = unavailable()
    if why:
        pytest.skip(why)
    base = tmp_path / "slurm"
    for sub in ("state", "spool", "munge"):
        (base / sub).mkdir(parents=True)
    (base / "munge").chmod(0o700)
    key = base / "munge" / "munge.key"
    key.write_bytes(os.urandom(1024))
    key.chmod(0o400)
    host = socket.gethostname()
    conf = base / "slurm.conf"
    conf.write_text(SLURM_CONF.format(host=host, dir=base, ctld_port=free_port(),
                                      d_port=free_port(), cpus=os.cpu_count()))
    env = {**os.environ, "SLURM_CONF": str(conf),
           "PATH": f"{Path(sys.executable).parent}:{os.environ['PATH']}"}
    munge = base / "munge"
    started = [subprocess.Popen(
        ["munged", "--foreground", f"--socket={munge}/munge.sock", f"--key-file={key}",
         f"--pid-file={munge}/munged.pid", f"--log-file={munge}/munged.log",
         f"--seed-file={munge}/munged.seed", "--force"],
        stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT, start_new_session=True)]
    try:
        wait_for(lambda: (munge / "munge.sock").exists(), 10, "munged's socket")
        for daemon in ("slurmctld", "slurmd"):
            log = (base / f"{daemon}.log").open("w")
            started.append(subprocess.Popen([daemon, "-D"], env=env, stdout=log,
                                            stderr=subprocess.STDOUT, start_new_session=True))
        wait_for(lambda: "idle" in run(env, "sinfo", "-h", "-o", "%T").stdout, 60,
                 "an idle node (sinfo)")
        yield env
    finally:
        for proc in reversed(started):
            with_group(proc, signal.SIGTERM)
        for proc in reversed(started):
            try:
                proc.wait(20)
            except subprocess.TimeoutExpired:
                with_group(proc, signal.SIGKILL)
                proc.wait(10)


def with_group(proc: subprocess.Popen, sig: int) -> None:
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, sig)


def run(env: dict, *cmd: str) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=60)


def wait_for(ready, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if ready():
            return
        time.sleep(0.5)
    raise AssertionError(f"no {what} within {timeout_s:g} s")


def submit(env: dict, cwd: Path, **variables: str) -> str:
    try:
        socket.gethostbyname(socket.gethostname())
    except OSError:  # a machine whose own name does not resolve: the services use loopback
        variables["TPDEB_ROUTER_HOST"] = "127.0.0.1"
    exports = ",".join(["ALL", *(f"{k}={v}" for k, v in variables.items())])
    done = subprocess.run(["sbatch", "--parsable", "--nodes=1", f"--export={exports}",
                           str(SBATCH)], env=env, cwd=cwd, capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 0, done.stderr
    return done.stdout.strip().split(";")[0]


def finished(env: dict, job: str) -> bool:
    return not run(env, "squeue", "-h", "-j", job).stdout.strip()


def test_the_batch_script_runs_a_whole_run_and_stops_cleanly_on_scancel(slurm, tmp_path):
    common = {"TPDEB_ENV_ID": "InvertedPendulum-v5", "TPDEB_NUM_ENVS": "2"}
    # the first job with two replay shards and two learner ranks (tasks of the first node)
    job = submit(slurm, tmp_path, TPDEB_TOTAL_TIMESTEPS="20000", TPDEB_ACTORS_PER_NODE="2",
                 TPDEB_REPLAY_SHARDS="2", TPDEB_LEARNERS="2", **common)
    wait_for(lambda: finished(slurm, job), 300, f"end of job {job}")
    out = (tmp_path / f"tpdeb-{job}.out").read_text()
    run_dir = tmp_path / "runs" / f"tpdeb-{job}"
    logs = {p.stem: p.read_text() for p in (run_dir / "logs").glob("*.log")}
    assert "learner exited with 0" in out, out + "\n".join(logs.values())
    assert list((run_dir / "checkpoints").glob("final_*.pt"))
    assert "actor 0:" in logs["actors"] and "actor 1:" in logs["actors"]  # ids from the ranks
    assert "shard 0 of 2" in logs["replay"] and "shard 1 of 2" in logs["replay"]
    assert "rank 1 of 2" in logs["learner"], logs["learner"]
    assert (run_dir / "replay-1").is_dir() and (run_dir / "ranks" / "1").is_dir()
    assert "with TLS, user/password" in logs["router"]
    assert "stopped (SIGTERM)" in logs["router"]  # stopped by the script at the end
    mode = (run_dir / "security" / "users.txt").stat().st_mode & 0o777
    assert mode == 0o600

    job = submit(slurm, tmp_path, TPDEB_TOTAL_TIMESTEPS="5000000", **common)
    run_dir = tmp_path / "runs" / f"tpdeb-{job}"
    wait_for(lambda: "SPS" in read(run_dir / "logs" / "learner.log"), 180, "training")
    # Requeued (a preemption, a node failure): the same job id, run dir and run go on.
    assert run(slurm, "scontrol", "requeue", job).returncode == 0
    wait_for(lambda: run(slurm, "squeue", "-h", "-j", job, "-o", "%T").stdout.strip()
             in ("PENDING", "RUNNING"), 60, "the requeued job")
    run(slurm, "scontrol", "update", f"jobid={job}", "starttime=now")
    wait_for(lambda: "resumed from" in read(run_dir / "logs" / "learner.log"), 240,
             "the learner resuming")
    wait_for(lambda: read(run_dir / "logs" / "learner.log").count("SPS") >= 2, 120, "training")
    assert "restored" in read(run_dir / "logs" / "replay.log")
    assert run(slurm, "scancel", job).returncode == 0
    wait_for(lambda: finished(slurm, job), 120, f"end of cancelled job {job}")
    logs = {p.stem: p.read_text() for p in (run_dir / "logs").glob("*.log")}
    assert "stopped at" in logs["learner"] and "checkpoint" in logs["learner"], logs["learner"]
    assert "stopped (SIGTERM)" in logs["replay"], logs["replay"]
    assert list((run_dir / "checkpoints").glob("ckpt_*.pt"))  # cancelled: no final one
    assert list((run_dir / "replay").glob("snapshot-*/COMPLETE"))


def read(path: Path) -> str:
    return path.read_text() if path.is_file() else ""
