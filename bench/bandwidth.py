"""Thin links: TPDEB against IMPACT and PPO+PER with the actors behind a constrained link, each
run given the same wall-clock budget (the env steps it reaches are part of the result).

    python bench/bandwidth.py                    # HalfCheetah, 3 algorithms × 4 links × seeds
                                                 # 11-13, 10 minutes each (hours: background)
    python bench/bandwidth.py --band             # TPDEB and IMPACT with a replay-ratio band
    python bench/bandwidth.py --envs Ant-v5 --seeds 11
    python bench/bandwidth.py --plan             # the runs, done or not
    python bench/bandwidth.py --report           # BENCHMARKS' thin-link section,
                                                 # docs/img/thinlink/, the verdict in
                                                 # RESULTS and README

Every run is a real `tpdeb-cluster` (router, replay, learner, 2 actors × 4 envs) with the
task's preset, `--set algo=…`, compression on (zstd trajectories, float16 parameters) and the
actors behind `tpdeb-link` at the same rate both ways; "unlimited" still routes through the link
(at 10^12 B/s) so that its bytes are counted the same way. `--train-for-seconds` ends each run
(the learner's clock); the checkpoint last written before each 5-minute mark is evaluated.
With `--band`, the learner may replay up to `--band-factor` × the preset's replay ratio while
inserts are scarce (`max_replay_ratio`): idle learner time turned into updates.

Resumable run by run: each finished run leaves docs/data/thinlink/{variant}/{env}__{link}__{seed}
.json; a run whose file exists is skipped. These are timings: nothing else may run meanwhile.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from race import OUT, finish, run_budgeted  # noqa: E402
from runs import ROOT, read_run_metrics  # noqa: E402

DATA = ROOT / "docs" / "data" / "thinlink"
UNLIMITED = 1e12
LINKS = (0, 2**20, 256 * 2**10, 64 * 2**10)  # bytes/s both ways; 0: unlimited
ALGOS = ("tpdeb", "impact", "ppo-per")
BANDED = ("tpdeb", "impact")
SEEDS = (11, 12, 13)
COMPRESSION = ["--set", "trajectory_compression=zstd", "--set", "params_dtype=float16"]


def link_name(rate: float) -> str:
    if rate <= 0 or rate >= UNLIMITED:
        return "unlimited"
    return f"{rate / 2**20:g} MB/s" if rate >= 2**20 else f"{rate / 2**10:g} kB/s"


def link_slug(rate: float) -> str:
    return link_name(rate).replace(" ", "").replace("/", "")


@dataclass(frozen=True)
class Run:
    algo: str
    band: bool
    env_id: str
    link: float
    seed: int

    @property
    def variant(self) -> str:
        return self.algo + ("-band" if self.band else "")

    @property
    def path(self) -> Path:
        return DATA / self.variant / f"{self.env_id}__{link_slug(self.link)}__{self.seed}.json"


def plan(envs: list[str], seeds: list[int], links: list[float], band: bool) -> list[Run]:
    """Seed-major, then env, then link from the widest: every link gets its first seed
    before any gets its second."""
    algos = BANDED if band else ALGOS
    return [Run(algo, band, env_id, link, seed) for seed in seeds for env_id in envs
            for link in sorted(links, key=lambda x: -(x or UNLIMITED)) for algo in algos]


def preset_replay_ratio(env_id: str, algo: str) -> float:
    from tpdeb.services.config.presets import layer
    from tpdeb.services.config.train import TrainConfig

    return TrainConfig(**layer(TrainConfig, {"env_id": env_id, "algo": algo})).replay_ratio


def cluster_flags(run: Run, band_factor: float) -> list[str]:
    rate = str(run.link if run.link > 0 else UNLIMITED)
    flags = ["--link-up-bytes-per-s", rate, "--link-down-bytes-per-s", rate,
             "--set", f"algo={run.algo}", *COMPRESSION]
    if run.band:
        ratio = preset_replay_ratio(run.env_id, run.algo)
        flags += ["--set", f"max_replay_ratio={band_factor * ratio:g}"]
    return flags


# the learner's figures a result keeps: its key -> the metric (its value at the end of the run)
LEARNER_FIGURES = {"samples_per_insert": "replay/samples_per_insert",
                   "batch_wait": "perf/batch_wait_fraction",
                   "sample_age": "replay/sample_age_updates"}


def run_figures(rows: list[dict]) -> dict:
    """What the link and the learner did over the run: bytes per env step each way (the link's
    count at the end), the mean parameter-version lag, and the learner's side at the end: the
    replay ratio it reached (sampled per inserted step), the fraction of its time spent waiting
    for a batch, and the mean age of a sampled fragment in learner updates."""
    link = [r for r in rows if "link/up_bytes_per_env_step" in r]
    lags = [r["actor/param_version_lag"] for r in rows if "actor/param_version_lag" in r]
    out = {
        "up_bytes_per_step": link[-1]["link/up_bytes_per_env_step"] if link else None,
        "down_bytes_per_step": link[-1]["link/down_bytes_per_env_step"] if link else None,
        "lag": statistics.mean(lags) if lags else None,
    }
    for key, metric in LEARNER_FIGURES.items():
        values = [r[metric] for r in rows if metric in r]
        out[key] = values[-1] if values else None
    return out


def execute(runs: list[Run], minutes: float, band_factor: float, eval_episodes: int) -> None:
    todo = [r for r in runs if not r.path.exists()]
    print(f"[bandwidth] {len(runs)} runs of {minutes:g} minutes, {len(runs) - len(todo)} already "
          f"done; results in {DATA}", flush=True)
    for n, run in enumerate(todo, 1):
        name = f"{run.env_id}__{link_slug(run.link)}__{run.seed}"
        print(f"[bandwidth] run {n}/{len(todo)} {time.strftime('%H:%M')}: {run.variant} | "
              f"{run.env_id} | link {link_name(run.link)} | seed {run.seed} | {minutes:g} min …",
              flush=True)
        run_dir = OUT / "thinlink" / run.variant / name
        flags = cluster_flags(run, band_factor)
        result = run_budgeted(run.env_id, run.seed, 60.0 * minutes, flags, run_dir,
                              OUT / "thinlink" / run.variant / f"{name}.log", eval_episodes,
                              "bandwidth")
        if result is not None:
            result.update(system=run.variant, algo=run.algo, band=run.band, link=run.link,
                          flags=flags, **run_figures(read_run_metrics(run_dir)))
        finish(run.path, result, "bandwidth")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", nargs="+", default=["HalfCheetah-v5"])
    parser.add_argument("--seeds", type=int, nargs="+", default=list(SEEDS))
    parser.add_argument("--links", type=float, nargs="+", default=list(LINKS),
                        help="link rates in bytes/s both ways, 0 = unlimited")
    parser.add_argument("--minutes", type=float, default=10.0)
    parser.add_argument("--band", action="store_true",
                        help="TPDEB and IMPACT with a replay-ratio band instead of the grid")
    parser.add_argument("--band-factor", type=float, default=4.0,
                        help="the band's upper end as a multiple of the preset's replay ratio")
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument("--plan", action="store_true", help="no runs: list them")
    parser.add_argument("--report", action="store_true",
                        help="no runs: write docs/BANDWIDTH.md and its figures")
    args = parser.parse_args()
    if args.band_factor < 1:
        parser.error(f"--band-factor {args.band_factor:g}: the band's upper end must be at least "
                     "the replay ratio (a factor >= 1)")
    if args.report:
        from bandwidth_report import report

        report(DATA)
        return
    runs = plan(args.envs, args.seeds, args.links, args.band)
    if args.plan:
        for r in runs:
            print(f"{r.variant:13} {r.env_id:14} {link_name(r.link):10} seed {r.seed}  "
                  f"{'done' if r.path.exists() else 'to run'}")
        return
    execute(runs, args.minutes, args.band_factor, args.eval_episodes)


if __name__ == "__main__":
    main()
