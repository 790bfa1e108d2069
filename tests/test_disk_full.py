"""A disk that refuses writes (ENOSPC) part-way: the run's metrics and TensorBoard events lose
only the rows written meanwhile, never end in half a line or record, say so once per outage and
carry on when space is back; a whole cluster on a tmpfs that fills for a while finishes."""

import errno
import logging
import os

import pytest

import tpdeb.services.store.diskio as diskio
from tpdeb.services.store.diskio import AppendFile, DiskGuard
from tpdeb.services.store.metrics import MetricsWriter, read_metrics


class FullDisk:
    """os.write for diskio: while `full`, each append gets half its bytes down, then ENOSPC."""

    def __init__(self):
        self.full, self._short = False, False
        self._real = os.write

    def __call__(self, fd, data):
        if not self.full:
            return self._real(fd, data)
        if not self._short:
            self._short = True
            return self._real(fd, bytes(data[: len(data) // 2]))
        self._short = False
        raise OSError(errno.ENOSPC, "No space left on device")


def refused_fsyncs(monkeypatch, full: bool) -> list[bool]:
    """The replay log's fsync raises ENOSPC while the returned flag's [0] is True."""
    import tpdeb.services.store.persistence as persistence

    real, flag = persistence.os.fsync, [full]

    def fsync(fd):
        if flag[0]:
            raise OSError(errno.ENOSPC, "No space left on device")
        real(fd)

    monkeypatch.setattr(persistence.os, "fsync", fsync)
    return flag


def test_an_append_the_disk_refuses_part_way_is_cut_back_off(tmp_path, monkeypatch):
    disk = FullDisk()
    monkeypatch.setattr(diskio.os, "write", disk)
    f = AppendFile(tmp_path / "rows")
    f.append(b"one\n")
    disk.full = True
    with pytest.raises(OSError, match="No space"):
        f.append(b"two, a longer line\n")
    disk.full = False
    f.append(b"three\n")
    f.close()
    assert (tmp_path / "rows").read_bytes() == b"one\nthree\n"


def test_the_guard_says_once_skips_until_the_retry_and_says_when_writes_work_again(caplog):
    now = [0.0]
    guard = DiskGuard("metrics rows", "/run/metrics.jsonl", logging.getLogger("t"), retry_s=5,
                      clock=lambda: now[0])
    calls = []

    def refused():
        calls.append(now[0])
        raise OSError(errno.ENOSPC, "No space left on device")

    with caplog.at_level(logging.INFO, "t"):
        assert not guard.attempt(refused)
        now[0] = 2.0
        assert not guard.attempt(refused)  # inside the retry interval: not even tried
        now[0] = 6.0
        assert not guard.attempt(refused)  # tried again, still full: no second line
        now[0] = 12.0
        assert guard.attempt(lambda: calls.append("ok"))
    assert calls == [0.0, 6.0, "ok"]
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 2
    assert "metrics rows not written: /run/metrics.jsonl: No space left on device" in lines[0]
    assert "takes writes again (3 skipped meanwhile)" in lines[1]


def test_metrics_and_events_survive_a_full_disk_and_resume(tmp_path, monkeypatch, caplog):
    disk = FullDisk()
    monkeypatch.setattr(diskio.os, "write", disk)
    writer = MetricsWriter(tmp_path, logging.getLogger("t"))
    writer.rows_guard.retry_s = writer.events_guard.retry_s = 0.0
    writer.log(100, {"charts/episodic_return": 1.0})
    writer.flush()
    disk.full = True
    with caplog.at_level(logging.INFO, "t"):
        for step in (200, 300):
            writer.log(step, {"charts/episodic_return": 2.0})
            writer.flush()  # refused: nothing raised, the run goes on
        disk.full = False
        writer.log(400, {"charts/episodic_return": 4.0})
        writer.close()
    assert [r["global_step"] for r in read_metrics(tmp_path / "metrics.jsonl")] == [100, 400]
    assert (tmp_path / "metrics.jsonl").read_bytes().endswith(b"\n")
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 2  # one per file, for the whole outage
    accumulator = pytest.importorskip(
        "tensorboard.backend.event_processing.event_accumulator")
    acc = accumulator.EventAccumulator(str(tmp_path))
    acc.Reload()
    assert [e.step for e in acc.Scalars("charts/episodic_return")] == [100, 400]


def test_a_cluster_whose_disk_fills_for_a_while_finishes_and_loses_nothing_acknowledged(
        procs, tmp_path):
    import re
    import subprocess
    import time

    disk = tmp_path / "disk"
    disk.mkdir()
    if os.geteuid() != 0 or subprocess.run(
            ["mount", "-t", "tmpfs", "-o", "size=32m", "tmpfs", str(disk)],
            capture_output=True).returncode != 0:
        pytest.skip("needs root and a tmpfs mount")
    try:
        run_dir = disk / "run"
        cluster = procs.spawn("cluster", "--env-id", "InvertedPendulum-v5", "--seed", "1",
                              "--total-timesteps", "60000", "--run-dir", str(run_dir))
        procs.wait_for_line(cluster, "[learner] tpdeb-learner: [", timeout_s=120)
        # unbuffered: the write that meets the full disk raises, and closing has nothing left
        # to flush (a buffered tail would raise again on close, outside pytest.raises)
        with (disk / "fill").open("wb", buffering=0) as f, pytest.raises(OSError, match="No space"):
            while True:  # the disk fills up, as a neighbour's job would fill it
                f.write(b"\0" * (1 << 20))
                f.flush()
        time.sleep(8)
        (disk / "fill").unlink()
        assert cluster.wait(180) == 0, procs.output(cluster)[-3000:]
        out = procs.output(cluster)
    finally:
        procs.stop_all()
        subprocess.run(["umount", "-l", str(disk)], check=False)
    for what in ("the write-ahead log cannot be written", "metrics rows not written"):
        assert out.count(what) <= 1, out  # said once per outage, if the outage reached it
    assert "write-ahead log cannot be written" in out and "takes writes again" in out, out
    assert "Traceback" not in out, out

    def total(pattern):
        return sum(int(n.replace(",", "")) for n in re.findall(pattern, out))

    acknowledged = total(r"([\d,]+) acknowledged")
    sent = total(r"([\d,]+) fragments sent")
    ingested = total(r"([\d,]+) steps ingested")  # said once, by the replay
    fragment_len = int(re.search(r"serving InvertedPendulum-v5 \(obs \d+, act \d+, T (\d+)\)",
                                 out).group(1))
    assert ingested % fragment_len == 0, ingested
    # Every acknowledged fragment is in; none is in twice. The actors stop first, so a fragment
    # whose ack was still on its way when they did is in without being counted acknowledged.
    assert acknowledged <= ingested // fragment_len <= sent, (acknowledged, ingested, sent)
