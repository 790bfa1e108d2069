"""The bench scripts' cluster runner: a script stopped with SIGTERM stops its cluster too (the
cluster runs in a session of its own, so nothing else would reach it)."""

import contextlib
import os
import signal
import subprocess
import sys
import time

from tests.procs import ROOT, pids_with

SCRIPT = """
import sys
from pathlib import Path
sys.path.insert(0, {bench!r})
from runs import run_cluster
run_cluster("InvertedPendulum-v5", 10**9, 1, Path({run_dir!r}),
            ["--set", "preset=none", "--actors", "1"], Path({log!r}), 600)
"""


def test_a_script_stopped_with_sigterm_stops_its_cluster(tmp_path):
    run_dir, log = tmp_path / "run", tmp_path / "cluster.log"
    code = SCRIPT.format(bench=str(ROOT / "bench"), run_dir=str(run_dir), log=str(log))
    script = subprocess.Popen([sys.executable, "-c", code], cwd=ROOT, start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while "tpdeb-learner: run" not in (log.read_text() if log.exists() else ""):
            assert script.poll() is None and time.monotonic() < deadline, "cluster did not start"
            time.sleep(0.5)
        assert pids_with(str(run_dir)), "the cluster's services should be running"
        script.send_signal(signal.SIGTERM)
        assert script.wait(90) == 128 + signal.SIGTERM
        deadline = time.monotonic() + 30
        while pids_with(str(run_dir)) and time.monotonic() < deadline:
            time.sleep(0.5)
        assert pids_with(str(run_dir)) == []
    finally:
        for pid in [script.pid, *pids_with(str(run_dir))]:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        script.wait(10)
