"""Soak benchmark: does any service's memory, the replay's disk use, the env steps/s or the
learner's update time keep drifting over a long cluster run?

    python bench/soak.py --minutes 60 --out docs/data/soak-60.json   # an hour, HalfCheetah
    python bench/soak.py                                   # 10 min (deploy/local.toml)
    python bench/soak.py --minutes 3 --warmup-minutes 1    # a quick check of the script

Starts `tpdeb-cluster` with the cluster file (default deploy/local.toml) in a temporary run
dir, with `--total-timesteps` far beyond what the soak can reach, and every `--interval-s`
reads VmRSS of every process under the cluster from /proc. Services are told apart by their
command lines (tpdeb-router, tpdeb-replay, tpdeb-learner, tpdeb-actor --actor-id N, tpdeb-link;
the cluster itself is `cluster`), so the script follows whatever the cluster starts; a service
whose pid changes was restarted and is reported as such. Beside each process's RSS, three
gauges are sampled the same way and judged by the same rule: the replay's disk use (its
write-ahead log and snapshots), env steps/s (from the learner's progress lines) and the
learner's mean update time (`perf/update_ms`, the last row of metrics.jsonl).

After `--warmup-minutes` (buffers filling, allocator pools growing) each service is judged:
warm-up RSS = median of the first minute after warm-up, final RSS = median of the last minute,
drift = final vs warm-up, PASS when |drift| ≤ `--tolerance-pct` (5 %). The gauges are judged
the same way over five minutes (at most a quarter of the soak after warm-up): they vary by more
than that from one minute to the next, and the disk is a sawtooth cut at every snapshot.
`--rejudge RESULT.json` judges a saved soak's series again by today's rule, measuring nothing,
and adds that verdict beside the earlier ones (`verdicts`, each with its rule's version; the
run's own verdict stays in `summary`, `result` and `table_markdown`). At the end the
cluster gets SIGINT (its graceful stop: checkpoint, snapshot), the script waits for it and
checks that no process of the run is left. The series goes to `--out` (JSON) and a markdown table is
printed. Exit status 1 on a FAIL, a restart, an early exit or a process left behind.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import re
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import provenance
from procfs import SERVICES, cmdline, descendants, proc_table, rss_kib, service_name

ROOT = Path(__file__).resolve().parents[1]
WINDOW_S = 60.0  # a service's warm-up and final RSS are medians over one minute each
# A gauge's references are medians over up to five minutes: env steps/s and update times vary
# by several percent from one minute to the next, and the replay's disk is a sawtooth (its log
# grows and is cut at each snapshot), whose one-minute median depends on where the minute falls.
GAUGE_WINDOW_S = 300.0
GAUGES = ("replay disk (MiB)", "env steps/s", "update (ms)")  # sampled beside the RSS
RULE = "bench/soak.py:verdict"
RULE_VERSION = 2  # 1: every series' references over one minute; 2: a gauge's over five
PROGRESS = re.compile(r"^\[learner\] tpdeb-learner: \[\s*([\d,]+)/[\d,]+\]")


def say(text: str) -> None:
    print(f"[soak] {text}", flush=True)


class Sampler:
    """RSS of the cluster and every service under it, by service name; a name whose pid
    changes is a restart."""

    def __init__(self, cluster_pid: int, t0: float):
        self.cluster_pid, self.t0 = cluster_pid, t0
        self.series: dict[str, list[tuple[float, float]]] = {}  # name -> [(s, MiB)]
        self.pids: dict[str, list[int]] = {}
        self.seen: dict[int, tuple[int, str]] = {}  # pid -> (start ticks, name), for the end
        self.names: dict[int, str] = {}

    def sample(self) -> dict[str, float]:
        now = time.monotonic() - self.t0
        table = proc_table()
        current: dict[str, float] = {}
        for pid in [self.cluster_pid, *descendants(self.cluster_pid, table)]:
            if pid not in table:
                continue
            if pid not in self.names:
                name = "cluster" if pid == self.cluster_pid else service_name(cmdline(pid))
                if name is None:  # a helper under a service: kept apart, under its parent
                    parent = self.names.get(table[pid][0], "unknown")
                    name = f"{parent}/{Path(cmdline(pid)[0] or '?').name}"
                self.names[pid] = name
                self.seen[pid] = (table[pid][1], name)
                pids = self.pids.setdefault(name, [])
                if pid not in pids:
                    pids.append(pid)
            kib = rss_kib(pid)
            if kib is not None:
                name = self.names[pid]
                current[name] = current.get(name, 0.0) + kib / 1024
        for name, mib in current.items():
            self.series.setdefault(name, []).append((round(now, 2), round(mib, 2)))
        return current

    def restarts(self) -> dict[str, int]:
        return {name: len(pids) - 1 for name, pids in self.pids.items() if len(pids) > 1}

    def left_over(self, run_dir: Path) -> list[tuple[int, str]]:
        """Processes seen during the soak that still run (same pid and start time), and any
        whose command line names the run dir (started after the last sample)."""
        table = proc_table()
        left = {pid: name for pid, (start, name) in self.seen.items()
                if pid in table and table[pid][1] == start}
        for pid in table:
            if pid not in left and pid != os.getpid() and str(run_dir) in " ".join(cmdline(pid)):
                left[pid] = service_name(cmdline(pid)) or "unknown"
        return sorted(left.items())


def gauges(run_dir: Path, progress: list[tuple[float, int]]) -> dict[str, float]:
    """The replay's disk use, env steps/s over the last two progress lines, the learner's
    latest mean update time; each only once there is something to read."""
    out = {}
    replay = run_dir / "replay"
    if replay.is_dir():
        out[GAUGES[0]] = sum(f.stat().st_size for f in replay.rglob("*")
                                       if f.is_file()) / 2**20
    if len(progress) >= 2 and progress[-1][0] > progress[-2][0]:
        (t0, s0), (t1, s1) = progress[-2:]
        out[GAUGES[1]] = (s1 - s0) / (t1 - t0)
    with contextlib.suppress(OSError), (run_dir / "metrics.jsonl").open("rb") as f:
        f.seek(max(0, f.seek(0, os.SEEK_END) - 65536))
        for line in reversed(f.read().decode(errors="replace").splitlines()):
            if '"perf/update_ms"' in line:
                with contextlib.suppress(ValueError):
                    out[GAUGES[2]] = float(json.loads(line)["perf/update_ms"])
                break
    return out


# ----------------------------------------------------------------------------- verdict

def judge(series: list[tuple[float, float]], warmup_s: float, end_s: float,
          tolerance_pct: float, window_s: float = WINDOW_S) -> dict:
    after = [(t, v) for t, v in series if t >= warmup_s]
    first = [v for t, v in after if t < warmup_s + window_s]
    last = [v for t, v in after if t >= end_s - window_s]
    if not first or not last:
        return {"result": "FAIL", "why": "no samples after warm-up / in the last window",
                "samples": len(after)}
    warm, final = statistics.median(first), statistics.median(last)
    drift = 100 * (final - warm) / warm
    return {"warmup_mib": warm, "min_mib": min(v for _, v in after),
            "max_mib": max(v for _, v in after), "final_mib": final, "drift_pct": drift,
            "samples": len(after), "window_s": window_s,
            "result": "PASS" if abs(drift) <= tolerance_pct else "FAIL"}


def window_of(name: str, warmup_s: float, end_s: float) -> float:
    """The reference window of a series: a minute for RSS; for a gauge up to five minutes, at
    most a quarter of the soak after warm-up (never less than a minute)."""
    if name not in GAUGES:
        return WINDOW_S
    return max(WINDOW_S, min(GAUGE_WINDOW_S, (end_s - warmup_s) / 4))


def failing(summary: dict) -> list[str]:
    """The series of a judged soak that did not pass."""
    return [n for n, s in summary.items() if s["result"] != "PASS"]


def verdict(results: dict) -> dict:
    """Every series of `results` (its meta, series, problems and restarts) judged by today's
    rule: the summary per series, the result, the reasons it fails and the table."""
    meta, warmup_s = results["meta"], 60 * results["meta"]["warmup_minutes"]
    end_s, tolerance = meta["soak_s"], meta["tolerance_pct"]
    summary = {n: judge(v, warmup_s, end_s, tolerance, window_of(n, warmup_s, end_s))
               for n, v in results["series"].items()}
    reasons = [f"{n}: drift {summary[n]['drift_pct']:+.1f} % beyond ±{tolerance:g} %"
               if "drift_pct" in summary[n] else f"{n}: {summary[n]['why']}"
               for n in failing(summary)] + list(results["problems"])
    return {"summary": summary, "result": "FAIL" if reasons else "PASS", "reasons": reasons,
            "table_markdown": render(summary, results["restarts"], tolerance)}


def add_verdict(results: dict, judged: dict, rejudged: bool) -> dict:
    """Today's rule's verdict beside the file's others. The run's own verdict's summary and
    table are the file's `summary` and `table_markdown`; a later one keeps its own."""
    if not rejudged:
        return provenance.add_verdict(results, RULE, RULE_VERSION, judged["result"] == "PASS",
                                      judged["reasons"], note="the run's own")
    return provenance.add_verdict(results, RULE, RULE_VERSION, judged["result"] == "PASS",
                                  judged["reasons"], note="judged again from the saved series",
                                  details={"summary": judged["summary"],
                                           "table_markdown": judged["table_markdown"]})


def render(summary: dict[str, dict], restarts: dict[str, int], tolerance_pct: float) -> str:
    lines = [f"| service RSS (MiB) or gauge | warm-up | min | max | final | drift % | "
             f"±{tolerance_pct:g} % |", "|---|---:|---:|---:|---:|---:|---|"]
    for name, s in summary.items():
        if "drift_pct" not in s:
            lines.append(f"| {name} | | | | | | FAIL ({s['why']}) |")
            continue
        note = f" (restarted {restarts[name]}×)" if name in restarts else ""
        lines.append(f"| {name} | {s['warmup_mib']:,.1f} | {s['min_mib']:,.1f} | "
                     f"{s['max_mib']:,.1f} | {s['final_mib']:,.1f} | {s['drift_pct']:+.1f} | "
                     f"{s['result']}{note} |")
    return "\n".join(lines)


def figure(results: dict, path: Path) -> None:
    """Every series against minutes: the services' RSS against each one's warm-up reference
    (in percent), then each gauge with its warm-up reference; the ± tolerance band green, the
    warm-up grey."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from tpdeb.services.plot import save

    meta, series, summary = results["meta"], results["series"], results["summary"]
    gauge_names = [n for n in GAUGES if n in series]
    rss_names = [n for n in series if n not in GAUGES]
    fig, axes = plt.subplots(2, 2, figsize=(10, 6.4), sharex=True)
    tol = meta["tolerance_pct"]
    ax = axes[0][0]  # every service's RSS against its own warm-up reference, in percent
    reach = 2 * tol  # the y range: the band twice over, or what the soak after warm-up reached
    for n, name in enumerate(rss_names):
        ref = summary.get(name, {}).get("warmup_mib")
        if ref:
            pct = [(t / 60, 100 * (v / ref - 1)) for t, v in series[name]]
            ax.plot(*zip(*pct, strict=True), color=f"C{n}", lw=1,
                    label=f"{name} ({ref:,.0f} MiB)")
            reach = max([reach] + [abs(p) for m, p in pct if m >= meta["warmup_minutes"]])
    ax.axhspan(-tol, tol, color="C2", alpha=0.15)
    ax.set_ylim(-1.2 * reach, 1.2 * reach)
    panels = [(ax, f"RSS vs warm-up (%, ±{tol:g} % shaded)")]
    for ax, name in zip([axes[0][1], axes[1][0], axes[1][1]], gauge_names, strict=False):
        ax.plot([t / 60 for t, _ in series[name]], [v for _, v in series[name]], lw=1,
                label=name)
        ref = summary.get(name, {}).get("warmup_mib")
        if ref is not None:
            ax.axhspan(ref * (1 - tol / 100), ref * (1 + tol / 100), color="C2", alpha=0.15,
                       label=f"warm-up ± {tol:g} %")
        panels.append((ax, name))
    for ax, ylabel in panels:
        ax.axvspan(0, meta["warmup_minutes"], color="grey", alpha=0.15)
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, ncol=2)
    for ax in axes[1]:
        ax.set_xlabel("minutes (warm-up shaded)")
    fig.suptitle(f"soak: {meta['minutes']:g} min, {Path(meta['config']).name} "
                 f"({results['result']})")
    save(fig, path)


def rejudge(path: Path, png: Path | None, parser) -> int:
    """--rejudge: the verdict of a saved soak by today's rule, from its series (nothing is
    measured), added beside the verdicts the file holds unless this rule's version has judged
    it already; the run's own verdict and every earlier one are kept as they are."""
    try:
        results = json.loads(path.read_text())
        judged = verdict(results)
        if png is not None:
            figure({**results, **judged}, png)
    except (OSError, ValueError, KeyError, TypeError) as exc:
        parser.error(f"--rejudge {path}: not a soak result this script wrote ({exc!r})")
    print(judged["table_markdown"])
    done = [v for v in results.get("verdicts", [])
            if v["rule"] == RULE and v["rule_version"] == RULE_VERSION]
    if done:
        say(f"{done[-1]['verdict']} by rule version {RULE_VERSION}, already in {path}; "
            "nothing written")
    else:
        add_verdict(results, judged, rejudged=True)
        path.write_text(json.dumps(results, indent=1))
        provenance.written(path)
        say(f"{judged['result']} by rule version {RULE_VERSION}"
            + (f" ({'; '.join(judged['reasons'])})" if judged["reasons"] else "")
            + f"; added to {path}'s verdicts" + (f", figure in {png}" if png else ""))
    return 0 if judged["result"] == "PASS" else 1


def order(name: str) -> tuple:
    role = name.split("-")[0].split("/")[0]
    return (SERVICES.index(role) if role in SERVICES else len(SERVICES), name)


# ----------------------------------------------------------------------------- the run

def cluster_command() -> list[str]:
    script = Path(sys.executable).parent / "tpdeb-cluster"  # a venv needs no activation
    return [str(script)] if script.exists() else [sys.executable, "-m", "tpdeb.services.cluster"]


def stop_cluster(proc: subprocess.Popen, timeout_s: float) -> int | None:
    """SIGINT (the cluster's graceful stop), then SIGKILL to its group if it hangs."""
    if proc.poll() is None:
        with contextlib.suppress(ProcessLookupError):
            proc.send_signal(signal.SIGINT)
        try:
            return proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            say(f"the cluster did not stop within {timeout_s:g} s of SIGINT: killing it")
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
            return None
    return proc.returncode


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--minutes", type=float, default=10.0, help="length of the soak")
    p.add_argument("--warmup-minutes", type=float, default=2.0,
                   help="start-up time excluded from the verdict")
    p.add_argument("--interval-s", type=float, default=5.0, help="seconds between RSS samples")
    p.add_argument("--tolerance-pct", type=float, default=5.0,
                   help="largest |final − warm-up| drift that passes, in percent")
    p.add_argument("--cluster-file", default=str(ROOT / "deploy" / "local.toml"),
                   help="cluster file")
    p.add_argument("--total-timesteps", type=int, default=100_000_000,
                   help="the run's length: far beyond what the soak reaches, so it never ends")
    p.add_argument("--stop-timeout-s", type=float, default=120.0,
                   help="how long the cluster may take to stop after SIGINT")
    p.add_argument("--out", default=str(ROOT / "docs" / "data" / "soak.json"))
    p.add_argument("--keep-run-dir", action="store_true",
                   help="keep the temporary run dir (it is always kept when the soak fails)")
    p.add_argument("--figure", type=Path,
                   help="also draw the series into this PNG (needs the plot extra)")
    p.add_argument("--rejudge", type=Path, metavar="JSON",
                   help="run nothing: judge this soak's series again by today's rule (the "
                        "file is updated) and draw --figure from it")
    p.add_argument("cluster_args", nargs="*",
                   help="more tpdeb-cluster flags after --, e.g. -- --env-id Hopper-v5")
    args = p.parse_args()
    if args.rejudge is not None:
        return rejudge(args.rejudge, args.figure, p)
    if args.minutes - args.warmup_minutes < 2 * WINDOW_S / 60:
        p.error(f"--minutes {args.minutes:g} with --warmup-minutes {args.warmup_minutes:g} "
                "leaves less than 2 minutes after warm-up (one for each reference median)")
    if args.interval_s <= 0 or args.interval_s * 3 > WINDOW_S:
        p.error(f"--interval-s {args.interval_s:g}: must be > 0 and ≤ {WINDOW_S / 3:g} (at least "
                "3 samples in each reference minute)")

    record = provenance.start()
    run_dir = Path(tempfile.mkdtemp(prefix="tpdeb-soak-"))
    argv = [*cluster_command(), "--cluster-file", args.cluster_file, "--total-timesteps",
            str(args.total_timesteps), "--run-dir", str(run_dir), *args.cluster_args]
    log_path = run_dir / "cluster-stdout.log"
    duration_s, warmup_s = 60 * args.minutes, 60 * args.warmup_minutes
    say(f"{args.minutes:g} min soak ({args.warmup_minutes:g} min warm-up), RSS every "
        f"{args.interval_s:g} s; {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}")
    say(f"$ {' '.join(argv)}")
    started = time.strftime("%Y-%m-%d %H:%M:%S")
    t0 = time.monotonic()
    log = log_path.open("w", buffering=1)  # line by line: readable while the soak runs
    proc = subprocess.Popen(argv, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            stdin=subprocess.DEVNULL, text=True, bufsize=1,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"}, start_new_session=True)
    progress: list[tuple[float, int]] = []  # (s, learner global step)

    def read_output() -> None:
        for line in proc.stdout:
            log.write(line)
            if (m := PROGRESS.search(line)) is not None:
                progress.append((round(time.monotonic() - t0, 2), int(m.group(1).replace(",", ""))))

    reader = threading.Thread(target=read_output, daemon=True, name="cluster-stdout")
    reader.start()
    sampler = Sampler(proc.pid, t0)
    problems: list[str] = []
    tty = sys.stdout.isatty()
    last_line = -1e9
    exit_code = None
    try:
        while (elapsed := time.monotonic() - t0) < duration_s:
            if proc.poll() is not None:
                problems.append(f"the cluster exited with code {proc.returncode} after "
                                f"{elapsed:.0f} s (see {log_path})")
                break
            current = sampler.sample()
            for name, value in gauges(run_dir, progress).items():
                sampler.series.setdefault(name, []).append((round(elapsed, 2), round(value, 3)))
            if tty or elapsed - last_line >= 60:
                last_line = elapsed
                phase = "warm-up" if elapsed < warmup_s else "soak"
                step = f" | step {progress[-1][1]:,}" if progress else ""
                rss = " | ".join(f"{n} {v:,.0f}" for n, v in sorted(current.items(),
                                                                    key=lambda kv: order(kv[0])))
                text = (f"[soak] {int(elapsed) // 60}:{int(elapsed) % 60:02d}/"
                        f"{int(duration_s) // 60}:{int(duration_s) % 60:02d} {phase}{step} | "
                        f"RSS MiB: {rss}")
                print(("\r\033[K" + text) if tty else text, end="" if tty else "\n", flush=True)
            time.sleep(max(0.0, args.interval_s - (time.monotonic() - t0 - elapsed)))
    except KeyboardInterrupt:
        problems.append("interrupted")
    finally:
        if tty:
            print()
        end_s = time.monotonic() - t0
        say("stopping the cluster (SIGINT)…")
        exit_code = stop_cluster(proc, args.stop_timeout_s)
        stopped_s = time.monotonic() - t0 - end_s
        reader.join(10)
        log.close()
        left = sampler.left_over(run_dir)
        for pid, _ in left:  # ours: seen under this run's cluster, same start time
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
    if exit_code not in (0, 130):
        problems.append(f"the cluster's exit code after SIGINT was {exit_code} (expected 130)")
    if left:
        problems.append(f"processes left after the cluster stopped (killed): {left}")
    restarts = sampler.restarts()
    if restarts:
        problems.append(f"services restarted during the soak: {restarts}")

    names = sorted(sampler.series, key=order)
    results = {
        "meta": {"started": started, "minutes": args.minutes,
                 "warmup_minutes": args.warmup_minutes, "interval_s": args.interval_s,
                 "tolerance_pct": args.tolerance_pct, "window_s": WINDOW_S,
                 "gauge_window_s": GAUGE_WINDOW_S,
                 "cpu_count": os.cpu_count(), "loadavg_end": os.getloadavg(),
                 "command": argv, "config": args.config, "soak_s": end_s,
                 "stop_s": stopped_s, "exit_code": exit_code},
        "restarts": restarts, "pids": sampler.pids,
        "series": {n: sampler.series[n] for n in names}, "learner_steps": progress,
        "problems": problems}
    judged = verdict(results)
    results.update(summary=judged["summary"], result=judged["result"],
                   table_markdown=judged["table_markdown"])
    provenance.stamp(results, record)
    add_verdict(results, judged, rejudged=False)
    failed, table = failing(judged["summary"]), judged["table_markdown"]
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=1))
    provenance.written(out)

    print()
    print(table)
    print()
    if progress:
        say(f"learner reached step {progress[-1][1]:,} in {end_s / 60:.1f} min")
    say(f"cluster stopped in {stopped_s:.1f} s with code {exit_code}; "
        f"{'no process left' if not left else f'{len(left)} process(es) left and killed'}")
    for problem in problems:
        say(f"problem: {problem}")
    say(f"series in {out}")
    if args.figure is not None:
        figure(results, args.figure)
        say(f"figure in {args.figure}")
    if failed or problems:
        say(f"FAIL ({', '.join(failed) or 'see the problems above'}); run dir kept: {run_dir}")
        return 1
    if args.keep_run_dir:
        say(f"run dir kept: {run_dir}")
    else:
        shutil.rmtree(run_dir, ignore_errors=True)
    say("PASS")
    return 0


if __name__ == "__main__":
    sys.exit(main())
