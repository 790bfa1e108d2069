"""Tables and figures of the race from the finished runs in docs/data/{tag}/{system}/.

Writes the part of docs/RESULTS.md between `<!-- race:begin -->` and `<!-- race:end -->` (for
the reported tag, `race`) and one PNG per task of return against wall-clock minutes in
docs/img/{tag}/. Called by `python bench/race.py --report`.
"""

from __future__ import annotations

import json
import statistics
from pathlib import Path

import numpy as np
from paper_report import SAC_1M, SAC_KIND, cell, replace_between, seeds  # noqa: I001  (bench/ is on sys.path)
from runs import ROOT

from tpdeb.services.plot import band, save, smooth

SYSTEMS = {"tpdeb": "TPDEB", "sb3-sac": "SB3 SAC (zoo)", "sb3-ppo": "SB3 PPO (zoo)",
           "cleanrl-sac": "CleanRL SAC"}
WINDOW = 20  # episodes in the smoothed curves
GRID_S = 10.0
BEGIN, END = "<!-- race:begin -->", "<!-- race:end -->"
TUNE_BEGIN, TUNE_END = "<!-- race-tune:begin -->", "<!-- race-tune:end -->"


def load(directory: Path) -> list[dict]:
    return [json.loads(p.read_text()) for p in sorted(directory.glob("*/*.json"))]


def curve(run: dict, budget: float) -> tuple[np.ndarray, np.ndarray]:
    """The run's smoothed return on a grid of GRID_S seconds up to `budget` (NaN before its
    first episode)."""
    grid = np.arange(GRID_S, budget + 1e-9, GRID_S)
    if not run["episodes"]:
        return grid, np.full(grid.shape, np.nan)
    t, _, r = np.array(run["episodes"], dtype=np.float64).T
    order = np.argsort(t, kind="stable")
    t, r = t[order], smooth(r[order], WINDOW)
    idx = np.searchsorted(t, grid, side="right") - 1
    values = np.where(idx >= 0, r[np.clip(idx, 0, None)], np.nan)
    return grid, values


def mean_curve(runs: list[dict]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    budget = min(r["budget_s"] for r in runs)
    curves = [curve(r, budget) for r in runs]
    values = np.array([v for _, v in curves])
    mean, std = np.full((2, values.shape[1]), np.nan)
    seen = np.isfinite(values).any(axis=0)  # before any run's first episode: NaN, no warning
    mean[seen], std[seen] = np.nanmean(values[:, seen], axis=0), np.nanstd(values[:, seen], axis=0)
    return curves[0][0], mean, std


def time_to(runs: list[dict], threshold: float) -> str:
    """The time at which the runs' mean smoothed curve first reaches `threshold`."""
    if not runs or threshold != threshold:
        return "—"
    grid, mean, _ = mean_curve(runs)
    hit = np.flatnonzero(np.nan_to_num(mean, nan=-np.inf) >= threshold)
    return f"{grid[hit[0]] / 60:.1f} min" if hit.size else f"not in {grid[-1] / 60:g} min"


def at(runs: list[dict], mark: str, what: str) -> list[float]:
    out = []
    for r in runs:
        entry = r["marks"].get(mark)
        if entry is None:
            continue
        value = entry["train_return"] if what == "train" else (entry.get("eval") or {}).get(
            "mean_return")
        if value is not None and value == value:
            out.append(value)
    return out


def final_mark(runs: list[dict]) -> str:
    return str(int(min(r["budget_s"] for r in runs)))


def goal(values: list[float], bar: float) -> str:
    """TPDEB's goal on one task, judged on its median over seeds: "met" where the median is at
    or above SAC's published 1M return `bar`, else "not met"; a single seed is not judged."""
    if not values:
        return "—"
    if len(values) < 2:
        return "not judged (one seed)"
    return "met" if statistics.median(values) >= bar else "not met"


def whole(values: list[float]) -> str:
    """Seeds reported whole: mean ± std, and beside it the median (what the goal is judged on)
    and the worst seed."""
    if len(values) < 2:
        return cell(values)
    return f"{cell(values)}; median {statistics.median(values):,.0f}, worst {min(values):,.0f}"


def sitting_table(results: list[dict], envs: list[str]) -> str:
    """Which sitting made each task's runs, and the machine's pace in it: the plain one-core
    acting loop's env steps/s measured before each run (shown, never used to rescale)."""
    lines = ["| task | sitting | runs | acting loop before each run, env steps/s "
             "(median, range) |", "|---|---|---|---|"]
    for env_id in envs:
        runs = [r for r in results if r["env_id"] == env_id]
        for sitting in sorted({r.get("sitting") or "not recorded" for r in runs}):
            mine = [r for r in runs if (r.get("sitting") or "not recorded") == sitting]
            count = ", ".join(f"{SYSTEMS[s]} {sum(r['system'] == s for r in mine)}"
                              for s in SYSTEMS if any(r["system"] == s for r in mine))
            pace = [r["calibration"]["env_steps_per_s"] for r in mine if r.get("calibration")]
            shown = (f"{statistics.median(pace):,.0f} ({min(pace):,.0f}–{max(pace):,.0f})"
                     if pace else "not measured")
            lines.append(f"| {env_id} | {sitting} | {count} | {shown} |")
    return "\n".join(lines)


def budget_table(results: list[dict], envs: list[str]) -> str:
    """Each system's return at the end of the budget, against SAC's 1M return: TPDEB's goal is
    judged on its median over seeds, like for like (training against CleanRL's training return,
    evaluation against the zoo's evaluated model); the peers' single seeds are shown, not
    judged."""
    shown = [s for s in SYSTEMS if s in ("tpdeb", "sb3-sac", "sb3-ppo")
             or any(r["system"] == s for r in results)]
    lines = ["| task | " + " | ".join(f"{SYSTEMS[s]} training | {SYSTEMS[s]} evaluation"
                                        for s in shown)
             + " | SAC at 1M (source) | TPDEB median / SAC 1M | TPDEB seeds at or above "
             "| goal (median) |",
             "|---|" + "---|---|" * len(shown) + "---|---|---|---|"]
    for env_id in envs:
        row, ours = [env_id], {}
        for system in shown:
            runs = [r for r in results if r["env_id"] == env_id and r["system"] == system]
            if not runs:
                row += ["—", "—"]
                continue
            mark = final_mark(runs)
            train, ev = at(runs, mark, "train"), at(runs, mark, "eval")
            ours = {"training": train, "evaluation": ev} if system == "tpdeb" else ours
            show = whole if system == "tpdeb" else cell
            row += [show(train), show(ev)]
        bar, source = SAC_1M[env_id]
        kind = SAC_KIND[source]
        mine = ours[kind] if ours else []
        ratio = f"{statistics.median(mine) / bar:.2f} ({kind})" if mine else "—"
        above = f"{sum(v >= bar for v in mine)} of {len(mine)}" if mine else "—"
        row += [f"{bar:,} ({source})", ratio, above, goal(mine, bar)]
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines)


def marks_table(results: list[dict], envs: list[str]) -> str:
    """TPDEB's training (and evaluation) return at each mark, with its steps."""
    runs_of = {e: [r for r in results if r["env_id"] == e and r["system"] == "tpdeb"]
               for e in envs}
    marks = sorted({m for runs in runs_of.values() for r in runs for m in r["marks"]}, key=float)
    lines = ["| task | " + " | ".join(f"{float(m) / 60:g} min" for m in marks)
             + " | env steps in the budget | startup and shutdown |",
             "|---|" + "---|" * len(marks) + "---|---|"]
    for env_id, runs in runs_of.items():
        if not runs:
            continue
        cells = []
        for m in marks:
            train, ev = at(runs, m, "train"), at(runs, m, "eval")
            cells.append(f"{statistics.mean(train):,.0f} (eval {statistics.mean(ev):,.0f})"
                         if train and ev else "—")
        steps = statistics.mean(r["steps"] for r in runs)
        overhead = statistics.mean(r["wall_s"] - r["train_s"] for r in runs)
        lines.append(f"| {env_id} ({seeds(len(runs))}) | " + " | ".join(cells)
                     + f" | {steps / 1e6:.2f}M | {overhead:.0f} s |")
    return "\n".join(lines)


def reach_table(results: list[dict], envs: list[str]) -> str:
    """How long each system needs to reach the other's end-of-budget training return: a
    description, no verdict (the peers ran one seed: no spread to judge by)."""
    lines = ["| task | peer | peer's return at the end | TPDEB reaches it after | TPDEB's return "
             "at the end | peer reaches it after |", "|---|---|---|---|---|---|"]
    for env_id in envs:
        ours = [r for r in results if r["env_id"] == env_id and r["system"] == "tpdeb"]
        for system in SYSTEMS:
            theirs = [r for r in results if r["env_id"] == env_id and r["system"] == system]
            if system == "tpdeb" or not ours or not theirs:
                continue
            their_end = statistics.mean(at(theirs, final_mark(theirs), "train") or [np.nan])
            our_end = statistics.mean(at(ours, final_mark(ours), "train") or [np.nan])
            lines.append(f"| {env_id} | {SYSTEMS[system]} | {their_end:,.0f} | "
                         f"{time_to(ours, their_end)} | {our_end:,.0f} | "
                         f"{time_to(theirs, our_end)} |")
    return "\n".join(lines)


def figure(results: list[dict], env_id: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.4, 3.8))
    for n, (system, name) in enumerate(SYSTEMS.items()):
        runs = [r for r in results if r["env_id"] == env_id and r["system"] == system]
        if runs:
            grid, mean, std = mean_curve(runs)
            band(ax, grid / 60, mean, std, f"C{n}", f"{name} ({seeds(len(runs))})")
    bar, source = SAC_1M[env_id]
    ax.axhline(bar, color="grey", lw=0.8, ls="--", label=f"SAC at 1M steps ({source})")
    ax.set_title(env_id)
    ax.set_xlabel("wall-clock minutes on two cores")
    ax.set_ylabel("training return")
    ax.legend(fontsize=7)
    save(fig, path)


def report(directory: Path, envs: list[str]) -> None:
    results = load(directory)
    if not results:
        print(f"no finished runs in {directory}")
        return
    tag = directory.relative_to(ROOT / "docs" / "data")
    present = [e for e in envs if any(r["env_id"] == e for r in results)]
    text = "\n\n".join([
        "Return after the budget on two cores (training: mean of the episodes ending in its "
        "last 10 %; evaluation: the policy at the end, 10 deterministic episodes). The goal, "
        "TPDEB at or above SAC's published return at 1M env steps, is judged on TPDEB's median "
        "over its seeds, like for like (training against CleanRL's training return, evaluation "
        "against the zoo's evaluated model). The peers ran one seed each: they are compared "
        "descriptively, with no verdict.",
        budget_table(results, present), "TPDEB along the way:", marks_table(results, present),
        "Time to reach the other's return (mean smoothed curve over seeds):",
        reach_table(results, present),
        "Where and when each task's runs were made (a race's runs share one sitting):",
        sitting_table(results, present)])
    for env_id in present:
        image = ROOT / "docs" / "img" / tag / f"{env_id}.png"
        figure(results, env_id, image)
        text += f"\n\n![{env_id}](img/{tag}/{env_id}.png)"
    print(text)
    if str(tag) == "race" and replace_between(ROOT / "docs" / "RESULTS.md", BEGIN, END, text):
        print("\nupdated docs/RESULTS.md")


def tuning_table(directory: Path) -> str:
    """The race presets' tuning runs (docs/data/race-tune/{variant}/tpdeb/*.json), one row per
    run: the variant's settings over the task's race preset as it was then, and where the run
    stood at its marks."""
    rows = []
    for path in sorted(directory.glob("*/tpdeb/*.json")):
        run = json.loads(path.read_text())
        settings = " + ".join(run.get("overrides", [])) or "—"
        for mark, at in run["marks"].items():
            ev = at.get("eval", {}).get("mean_return")
            rows.append((run["env_id"], path.parts[-3], settings, run["seed"],
                         f"{float(mark) / 60:g}", f"{at['steps']:,}",
                         f"{at['train_return']:,.0f}", f"{ev:,.0f}" if ev is not None else "—"))
    rows.sort(key=lambda r: (r[0], r[1] != "preset", r[1], r[3], float(r[4])))
    head = ("| task | variant | settings | seed | minutes | env steps | training return | "
            "evaluation |\n|---|---|---|---|---|---|---|---|")
    return "\n".join([head, *("| " + " | ".join(map(str, r)) + " |" for r in rows)])


def tuning_report(directory: Path) -> None:
    if not any(directory.glob("*/tpdeb/*.json")):
        print(f"no finished tuning runs in {directory}")
        return
    text = tuning_table(directory)
    print(text)
    if replace_between(ROOT / "docs" / "RESULTS.md", TUNE_BEGIN, TUNE_END, text):
        print("\nupdated docs/RESULTS.md (race presets' tuning runs)")
