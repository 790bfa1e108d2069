"""The learner on a GPU, and a cluster on a bigger machine: the first scaling curve.

    python bench/gpu.py                      # ≤ 8 minutes, on a machine with a CUDA GPU
    python bench/gpu.py --device cpu --seconds 1 --cluster-seconds 15 --actors 1 2  # a smoke run

1. The learner's compiled update, as the service runs it, on HalfCheetah-v5 batches (the
   preset's 8 fragments × 64 steps) with 64×64, 256×256 and 1024×1024 networks: updates/s on
   the device, and on the CPU at 1 torch thread and at every core.
2. `tpdeb-cluster` on HalfCheetah-v5 (its preset, the learner on the device) with 1, 2, 4, 8 and
   14 actors × 4 envs (and 14 again with the learner on the CPU, for comparison), each trained
   for `--cluster-seconds` (`--train-for-seconds`): env steps/s
   and updates/s over the run (from its end.json), and the CPU the replay server, the router,
   the learner and the actors used per second of the run's wall-clock, start-up included (from
   /proc, sampled every second).

Prints the machine (CPU model and cores, GPU, torch) and markdown tables for BENCHMARKS; writes
bench/out/gpu/results.json. These are timings: nothing else may run meanwhile.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import signal
import statistics
import subprocess
import sys
import time
from pathlib import Path

import provenance
import torch
from procfs import CpuSampler, cmdline, descendants, service_name
from throughput import bench_learner, preset_config, sample_batches

from tpdeb.services.device import describe, resolve_device
from tpdeb.services.store.metrics import read_metrics

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "bench" / "out" / "gpu"
SIZES = ((64, 64), (256, 256), (1024, 1024))
SHARED = "perf/sample_replies_shared_memory"  # the learner's batches through shared memory


def machine(device: torch.device) -> dict:
    m = provenance.machine()
    return {"cpu": m["cpu"] or "?", "cores": m["cores"], "device": describe(device),
            "torch": torch.__version__, "python": platform.python_version()}


def updates_per_s(spec, config, fragments, batches, device, threads: int,
                  seconds: float) -> float:
    """The learner's compiled update as the service runs it (bench/throughput.py)."""
    return bench_learner(config, spec, fragments, batches, seconds, device, threads)[
        "updates_per_s"]


def learner_rates(args, device) -> list[dict]:
    rows = []
    for hidden in SIZES:
        config = preset_config(args.env_id, 4, args.seed)
        config.hidden_sizes = hidden
        spec, fragments, batches = sample_batches(config, count=16)
        row = {"hidden": "×".join(map(str, hidden)), "batch_steps": config.batch_steps}
        row["device"] = updates_per_s(spec, config, fragments, batches, device, 1, args.seconds)
        row["cpu_1_thread"] = updates_per_s(spec, config, fragments, batches, "cpu", 1,
                                            args.seconds)
        row["cpu_all_threads"] = updates_per_s(spec, config, fragments, batches, "cpu",
                                               os.cpu_count() or 1, args.seconds)
        print(f"[gpu] {row['hidden']}: {row['device']:,.0f} updates/s on {device}, "
              f"{row['cpu_1_thread']:,.0f} on 1 CPU thread, {row['cpu_all_threads']:,.0f} on "
              f"{os.cpu_count()}", flush=True)
        rows.append(row)
    return rows


def by_role(seconds: dict[tuple[int, str], float]) -> dict[str, float]:
    """CPU seconds per role (the actors together, replay shards together, learner ranks
    together) from {(pid, service name): seconds}."""
    out: dict[str, float] = {}
    for (_, name), value in seconds.items():
        role = "actors" if name.startswith("actor") else name.split("-")[0]
        out[role] = out.get(role, 0.0) + value
    return out


def services_below(root: int) -> dict[tuple[int, str], int]:
    found = {}
    for pid in descendants(root):
        name = service_name(cmdline(pid))
        if name is not None:
            found[(pid, name)] = pid
    return found


def cluster_run(args, actors: int, device: str, shards: int = 1, learners: int = 1,
                env_id: str | None = None, out: Path = OUT, settings: tuple = (),
                environ: dict | None = None) -> dict:
    """One cluster run; `settings`: more KEY=VALUE for --set (batch growth, a wider batch);
    `environ`: more variables for the cluster (services' own settings, TPDEB_*)."""
    env_id = env_id or args.env_id
    name = f"{env_id}-{actors}actors-{device}" + (f"-{shards}shards-{learners}learners"
                                                  if (shards, learners) != (1, 1) else "")
    name += "".join(f"-{item.replace('=', '')}" for item in settings)
    name += "".join(f"-{k.lower()}{v}" for k, v in (environ or {}).items())
    run_dir = out / "runs" / name
    cmd = [sys.executable, "-m", "tpdeb.services.cluster", "--env-id", env_id,
           "--total-timesteps", str(10**9), "--train-for-seconds", str(args.cluster_seconds),
           "--actors", str(actors), "--num-envs", "4", "--seed", str(args.seed),
           "--run-dir", str(run_dir), "--set", f"device={device}",
           "--set", f"replay_shards={shards}", "--set", f"learners={learners}",
           *(arg for item in settings for arg in ("--set", item))]
    subprocess.run(["rm", "-rf", str(run_dir)], check=False)
    run_dir.parent.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    with (out / f"cluster_{name}.log").open("w") as log:
        proc = subprocess.Popen(cmd, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT,
                                start_new_session=True, env={**os.environ, **(environ or {})})
        sampler = CpuSampler(lambda: services_below(proc.pid), 1.0)
        sampler.start()
        try:
            code = proc.wait(args.cluster_seconds + 300)
        except BaseException:
            os.killpg(proc.pid, signal.SIGTERM)
            proc.wait(60)
            raise
        finally:
            sampler.stop()
    wall = time.perf_counter() - start
    end_file = run_dir / "end.json"
    end = json.loads(end_file.read_text()) if end_file.is_file() else {}
    train_s = end.get("train_elapsed_s") or float("nan")
    metrics = run_dir / "metrics.jsonl"
    shared = [r[SHARED] for r in (read_metrics(metrics) if metrics.is_file() else [])
              if SHARED in r]
    row = {"env_id": env_id, "actors": actors, "replay_shards": shards, "learners": learners,
           "settings": list(settings), "environ": dict(environ or {}), "device": device,
           "exit_code": code,
           "wall_s": round(wall, 1),
           "env_steps_per_s": end.get("global_step", 0) / train_s,
           "updates_per_s": end.get("updates", 0) / train_s,
           "cpu_per_s": {k: round(v / wall, 2) for k, v in by_role(sampler.last).items()},
           "batches_through_shared_memory": statistics.median(shared) if shared else None}
    cpu = row["cpu_per_s"]
    print(f"[gpu] {env_id}, {actors} actors, {shards} shard(s), {learners} learner(s) on {device}: "
          f"{row['env_steps_per_s']:,.0f} env steps/s, "
          f"{row['updates_per_s']:,.0f} updates/s; CPU/s replay {cpu.get('replay', 0):.2f}, "
          f"router {cpu.get('router', 0):.2f}, learner {cpu.get('learner', 0):.2f}, actors "
          f"{cpu.get('actors', 0):.2f} (exit {code})", flush=True)
    return row


def alternated(args, variants: dict[str, dict], pairs: int, actors: int, out: Path) -> dict:
    """Cluster runs of each variant (cluster_run's keyword arguments), `pairs` rounds with the
    order turned each round; each variant's runs and its medians of env steps/s and updates/s,
    and the first variant's env steps/s over the second's."""
    runs: dict[str, list[dict]] = {name: [] for name in variants}
    for i in range(pairs):
        for name in (list(variants) if i % 2 == 0 else list(reversed(variants))):
            runs[name].append(cluster_run(args, actors, "cpu", out=out, **variants[name]))
    result = {"runs": runs}
    for name, rows in runs.items():
        result[f"{name}_env_steps_per_s"] = statistics.median(r["env_steps_per_s"] for r in rows)
        result[f"{name}_updates_per_s"] = statistics.median(r["updates_per_s"] for r in rows)
        steps = " / ".join(f"{r['env_steps_per_s']:,.0f}" for r in rows)
        print(f"{name:>13}: env steps/s {steps} (median "
              f"{result[f'{name}_env_steps_per_s']:,.0f}); batches through shared memory "
              f"{[r['batches_through_shared_memory'] for r in rows]}", flush=True)
    first, second = list(variants)[:2]
    ratio = result[f"{first}_env_steps_per_s"] / result[f"{second}_env_steps_per_s"]
    result[f"ratio_{first}_over_{second}"] = round(ratio, 3)
    print(f"{first} ÷ {second}, env steps/s (medians): {ratio:.3f}")
    return result


def cluster_arguments(parser, cluster_seconds: float) -> None:
    """The options every bigger-machine bench shares: the learner's device, the actor counts,
    each cluster run's training seconds, the seed."""
    parser.add_argument("--device", default="cuda", help="the learner's device (cuda, cuda:N, "
                        "or cpu for a smoke run)")
    parser.add_argument("--actors", type=int, nargs="+", default=[1, 2, 4, 8, 14],
                        help="actor counts of the cluster runs (one replay, one learner)")
    parser.add_argument("--cluster-seconds", type=float, default=cluster_seconds,
                        help="training seconds of each cluster run")
    parser.add_argument("--seed", type=int, default=1)


def save(result: dict, record: dict, out: Path) -> None:
    """The results so far, stamped with the run's provenance, to {out}/results.json."""
    provenance.stamp(result, record)
    (out / "results.json").write_text(json.dumps(result, indent=1))


def cpu_cells(cpu: dict) -> str:
    """A table row's CPU-per-second cells: replay, router, learner, actors."""
    return " | ".join(f"{cpu.get(role, 0):.2f}" for role in ("replay", "router", "learner",
                                                              "actors"))


def tables(result: dict) -> str:
    m = result["machine"]
    out = [f"Machine: {m['cpu']}, {m['cores']} cores; learner device {m['device']}; torch "
           f"{m['torch']}.", "", "| network | updates/s on the device | CPU, 1 thread | CPU, "
           f"{m['cores']} threads |", "|---|---|---|---|"]
    out += [f"| {r['hidden']} | {r['device']:,.0f} | {r['cpu_1_thread']:,.0f} | "
            f"{r['cpu_all_threads']:,.0f} |" for r in result["learner"]]
    out += ["", "| actors × 4 envs | learner | env steps/s | updates/s | CPU/s replay | router "
            "| learner | actors |", "|---|---|---|---|---|---|---|---|"]
    for r in result["cluster"]:
        out.append(f"| {r['actors']} | {r['device']} | {r['env_steps_per_s']:,.0f} | "
                   f"{r['updates_per_s']:,.0f} | {cpu_cells(r['cpu_per_s'])} |")
    return "\n".join(out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    cluster_arguments(parser, cluster_seconds=40.0)
    parser.add_argument("--env-id", default="HalfCheetah-v5")
    parser.add_argument("--seconds", type=float, default=5.0,
                        help="each updates/s measurement")
    parser.add_argument("--cpu-actors", type=int, nargs="*", default=[14],
                        help="cluster runs repeated with the learner on the CPU, for comparison")
    args = parser.parse_args()
    record = provenance.start()
    device = resolve_device(args.device)
    OUT.mkdir(parents=True, exist_ok=True)
    result = {"machine": machine(device), "args": vars(args)}
    print(f"[gpu] {result['machine']}", flush=True)
    result["learner"] = learner_rates(args, device)
    result["cluster"] = []
    runs = [(n, args.device) for n in args.actors] + [(n, "cpu") for n in args.cpu_actors
                                                       if args.device != "cpu"]
    for actors, device_name in runs:
        result["cluster"].append(cluster_run(args, actors, device_name))
        save(result, record, OUT)
    result["table_markdown"] = tables(result)
    save(result, record, OUT)
    print()
    print(result["table_markdown"])


if __name__ == "__main__":
    main()
