"""A crowd of actors against one replay server (bench/crowd.py, short): every actor's fragments
are acknowledged at a like rate. Acks once went out one batch each and a burst of them overflowed
the replay's send queue: the acks were dropped, the later actors' windows stayed full until their
resends and the first actor took nearly everything (5,565 fragments against 54 in 8 s)."""

import contextlib
import json
import os
import signal
import subprocess
import sys

from tests.procs import ROOT, pids_with
from tpdeb.services.launcher.plan import free_port


def test_a_crowd_of_actors_is_acknowledged_evenly(tmp_path):
    out, endpoint = tmp_path / "out", f"tcp/127.0.0.1:{free_port()}"
    # the resend comes too late to mend a lost ack within the run: what is acknowledged arrived
    cmd = [sys.executable, "bench/crowd.py", "--actors", "8", "--seconds", "6", "--no-flood",
           "--resend-after-s", "60", "--out", str(out), "--endpoint", endpoint]
    crowd = subprocess.Popen(cmd, cwd=ROOT, start_new_session=True, text=True,
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        printed, _ = crowd.communicate(timeout=180)
        assert crowd.returncode == 0, printed
    finally:
        for pid in [crowd.pid, *pids_with(endpoint)]:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        crowd.wait(10)
    result = json.loads((out / "results.json").read_text())
    acked = result["acked_per_actor"]
    assert len(acked) == 8 and min(acked) > 0, acked
    assert min(acked) >= 0.25 * max(acked), f"some actors starved: {acked}"
    assert result["learner_requests"] > 0 and result["learner_ready_fraction"] > 0
