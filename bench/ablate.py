"""The paper's ablations (its Section 3.2, Fig 6) and two claims of its abstract, on the system
as it is: every run a real `tpdeb-cluster` with the task's preset and one setting changed.

    python bench/ablate.py --plan                 # every run: its settings, done or not
    python bench/ablate.py                        # run what is missing (hours: a background job)
    python bench/ablate.py --studies zeta tau     # some studies only
    python bench/ablate.py --studies priority --envs Hopper-v5   # and some tasks only
    python bench/ablate.py --report               # docs/ABLATIONS.md and docs/img/ablation/
    python bench/ablate.py --shard 2/8            # on a larger machine: eight of these at once

Studies (1M env steps, seeds 11-13 unless said; tuning seeds 1-3 are never used here):
    zeta      ζ ∈ {0, 0.1, 0.2, 0.4, 0.6, 1} on Ant (Fig 6a, and the policy loss: Fig 6b)
    tau       τ ∈ {0.001, 0.005, 0.01, 0.05, 0.1} on Ant (Fig 6c)
    buffers   N_u ∈ {5e3, 5e4, 5e5, 1e6} steps × N_p ∈ {1e3, 2e4, 4e4, 8e4} steps on Ant, seed 11
              only (Fig 6d; N_p becomes a capacity in fragments of the preset's length)
    workers   1, 2, 4, 8 actors on Ant (Fig 6e), against env steps and against wall-clock
    priority  priority by trajectory (the preset) vs by step, on Ant and Hopper
    kl        the preset vs no KL term (λ_kl = 0, no adaptive target), on Ant and Hopper

A run whose settings are the preset's is the comparison grid's own run (docs/data/paper/, made
by `bench/paper.py` and shared with it); every other run leaves one small JSON under
docs/data/ablation/{study}/{cell}/. A run whose file exists is skipped, so a stopped grid resumes
where it stopped. The workers study times the runs: nothing else may run meanwhile, and it makes
its own preset run (2 actors), so that every cell it compares by the clock ran on the same code.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace

sys.path.insert(0, str(Path(__file__).resolve().parent))
from paper import result_path, run_one  # noqa: E402

STEPS = 1_000_000
SEEDS = (11, 12, 13)
ALGO = "tpdeb"


@dataclass(frozen=True)
class Cell:
    """One setting of a study: training settings (`--set`) and the number of actors."""

    label: str
    settings: dict = field(default_factory=dict)
    actors: int | None = None

    @property
    def slug(self) -> str:
        return self.label.replace(" ", "").replace("=", "-").replace(",", "-").replace("/", "-")


@dataclass(frozen=True)
class Study:
    name: str
    figure: str
    envs: tuple[str, ...]
    cells: tuple[Cell, ...]
    seeds: tuple[int, ...] = SEEDS
    timed: bool = False  # then every cell is its own run, so all run on the same code


def _fragments(steps: int, fragment_len: int) -> int:
    return max(1, round(steps / fragment_len))


def _short(steps: int) -> str:
    """5000 → 5k, 1000000 → 1M."""
    for unit, size in (("M", 1_000_000), ("k", 1_000)):
        if steps >= size and steps % size == 0:
            return f"{steps // size}{unit}"
    return str(steps)


def studies(fragment_len: int = 64) -> dict[str, Study]:
    """The studies; `fragment_len` turns the paper's prioritised capacities (steps) into
    fragments."""
    ant, both = ("Ant-v5",), ("Ant-v5", "Hopper-v5")
    buffers = tuple(
        Cell(f"N_u={_short(nu)},N_p={_short(np_)}",
             {"uniform_capacity_steps": nu,
              "prioritized_capacity": _fragments(np_, fragment_len)})
        for nu in (5_000, 50_000, 500_000, 1_000_000) for np_ in (1_000, 20_000, 40_000, 80_000))
    return {s.name: s for s in (
        Study("zeta", "Fig 6a, 6b", ant,
              tuple(Cell(f"zeta={v:g}", {"zeta": v}) for v in (0.0, 0.1, 0.2, 0.4, 0.6, 1.0))),
        Study("tau", "Fig 6c", ant,
              tuple(Cell(f"tau={v:g}", {"tau": v}) for v in (0.001, 0.005, 0.01, 0.05, 0.1))),
        Study("buffers", "Fig 6d", ant, buffers, seeds=(11,)),
        Study("workers", "Fig 6e", ant, tuple(Cell(f"actors={n}", actors=n) for n in (1, 2, 4, 8)),
              timed=True),
        Study("priority", "abstract: trajectory vs step priority", both,
              (Cell("priority=trajectory", {"priority_mode": "trajectory"}),
               Cell("priority=step", {"priority_mode": "step"}))),
        Study("kl", "abstract: KL regularisation", both,
              (Cell("kl=preset"), Cell("kl=off", {"kl_coef": 0.0, "kl_target": 0.0}))),
    )}


def preset_values(env_id: str) -> dict:
    """Every training setting as a run of `env_id` on its preset resolves it, and the actors
    the default cluster file starts."""
    from tpdeb.services.config import load_toml
    from tpdeb.services.config.presets import layer
    from tpdeb.services.config.train import TrainConfig
    from tpdeb.services.launcher.plan import DEFAULT_FILE

    config = TrainConfig(**layer(TrainConfig, {"env_id": env_id}))
    values = dataclasses.asdict(config)
    values["actors"] = load_toml(DEFAULT_FILE)["services"]["actor"]["replicas"]
    return values


def is_preset(cell: Cell, preset: dict) -> bool:
    """Whether the cell changes nothing of the preset: then its run is the grid's own."""
    wanted = dict(cell.settings)
    if cell.actors is not None:
        wanted["actors"] = cell.actors
    return all(preset[key] == value for key, value in wanted.items())


def tag_of(study: Study, cell: Cell, preset: dict) -> str:
    """Where a cell's runs live: the comparison grid's own for a cell on the preset (but for a
    timed study, whose cells must all run on the same code), else the study's."""
    shared = not study.timed and is_preset(cell, preset)
    return "paper" if shared else f"ablation/{study.name}/{cell.slug}"


@dataclass(frozen=True)
class Run:
    study: str
    cell: Cell
    env_id: str
    seed: int
    tag: str  # results in docs/data/{tag}/

    @property
    def path(self) -> Path:
        return result_path(self.tag, self.env_id, ALGO, STEPS, self.seed)

    @property
    def shared(self) -> bool:
        return self.tag == "paper"


def plan(names: list[str], presets: dict[str, dict] | None = None,
         envs: list[str] | None = None) -> list[Run]:
    """The runs of the named studies, seed-major (every cell gets its first seed before any gets
    its second), a run shared by two studies listed once; `envs`, if given, keeps those tasks'
    runs only."""
    presets = presets if presets is not None else {}
    all_studies = studies()
    unknown = [n for n in names if n not in all_studies]
    if unknown:
        raise SystemExit(f"unknown study {', '.join(unknown)}; studies are "
                         f"{', '.join(all_studies)}")
    tasks = sorted({e for n in names for e in all_studies[n].envs})
    strange = [e for e in envs or () if e not in tasks]
    if strange:
        raise SystemExit(f"no study named here runs {', '.join(strange)}; they run "
                         f"{', '.join(tasks)}")
    runs, seen = [], set()
    for seed in sorted({s for n in names for s in all_studies[n].seeds}):
        for name in names:
            study = all_studies[name]
            if seed not in study.seeds:
                continue
            for env_id in study.envs:
                if envs and env_id not in envs:
                    continue
                if env_id not in presets:
                    presets[env_id] = preset_values(env_id)
                for cell in study.cells:
                    run = Run(name, cell, env_id, seed, tag_of(study, cell, presets[env_id]))
                    if run.path not in seen:
                        seen.add(run.path)
                        runs.append(run)
    return runs


def execute(runs: list[Run], timeout_s: float, eval_episodes: int) -> None:
    """Make every run whose file is missing, in order; one that fails is left for next time."""
    todo = [r for r in runs if not r.path.exists()]
    print(f"[ablate] {len(runs)} runs of {STEPS:,} steps, {len(runs) - len(todo)} already done",
          flush=True)
    for n, run in enumerate(todo, 1):
        print(f"[ablate] run {n}/{len(todo)}: {run.study} | {run.cell.label}", flush=True)
        sets = [f"{key}={value}" for key, value in run.cell.settings.items()]
        flags = ["--actors", str(run.cell.actors)] if run.cell.actors is not None else []
        args = SimpleNamespace(tag=run.tag, steps=STEPS, set=sets, timeout_s=timeout_s,
                               eval_episodes=eval_episodes)
        run_one(args, run.env_id, ALGO, run.seed, flags=flags)


def shard(text: str) -> tuple[int, int]:
    """'K/N' → (K, N), 0 ≤ K < N."""
    try:
        k, n = (int(part) for part in text.split("/"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: a shard is K/N, e.g. 0/4") from None
    if not 0 <= k < n:
        raise argparse.ArgumentTypeError(f"{text!r}: K/N needs 0 ≤ K < N")
    return k, n


def share(runs: list[Run], k: int, n: int) -> list[Run]:
    """Shard K of N: every N-th run still missing, from the K-th."""
    return [r for r in runs if not r.path.exists()][k::n]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--studies", nargs="+", default=list(studies()))
    parser.add_argument("--envs", nargs="+", metavar="ENV_ID",
                        help="only these tasks' runs (e.g. Hopper-v5)")
    parser.add_argument("--plan", action="store_true", help="no runs: list them")
    parser.add_argument("--report", action="store_true",
                        help="no runs: write docs/ABLATIONS.md and its figures")
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument("--timeout-s", type=float, default=4 * 3600)
    parser.add_argument("--shard", type=shard, metavar="K/N",
                        help="only every N-th missing run, from the K-th (0 ≤ K < N): N "
                             "processes with K = 0 … N-1, started together, share the grid "
                             "without overlap")
    args = parser.parse_args()
    if args.report:
        from ablate_report import report

        report(plan(list(studies())))
        return
    runs = plan(args.studies, envs=args.envs)
    if args.shard:
        runs = share(runs, *args.shard)
    if args.plan:
        done = 0
        for r in runs:
            done += r.path.exists()
            state = "done" if r.path.exists() else "to run"
            where = "the comparison grid's run" if r.shared else r.tag
            print(f"{r.study:9} {r.env_id:12} seed {r.seed}  {r.cell.label:24} {state:7} {where}")
        print(f"{len(runs)} runs, {done} done, {len(runs) - done} to run")
        return
    execute(runs, args.timeout_s, args.eval_episodes)


if __name__ == "__main__":
    main()
