"""The race: the best policy each system gives in 15 minutes of wall-clock on this machine.

    python bench/race.py --sitting --envs Hopper-v5   # one task's race in one sitting: TPDEB
                                         # seeds 11-15 and the peers (seed 11) interleaved
    python bench/race.py                 # TPDEB alone: the six tasks × seeds 11-15
    python bench/race.py --peers         # the peers alone (SB3 SAC and PPO with the zoo's
                                         # settings, CleanRL's SAC), seed 11, six tasks
    python bench/race.py --report        # RESULTS' race table and docs/img/race/*.png
    python bench/race.py --envs Hopper-v5 --seeds 1 --minutes 5 --tag race-tune/NAME \\
        --set learning_rate=3e-4         # a tuning run of the race preset (seeds 1-3 only)

A race is run as a race with `--sitting`: for each task, its TPDEB seeds and its peers' runs one
after the other in one sitting (one session's machine: 5 TPDEB seeds and the three peers are ~130
minutes), interleaved — TPDEB seed, SB3 SAC, SB3 PPO, CleanRL SAC, TPDEB seed, … — so that a change
of the machine's speed meets every system. Before each run the plain one-core acting loop (the
task's vector env and a fresh policy in numpy, nothing else; `calibrate`) is timed for 10 s, and
the run records that figure, its sitting (`--sitting-name`, default the UTC date and the machine's
boot id) and the machine, so runs of different sittings can be told apart and compared by their
calibration.

Each TPDEB run is a `tpdeb-cluster` with `--train-for-seconds` (the learner's clock, which
starts with its loop: actors starting and the replay filling count) on `preset = auto`, as a
user starts it, so with a clock budget the task's race preset (`deploy/presets/race/{env}.toml`
where there is one, else its per-step preset), and a periodic checkpoint every minute, all kept.
Its training curve is put on the clock through the learner's progress rows
(`perf/train_elapsed_s`, every 10 s); the checkpoint last written before each mark (5, 10
minutes; the final one for 15) is evaluated for 10 deterministic episodes. Each peer run is
`bench/peers.py`. Nothing else may run on the machine meanwhile: these are timings.

Resumable run by run: each finished run leaves docs/data/{tag}/{system}/{env}__{seed}.json
(episodes as (seconds, steps, return), and per mark the steps, the training return — the mean of
the episodes ending in the last 10 % of the time to the mark — and the evaluation); a run whose
file exists is skipped. Run dirs and logs go to bench/out/ (not kept).
"""

from __future__ import annotations

import argparse
import bisect
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import provenance  # noqa: E402
from paper import TASKS, evaluate  # noqa: E402
from runs import ROOT, read_run_metrics, run_cluster, save_json  # noqa: E402

DATA = ROOT / "docs" / "data"
OUT = ROOT / "bench" / "out"
REPORT_SEEDS = (11, 12, 13, 14, 15)
PEER_SEEDS = (11,)
PEERS = ("sb3-sac", "sb3-ppo", "cleanrl-sac")
CALIBRATION_S = 10.0
NEVER = 10**9  # total_timesteps of a race run: the clock is what ends it


def result_path(tag: str, system: str, env_id: str, seed: int) -> Path:
    return DATA / tag / system / f"{env_id}__{seed}.json"


def on_the_clock(rows: list[dict]) -> list[tuple[float, int, float]]:
    """The run's episodes as (training seconds, steps, return): each episode's time is
    interpolated between the learner's progress rows (steps, training seconds)."""
    clock = sorted((r["global_step"], r["perf/train_elapsed_s"]) for r in rows
                   if "perf/train_elapsed_s" in r)
    if not clock:
        return []
    steps = [s for s, _ in clock]
    out = []
    for r in rows:
        if "charts/episodic_return" not in r:
            continue
        step = r["global_step"]
        i = bisect.bisect_left(steps, step)
        if i == 0:
            t = clock[0][1] * (step / steps[0] if steps[0] else 1.0)
        elif i == len(steps):
            t = clock[-1][1]
        else:
            (s0, t0), (s1, t1) = clock[i - 1], clock[i]
            t = t0 + (t1 - t0) * ((step - s0) / (s1 - s0) if s1 > s0 else 1.0)
        out.append((round(t, 2), int(step), round(float(r["charts/episodic_return"]), 2)))
    return out


def return_at(episodes: list, mark: float) -> float:
    """Mean return of the episodes that ended in the last 10 % of the time to `mark`."""
    tail = [r for t, _, r in episodes if 0.9 * mark < t <= mark]
    if not tail:  # no episode ended in that window: the last ten before the mark
        tail = [r for t, _, r in episodes if t <= mark][-10:]
    return sum(tail) / len(tail) if tail else float("nan")


def checkpoints_at(run_dir: Path, marks: list[float]) -> dict[float, tuple[Path, dict]]:
    """For each mark, the checkpoint last written before it (the final one for the last mark),
    with its training seconds and steps."""
    from tpdeb.services.store.checkpoint import FINAL, checkpoint_dir, list_checkpoints, load

    timed = []
    for c in list_checkpoints(checkpoint_dir(run_dir)):
        state = load(c.path)
        timed.append((float(state.get("train_elapsed_s", 0.0)), c))
    chosen = {}
    for mark in marks:
        if mark == marks[-1]:
            pick = [(t, c) for t, c in timed if c.tag == FINAL]
        else:
            pick = [(t, c) for t, c in timed if t <= mark + 1.0 and c.tag != FINAL]
        if pick:
            t, c = max(pick, key=lambda tc: tc[0])
            chosen[mark] = (c.path, {"t_s": round(t, 1), "steps": c.global_step})
    return chosen


def run_budgeted(env_id: str, seed: int, budget_s: float, extra: list[str], run_dir: Path,
                 log: Path, eval_episodes: int, what: str) -> dict | None:
    """One `tpdeb-cluster` for `budget_s` training seconds (`extra`: its flags and settings),
    started from nothing, with a checkpoint every minute, all kept: its episodes on the clock
    and, per 5-minute mark, the checkpoint last written before it, evaluated. None where it
    failed (`what` names it in the message)."""
    if run_dir.exists():  # a run cut short: start again from nothing
        shutil.rmtree(run_dir)
    record = provenance.start()
    code, wall_s = run_cluster(env_id, NEVER, seed, run_dir,
                               ["--train-for-seconds", str(budget_s), *extra], log, budget_s + 600,
                               env={"TPDEB_KEEP_CHECKPOINTS": "1000",
                                    "TPDEB_CHECKPOINT_INTERVAL_S": "60"})
    end = run_dir / "end.json"
    if code != 0 or not end.is_file():
        print(f"[{what}]   exit code {code} after {wall_s:.0f} s; see {log} (not recorded, will "
              "be rerun)", flush=True)
        return None
    end = json.loads(end.read_text())
    marks = {}
    for mark, (path, where) in checkpoints_at(run_dir, marks_for(budget_s)).items():
        marks[str(int(mark))] = {**where, "eval": evaluate(path, eval_episodes, 10_000 + seed)}
    return {"env_id": env_id, "seed": seed, "budget_s": budget_s, "train_s":
            end["train_elapsed_s"], "wall_s": round(wall_s, 1), "steps": end["global_step"],
            "episodes": on_the_clock(read_run_metrics(run_dir)), "marks": marks,
            "provenance": record}


def run_tpdeb(args, env_id: str, seed: int) -> dict | None:
    """One TPDEB run as a user starts it: `preset = auto` with a clock budget picks the task's
    race preset where there is one; the run records the file its train.toml names."""
    name = f"{env_id}__{seed}"
    extra = [arg for item in args.set for arg in ("--set", item)]
    print(f"[race] {time.strftime('%H:%M')} {args.tag}: tpdeb | {env_id} | seed {seed} | "
          f"{args.minutes:g} min …", flush=True)
    run_dir = OUT / args.tag / "tpdeb" / name
    result = run_budgeted(env_id, seed, 60.0 * args.minutes, extra, run_dir,
                          OUT / args.tag / "tpdeb" / f"{name}.log", args.eval_episodes, "race")
    if result is not None:
        result.update(system="tpdeb", overrides=list(args.set),
                      preset=preset_used(run_dir))
    return result


def preset_used(run_dir: Path) -> str:
    """The preset a run's train.toml names, relative to the repository where it is in it."""
    from tpdeb.services.config import load_toml

    preset = load_toml(run_dir / "train.toml")["run"].get("preset", "none")
    if preset == "none":
        return "none"
    try:
        return str(Path(preset).relative_to(ROOT))
    except ValueError:
        return preset


def run_peer(args, system: str, env_id: str, seed: int) -> dict | None:
    budget = 60.0 * args.minutes
    path = result_path(args.tag, system, env_id, seed)
    cmd = [sys.executable, str(ROOT / "bench" / "peers.py"), "--system", system,
           "--env-id", env_id, "--seed", str(seed), "--seconds", str(budget),
           "--marks", *map(str, marks_for(budget)), "--eval-episodes",
           str(args.eval_episodes), "--out", str(path.with_suffix(".peer"))]
    print(f"[race] {time.strftime('%H:%M')} {args.tag}: {system} | {env_id} | seed {seed} | "
          f"{args.minutes:g} min …", flush=True)
    log = OUT / args.tag / system / f"{env_id}__{seed}.log"
    log.parent.mkdir(parents=True, exist_ok=True)
    record = provenance.start()
    with log.open("w") as out:
        code = subprocess.run(cmd, cwd=ROOT, stdout=out, stderr=subprocess.STDOUT).returncode
    peer = path.with_suffix(".peer")
    if code != 0 or not peer.is_file():
        print(f"[race]   exit code {code}; see {log} (not recorded)", flush=True)
        return None
    result = json.loads(peer.read_text())
    peer.unlink()
    result["provenance"] = record
    return result


def interleaved(env_id: str, seeds: list[int], peer_seeds: list[int],
                peers: tuple[str, ...] = PEERS) -> list[tuple[str, str, int]]:
    """One task's sitting: each TPDEB seed, then (while they last) each peer at the next peer
    seed — TPDEB 11, SAC 11, PPO 11, TPDEB 12, … — as (system, env, seed) jobs."""
    jobs: list[tuple[str, str, int]] = []
    for i, seed in enumerate(seeds):
        jobs.append(("tpdeb", env_id, seed))
        if i < len(peer_seeds):
            jobs += [(peer, env_id, peer_seeds[i]) for peer in peers]
    for peer_seed in peer_seeds[len(seeds):]:
        jobs += [(peer, env_id, peer_seed) for peer in peers]
    return jobs


def sitting_name() -> str:
    """The UTC date and the kernel's boot id: every run on one session's machine (one boot)
    shares it, however many bench invocations and hours it spans."""
    try:
        boot = Path("/proc/sys/kernel/random/boot_id").read_text().strip()[:8]
    except OSError:
        boot = "unknown-boot"
    return f"{time.strftime('%Y-%m-%d', time.gmtime())}/{boot}"


def calibrate(env_id: str, seconds: float = CALIBRATION_S) -> dict:
    """The plain one-core acting loop's env steps/s on this task (its preset's envs per actor,
    a fresh policy in numpy): what the machine gives right now, beside each run's figures."""
    from throughput import bench_acting_limit, preset_config

    result = bench_acting_limit(preset_config(env_id, 4, 0), seconds)
    return {"env_id": env_id, "num_envs": 4, "env_steps_per_s": round(result["env_steps_per_s"]),
            "seconds": round(result["seconds"], 1)}


def marks_for(budget: float) -> list[float]:
    """Every 5 minutes up to the budget (seconds), and the budget."""
    marks = [300.0 * k for k in range(1, int(budget // 300) + 1)]
    return marks if marks and marks[-1] == budget else [*marks, budget]


def finish(path: Path, result: dict | None, what: str = "race") -> None:
    """Add each mark's training return and write the result file (nothing for a failed run)."""
    if result is None:
        return
    for mark, at in result["marks"].items():
        at["train_return"] = return_at([tuple(e) for e in result["episodes"]], float(mark))
    save_json(path, provenance.stamp(result, result["provenance"]))
    shown = " | ".join(f"{int(m) / 60:g} min: {at['train_return']:,.0f}"
                       + (f" (eval {at['eval']['mean_return']:,.0f})" if at.get("eval") else "")
                       for m, at in result["marks"].items())
    print(f"[{what}]   → {shown} | {result['steps']:,} steps", flush=True)


def peers_available() -> bool:
    try:
        import rl_zoo3  # noqa: F401
        import stable_baselines3  # noqa: F401
    except ImportError:
        return False
    return True


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", nargs="+")
    parser.add_argument("--seeds", type=int, nargs="+")
    parser.add_argument("--minutes", type=float, default=15.0)
    parser.add_argument("--tag", default="race")
    parser.add_argument("--peers", action="store_true",
                        help="run the peers (SB3 SAC and PPO, CleanRL SAC) instead of TPDEB")
    parser.add_argument("--sitting", action="store_true",
                        help="each task's TPDEB seeds and peers interleaved, in one sitting")
    parser.add_argument("--peer-seeds", type=int, nargs="+",
                        help=f"the peers' seeds in a sitting (default {list(PEER_SEEDS)})")
    parser.add_argument("--sitting-name", default=sitting_name(),
                        help="what the runs record as their sitting (default: the UTC date and "
                        "this machine's boot id: one session's machine)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="a training setting on top of the race preset (TPDEB runs)")
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument("--report", action="store_true",
                        help="no runs: RESULTS' race table and the figures")
    args = parser.parse_args()
    if args.report:
        from race_report import report, tuning_report

        report(DATA / args.tag, args.envs or list(TASKS))
        if args.tag == "race":
            tuning_report(DATA / "race-tune")
        return
    if (args.peers or args.sitting) and not peers_available():
        sys.exit("race: the peers need the bench-only extra: .venv/bin/pip install -e '.[peers]'")
    envs = args.envs or list(TASKS)
    if args.sitting:
        seeds = args.seeds or list(REPORT_SEEDS)
        jobs = [j for env_id in envs for j in interleaved(env_id, seeds,
                                                           args.peer_seeds or list(PEER_SEEDS))]
    else:
        seeds = args.seeds or (list(PEER_SEEDS) if args.peers else list(REPORT_SEEDS))
        systems = PEERS if args.peers else ("tpdeb",)
        jobs = [(system, env_id, seed) for seed in seeds for env_id in envs
                for system in systems]
    todo = [j for j in jobs if not result_path(args.tag, *j).exists()]
    print(f"[race] {args.tag}: {len(jobs)} runs of {args.minutes:g} minutes, "
          f"{len(jobs) - len(todo)} already done; sitting {args.sitting_name}; results in "
          f"{DATA / args.tag}", flush=True)
    for n, (system, env_id, seed) in enumerate(todo, 1):
        print(f"[race] run {n}/{len(todo)}: calibrating ({CALIBRATION_S:g} s)", flush=True)
        calibration = calibrate(env_id)
        result = (run_tpdeb(args, env_id, seed) if system == "tpdeb"
                  else run_peer(args, system, env_id, seed))
        if result is not None:
            result.update(sitting=args.sitting_name, calibration=calibration)
        finish(result_path(args.tag, system, env_id, seed), result)

if __name__ == "__main__":
    main()
