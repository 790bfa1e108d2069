"""docs/ABLATIONS.md and docs/img/ablation/*.png from the ablation grid's result files
(`python bench/ablate.py --report`): per study the paper's statement, a table, curves (mean ±
std over seeds of the 20-point moving average, as the paper plots) and the verdict, computed."""

from __future__ import annotations

import json
import statistics
import textwrap
from collections import Counter
from itertools import pairwise
from pathlib import Path

import numpy as np
import provenance
from ablate import Cell, Study, preset_values, studies, tag_of  # noqa: I001  (bench/ is on sys.path)
from paper import result_path
from paper_report import (
    NOT_JUDGED,
    VERDICT,
    against_bar,
    cell,
    compare,
    difference,
    gap_cell,
    grows,
    judgement,
    mean_curve,
    outcome,
    replace_between,
    seeds,
    spread_test,
)
from provenance import commit_of
from runs import ROOT

from tpdeb.services.plot import band, label_axes, save, smooth

DOC = ROOT / "docs" / "ABLATIONS.md"
RESULTS = ROOT / "docs" / "RESULTS.md"
SUMMARY = "<!-- ablations:begin -->", "<!-- ablations:end -->"
IMAGES = ROOT / "docs" / "img" / "ablation"
WINDOW = 20

PAPER = {
    "zeta": "“As ζ increases […] performance exhibits an initial increase followed by a decline "
            "[…] ζ = 0.2 is the optimal choice for the Ant-v2 task”; with ζ = 0 it degrades to a "
            "standard policy gradient method; the policy loss decreases fastest at ζ = 0.2.",
    "tau": "“When τ is 0.01, 0.05, or 0.10, the robot’s performance drops sharply in the "
           "mid-training phase […] when τ = 0.001 the training remains stable but the "
           "performance is limited.”",
    "buffers": "“Overall, increasing the replay Buffer size improves performance, but an "
               "excessively large prioritized Buffer can lead to performance degradation due to "
               "the difficulty of learning from outdated experiences.”",
    "workers": "“A greater number of workers can increase sample throughput, enabling the robot "
               "to achieve better performance in a shorter period. However, as the number of "
               "workers increases, the performance gains diminish.”",
    "priority": "its abstract: “trajectory-level prioritization captures high-quality samples "
                "more effectively than step-wise methods.”",
    "kl": "its abstract: “KL-regularization enhances stability across asynchronous updates.”",
}


CLAIM = {
    "zeta": "a best ζ inside the range, at 0.2, above ζ 0",
    "tau": "τ ≥ 0.01 collapses mid-training; τ 0.001 stable but limited",
    "buffers": "a larger uniform buffer helps; too large a prioritised one hurts",
    "workers": "more workers, better sooner, with diminishing gains",
    "priority": "trajectory priority above step priority",
    "kl": "the KL term makes training more stable",
}


NOTES = {
    "buffers": "N_u is the uniform buffer's capacity in env steps; the paper's prioritised "
               "capacities, in steps, become capacities in whole fragments of the preset's "
               "length (64 steps). One seed per cell: a cell's value carries that seed's noise "
               "and shows no spread, so no part of the statement is judged; the lines below "
               "give directions only.",
    "priority": "Step priority is PER over single transitions (the PPO+PER baseline's sampler) "
                "inside TPDEB: B_p's share of a batch is as many single-step draws as the "
                "trajectory sampler's fragments hold steps, each weighted by its own importance "
                "weight. The learner receives every fragment a draw hit, whole, with a per-step "
                "weight matrix: V-trace needs each drawn step's suffix. With the presets' batch "
                "of 8 fragments of 64 steps and ζ 0.2, B_p's share is 2 fragments with trajectory "
                "priority and 128 draws spread over up to all 64 of B_p's fragments with step "
                "priority, so each update costs more. The verdict reads the return per env "
                "step; what each costs is a line of its own.",
    "kl": "kl=preset is each task's own KL term: Ant's preset keeps the fixed λ_kl = 0.01, "
          "Hopper's adapts λ_kl to hold KL(μ‖π_θ) at 0.04; kl=off is λ_kl = 0 with no target. "
          "\"Falls from its peak\" is each seed's smoothed curve's fall by the end, as a "
          "fraction of its peak. At 1M steps the learning rate anneals to 0, which bounds the "
          "learner's drift by itself; runs longer than the budget a preset was tuned for are "
          "where the KL term may matter most (not judged here): RESULTS (\"Runs longer than "
          "the budget the preset was tuned for\") has HalfCheetah with KL(μ‖π_θ) held at 0.2 "
          "going over 12M steps from about 6,700 and 6,500 in the first 10 % of its kept curves "
          "to 10,570 and 10,842 in the last (`docs/data/tune/hc-long-klt0.2/`), where the fixed "
          "λ_kl = 0.01 fell (6,402 → 3,511 over an hour, read from that run's log, not kept; "
          "5,536 → 2,201 under half an hour of faults, `docs/data/chaos-30-fixed-kl.json`). "
          "Those runs are no matched ablation (tuning seeds, other lengths), so the verdict below "
          "reads the 1M-step runs alone.",
    "workers": "On two cores every actor shares the machine with the learner and the other "
               "actors. Against env steps the runs show what more workers give per sample; "
               "against wall-clock, what they give on this machine, which is the honest "
               "measure here: the actors do not add cores. Each run is timed, with nothing else "
               "running, and every cell is the study's own run (2 actors is the preset, run "
               "again rather than taken from the comparison grid), so all four ran on the same "
               "code.",
}

def cell_runs(study: Study, env_id: str, c: Cell, preset: dict) -> list[dict]:
    tag = tag_of(study, c, preset)
    paths = [result_path(tag, env_id, "tpdeb", 1_000_000, s) for s in study.seeds]
    return [json.loads(p.read_text()) for p in paths if p.exists()]


def training(runs: list[dict]) -> list[float]:
    return [r["final_return"] for r in runs]


def evaluation(runs: list[dict]) -> list[float]:
    return [r["eval"]["mean_return"] for r in runs if r.get("eval")]


def peak_and_end(runs: list[dict]) -> tuple[float, float]:
    """The smoothed mean curve's peak and its last value."""
    _, mean, _ = mean_curve(runs)
    return float(mean.max()), float(mean[-1])


def fall(runs: list[dict]) -> float:
    """How far the smoothed mean curve ends below its peak (0: it ends at its best)."""
    peak, end = peak_and_end(runs)
    return peak - end


def clock_curve(run: dict) -> tuple[np.ndarray, np.ndarray]:
    """The run's smoothed return against the learner's training seconds."""
    steps, returns = np.array(run["curve"], dtype=np.float64).T
    clock = np.array(run["clock"], dtype=np.float64)
    return np.interp(steps, clock[:, 0], clock[:, 1]), smooth(returns, WINDOW)


def table(rows: list[tuple[str, list[dict]]], extra: str = "") -> str:
    out = ["| setting | training return | evaluation | mean over training | "
           f"{extra + ' | ' if extra else ''}seeds |",
           "|---|---|---|---|" + ("---|" if extra else "") + "---|"]
    for label, runs in rows:
        over = f"{np.mean(mean_curve(runs)[1]):,.0f}" if runs else "—"
        more = f"{fall(runs):,.0f} | " if extra and runs else ("— | " if extra else "")
        out.append(f"| {label} | {cell(training(runs))} | {cell(evaluation(runs))} | {over} | "
                   f"{more}{len(runs)} |")
    return "\n".join(out)


def curves(rows: list[tuple[str, list[dict]]], title: str, path: Path, key: str = "curve",
           ylabel: str = "episodic return") -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.4, 3.8))
    for n, (label, runs) in enumerate(rows):
        runs = [{**r, "curve": r[key]} for r in runs if r.get(key)]
        if runs:
            grid, mean, std = mean_curve(runs)
            band(ax, grid, mean, std, f"C{n}", f"{label} ({seeds(len(runs))})")
    label_axes(ax, title, ylabel)
    save(fig, path)


def clock_figure(rows: list[tuple[str, list[dict]]], title: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.4, 3.8))
    for n, (label, runs) in enumerate(rows):
        runs = [r for r in runs if r.get("clock")]
        if not runs:
            continue
        end = min(clock_curve(r)[0][-1] for r in runs)
        grid = np.linspace(0.0, end, 200)
        values = np.array([np.interp(grid, *clock_curve(r)) for r in runs])
        band(ax, grid / 60.0, values.mean(0), values.std(0), f"C{n}",
             f"{label} ({seeds(len(runs))})")
    label_axes(ax, title, "episodic return")
    ax.set_xlabel("training minutes (2 cores)")
    save(fig, path)


def heatmap(grid: dict[tuple[str, str], float], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    nus = list(dict.fromkeys(k[0] for k in grid))
    nps = list(dict.fromkeys(k[1] for k in grid))
    values = np.array([[grid.get((nu, np_), np.nan) for np_ in nps] for nu in nus])
    fig, ax = plt.subplots(figsize=(5.0, 4.0))
    image = ax.imshow(values, cmap="viridis", vmin=0.0, vmax=1.0)
    ax.set_xticks(range(len(nps)), nps)
    ax.set_yticks(range(len(nus)), nus)
    ax.set_xlabel("N_p (steps)")
    ax.set_ylabel("N_u (steps)")
    for i in range(len(nus)):
        for j in range(len(nps)):
            if np.isfinite(values[i, j]):
                ax.text(j, i, f"{values[i, j]:.2f}", ha="center", va="center", color="w")
    fig.colorbar(image, ax=ax, label="training return / best cell")
    save(fig, path)


def versus(env_id: str, ours: list[dict], theirs: list[dict], what: str) -> str:
    outcome = compare(training(ours), training(theirs))
    return (f"{env_id}: {what} {cell(training(ours))} against {cell(training(theirs))}: "
            f"{VERDICT[outcome]}")


def cost(runs: list[dict]) -> str:
    """The learner's fastest time per update and minutes per run over the seeds, with the
    range: a run that shared the machine with another is slower, never faster, so the fastest
    is the nearest to the machine alone (and the range shows how far the others were from it);
    with the commits the runs ran on: a learner made faster between two commits shows here as
    much as a setting."""
    update = [r["diagnostics"]["perf/update_ms"] for r in runs
              if "perf/update_ms" in r.get("diagnostics", {})]
    minutes = sorted(r["wall_s"] / 60 for r in runs)
    codes = sorted({commit_of(r) for r in runs})
    per_update = f"{min(update):.0f} ms per update, " if update else ""
    spread = (f"; {minutes[0]:.1f}–{minutes[-1]:.1f}"
              if f"{minutes[0]:.1f}" != f"{minutes[-1]:.1f}" else "")
    return (f"{per_update}{minutes[0]:.1f} min per run (the fastest of {len(minutes)}{spread}; "
            f"commit{'s' * (len(codes) > 1)} {', '.join(codes)})")


def marginals(means: dict[str, float], part: int, scale: float | None = None
              ) -> list[tuple[str, float]]:
    """Per value of one buffer axis (0: N_u, 1: N_p), in the study's order, the mean over the
    other axis of the cells' values divided by `scale` (default: the best cell's)."""
    top = scale or max(means.values())
    by_value: dict[str, list[float]] = {}
    for label, mean in means.items():
        by_value.setdefault(label.split(",")[part].split("=")[1], []).append(mean / top)
    return [(value, statistics.mean(v)) for value, v in by_value.items()]


STALENESS = (("replay/sample_age_updates", "a sampled fragment's age in learner updates", ",.0f"),
             ("losses/kl_behaviour", "KL(μ‖π_θ) to the policies that made the data", ".2f"))


def staleness(env_id: str, rows: list[tuple[str, list[dict]]]) -> list[str]:
    """How old the buffers' data is when sampled, per axis, from the runs' end-of-run
    diagnostics: the paper's reading of a too-large buffer ("outdated experiences")."""
    lines = []
    for key, what, fmt in STALENESS:
        cells = {label: statistics.mean(r["diagnostics"][key] for r in runs)
                 for label, runs in rows if all(key in r.get("diagnostics", {}) for r in runs)}
        if len(cells) < 2:
            continue
        lines += [f"{env_id}: {what} at the end, by {axis}: " + "; ".join(
            f"{value} {format(m, fmt)}" for value, m in marginals(cells, part, scale=1.0))
            for part, axis in ((0, "N_u"), (1, "N_p"))]
    return lines


def verdict(study: Study, by_env: dict[str, list[tuple[str, list[dict]]]],
            presets: dict[str, dict]) -> str:
    """What the runs say of the paper's statement, with the numbers; '' with too few runs."""
    lines = []
    for env_id, rows in by_env.items():
        rows = [(label, runs) for label, runs in rows if runs]
        if len(rows) < 2:
            continue
        means = {label: statistics.mean(training(runs)) for label, runs in rows}
        best = max(means, key=means.get)
        if study.name == "zeta":
            lines.append(f"{env_id}: the best ζ by mean is {best.split('=')[1]} "
                         f"({means[best]:,.0f}); " + "; ".join(
                             f"{k.split('=')[1]}: {v:,.0f}" for k, v in means.items()))
            runs = dict(rows)
            if "zeta=0.2" in runs and best != "zeta=0.2":
                lines.append(versus(env_id, runs[best], runs["zeta=0.2"],
                                    f"ζ {best.split('=')[1]} against ζ 0.2:"))
        elif study.name == "tau":
            lines.append(f"{env_id}: fall of the mean curve from its peak by the end: "
                         + "; ".join(f"τ {label.split('=')[1]}: {fall(runs):,.0f}"
                                     for label, runs in rows)
                         + f"; the best τ by mean is {best.split('=')[1]} ({means[best]:,.0f})")
        elif study.name == "buffers":
            for part, axis in ((0, "N_u"), (1, "N_p")):
                lines.append(f"{env_id}: mean normalised return by {axis}: " + "; ".join(
                    f"{value} {m:.2f}" for value, m in marginals(means, part)))
            lines.append(f"{env_id}: the best cell by mean is {best} ({means[best]:,.0f})")
            lines += staleness(env_id, rows) + own_buffers(study, env_id, presets[env_id])
        elif study.name == "workers":
            lines.append(f"{env_id}: at 1M steps " + "; ".join(
                f"{label.split('=')[1]} actors {means[label]:,.0f} in "
                f"{statistics.mean(r['wall_s'] for r in runs) / 60:.1f} min"
                for label, runs in rows))
        elif study.name in ("priority", "kl"):
            (a, ours), (b, theirs) = rows[0], rows[1]
            lines.append(versus(env_id, ours, theirs, f"{a} vs {b}:"))
            if study.name == "priority":
                lines.append(f"{env_id}: what each costs: " + "; ".join(
                    f"{label.split('=')[1]} {cost(runs)}" for label, runs in rows))
    return "\n".join(f"- {line}" for line in lines)


COLLAPSE = 0.2  # a curve ending this fraction or more below its peak collapsed
LEARNED = 0.5  # "stable" needs at least this fraction of the preset's own return on the task


def peak_fall(runs: list[dict]) -> float:
    """The fall of the smoothed mean curve from its peak by the end, as a fraction of the peak."""
    peak, end = peak_and_end(runs)
    return (peak - end) / peak if peak > 0 else 0.0


def seed_falls(runs: list[dict]) -> list[float]:
    """Each seed's smoothed curve's fall from its peak by the end, as a fraction of its peak."""
    return [peak_fall([r]) for r in runs]


def collapsed(falls: list[float]) -> int | None:
    """+1 where the seeds' falls are a collapse beyond their spread (mean − std above
    `COLLAPSE`), −1 where they stay below it beyond the spread (mean + std under it), 0 within
    the spread; None with one seed."""
    return against_bar(falls, COLLAPSE)


def at_minutes(runs: list[dict], minutes: float) -> list[float]:
    """Each run's smoothed return after `minutes` of the learner's clock."""
    return [float(np.interp(60.0 * minutes, *clock_curve(r))) for r in runs]


def value(label: str) -> float:
    """The number a cell's label sets: "tau=0.05" → 0.05, "actors=4" → 4."""
    return float(label.split("=")[1])


def above_all(name: str, ours: list[float], others: dict[str, list[float]]
              ) -> tuple[str, bool | None]:
    """Whether `ours` is higher than each of `others` beyond the seed spread (`compare`): the
    verdict per rival and whether it holds against every one; None while one rests on one
    seed."""
    results = {k: compare(ours, v) for k, v in others.items()}
    text = f"{name} {cell(ours)} against " + ", ".join(
        f"{k} {cell(v)} ({VERDICT[results[k]]})" for k, v in others.items())
    if None in results.values():
        return text, None
    return text, all(r == 1 for r in results.values())


def zeta_parts(runs: dict[str, list[dict]], env_id: str, own: list[dict]
               ) -> list[tuple[str, bool | None]]:
    """A peak inside the range: the ζ with the highest mean is not an end and is higher than
    both ends beyond the seed spread. ζ 0.2 the best: higher than every other ζ beyond the
    spread (the paper's "optimal choice"; level with another is not the best). ζ 0.2 above
    ζ 0, beyond the spread."""
    means = {k: statistics.mean(training(v)) for k, v in runs.items()}
    best = max(means, key=means.get)
    ends = (min(runs, key=value), max(runs, key=value))
    parts = []
    if best in ends:
        parts.append((f"a peak inside the range: the highest mean is {best}, an end", False))
    else:
        text, ok = above_all(best, training(runs[best]),
                             {k: training(runs[k]) for k in ends})
        parts.append((f"a peak inside the range, above both ends beyond the seed spread: "
                      f"{text}", ok))
    if "zeta=0.2" in runs:
        text, ok = above_all("zeta=0.2", training(runs["zeta=0.2"]),
                             {k: training(v) for k, v in runs.items() if k != "zeta=0.2"})
        parts.append((f"ζ 0.2 the best, above every other ζ beyond the seed spread: {text}", ok))
    if "zeta=0.2" in runs and "zeta=0" in runs:
        parts.append(spread_test("ζ 0.2 above ζ 0 (the plain policy gradient)", "zeta=0.2",
                                 training(runs["zeta=0.2"]), "zeta=0", training(runs["zeta=0"])))
    return parts


def tau_parts(runs: dict[str, list[dict]], env_id: str, own: list[dict]
              ) -> list[tuple[str, bool | None]]:
    """τ ≥ 0.01 falls sharply: more than half of those τ collapse beyond the seed spread
    (`collapsed`: each seed's fall from its peak, mean − std ≥ `COLLAPSE`). The smallest τ
    stable: it learned (its mean return at least `LEARNED` of the preset's own runs' on the
    task: a run that barely learns has nothing to fall from) and its seeds stay below a
    collapse beyond the spread (mean + std under `COLLAPSE`). Limited: the τ with the highest
    mean above it beyond the spread."""
    falls = {k: seed_falls(v) for k, v in runs.items()}
    big = [k for k in runs if value(k) >= 0.01]
    verdicts = {k: collapsed(falls[k]) for k in big}
    fell = [k for k in big if verdicts[k] == 1]
    text = (f"τ ≥ 0.01 falls sharply mid-training (≥ {COLLAPSE:.0%} below its peak by the end, "
            f"beyond the seed spread): {len(fell)} of {len(big)} (" + "; ".join(
                f"τ {k.split('=')[1]} {cell(falls[k], '.0%')}" for k in big) + ")")
    one_seed = None in verdicts.values()
    parts = [(text + (f", {NOT_JUDGED}" if one_seed else ""),
              None if one_seed else len(fell) * 2 > len(big))]
    smallest = min(runs, key=value)
    stable = collapsed(falls[smallest])
    ours = statistics.mean(training(runs[smallest]))
    head = f"{smallest} stays stable: it falls {cell(falls[smallest], '.0%')}, "
    text = head + ("below a collapse beyond the seed spread" if stable == -1 else
                   "not below a collapse beyond the seed spread")
    if stable is None:
        parts.append((head + NOT_JUDGED, None))
    elif not own:
        parts.append((f"{text}; the preset's own runs on {env_id} are missing, so that it "
                      f"learned (at least {LEARNED:.0%} of their return) is not shown", False))
    else:
        preset = statistics.mean(training(own))
        learned = ours >= LEARNED * preset
        parts.append((f"{text}; it reached {ours:,.0f}, "
                      + (f"at least {LEARNED:.0%} of the preset's {preset:,.0f} on {env_id}"
                         if learned else
                         f"under {LEARNED:.0%} of the preset's {preset:,.0f} on {env_id}: too "
                         "little learning to call stable"),
                      learned and stable == -1))
    best = max(runs, key=lambda k: statistics.mean(training(runs[k])))
    if best != smallest:
        parts.append(spread_test(f"{smallest} limited", best, training(runs[best]), smallest,
                                 training(runs[smallest])))
    return parts


def by_axis(runs: dict[str, list[dict]], part: int) -> dict[str, list[float]]:
    """Per value of one buffer axis (0: N_u, 1: N_p), in the study's order, per seed the mean
    training return over the other axis's cells (the seeds every one of those cells ran)."""
    cells: dict[str, list[dict[int, float]]] = {}
    for label, rs in runs.items():
        cells.setdefault(label.split(",")[part].split("=")[1], []).append(
            {r.get("seed", i): r["final_return"] for i, r in enumerate(rs)})
    out = {}
    for axis_value, seeds_of in cells.items():
        common = set.intersection(*(set(c) for c in seeds_of))
        out[axis_value] = [statistics.mean(c[s] for c in seeds_of) for s in sorted(common)]
    return out


def buffer_parts(runs: dict[str, list[dict]], env_id: str, own: list[dict]
                 ) -> list[tuple[str, bool | None]]:
    """A larger uniform buffer does better: the largest N_u's return (mean over the N_p cells,
    per seed) above the smallest's beyond the seed spread. The largest prioritised buffer does
    worse: the N_p with the highest such mean is a smaller one, above the largest beyond the
    spread. A cell with one seed has no spread: then neither part is judged and the direction
    is shown alone."""
    means = {k: statistics.mean(training(v)) for k, v in runs.items()}
    nu, np_ = marginals(means, 0), marginals(means, 1)
    top = max(np_, key=lambda x: x[1])
    direction = (f"N_u {nu[0][0]} {nu[0][1]:.2f} → {nu[-1][0]} {nu[-1][1]:.2f}",
                 f"N_p {np_[-1][0]} {np_[-1][1]:.2f} against the highest, {top[0]} "
                 f"{top[1]:.2f}")
    if any(len(v) < 2 for v in runs.values()):
        why = "normalised to the best cell; one seed per cell: no spread, the direction alone"
        return [(f"a larger uniform buffer does better: {direction[0]} ({why})", None),
                (f"the largest prioritised buffer does worse than a smaller one: "
                 f"{direction[1]} ({why})", None)]
    u, q = by_axis(runs, 0), by_axis(runs, 1)
    smallest, largest = list(u)[0], list(u)[-1]
    parts = [spread_test("a larger uniform buffer does better", f"N_u {largest}", u[largest],
                         f"N_u {smallest}", u[smallest])]
    biggest = list(q)[-1]
    best = max(q, key=lambda k: statistics.mean(q[k]))
    if best == biggest:
        parts.append((f"the largest prioritised buffer does worse than a smaller one: N_p "
                      f"{biggest} {cell(q[biggest])} has the highest mean", False))
    else:
        parts.append(spread_test("the largest prioritised buffer does worse than a smaller one",
                                 f"N_p {best}", q[best], f"N_p {biggest}", q[biggest]))
    return parts


def worker_parts(runs: dict[str, list[dict]], env_id: str, own: list[dict]
                 ) -> list[tuple[str, bool | None]]:
    """Better sooner: the most workers above the fewest after the same training minutes,
    beyond the seed spread. The gains diminish: the first step's gain is a gain beyond the
    spread (`compare`) and exceeds the last step's by more than the two gains' combined spread
    (`grows`); the steps between are shown, not judged."""
    runs = {k: v for k, v in runs.items() if all(r.get("clock") for r in v)}
    if len(runs) < 2:
        return []
    counts = sorted(runs, key=value)
    end = min(clock_curve(r)[0][-1] for v in runs.values() for r in v) / 60.0
    at = {k: at_minutes(runs[k], end) for k in counts}
    parts = [spread_test(f"more workers, better sooner (after {end:.1f} training minutes)",
                         counts[-1], at[counts[-1]], counts[0], at[counts[0]])]
    if len(counts) >= 3:
        gains = [difference(at[b], at[a]) for a, b in pairwise(counts)]
        first = compare(at[counts[1]], at[counts[0]])
        shrink, spread = grows(gains[0], gains[-1])
        text = (f"the gains diminish: {' → '.join(counts)} add "
                + ", ".join(gap_cell(g) for g in gains))
        if first is None or shrink is None:
            parts.append((f"{text}: {NOT_JUDGED}", None))
        else:
            parts.append((f"{text}; the first {'is' if first == 1 else 'is not'} a gain beyond "
                          f"the seed spread, and exceeds the last by "
                          f"{gains[0][0] - gains[-1][0]:+,.0f} against their combined spread of "
                          f"{spread:,.0f} ({VERDICT[shrink]})", first == 1 and shrink == 1))
    return parts


def pair_parts(runs: dict[str, list[dict]], env_id: str, own: list[dict]
               ) -> list[tuple[str, bool | None]]:
    (a, ours), (b, theirs) = list(runs.items())[:2]
    return [spread_test(f"{env_id}: {a} above {b}", a, training(ours), b, training(theirs))]


def kl_parts(runs: dict[str, list[dict]], env_id: str, own: list[dict]
             ) -> list[tuple[str, bool | None]]:
    """Stability: the return, and how far each seed's smoothed curve falls from its peak by the
    end. The KL term stabilises where the other falls further beyond the seed spread and its
    falls are a collapse beyond their spread (`collapsed`): small falls both ways leave
    nothing to stabilise."""
    (a, ours), (b, theirs) = list(runs.items())[:2]
    mine, other = seed_falls(ours), seed_falls(theirs)
    result = compare(other, mine)  # +1: the other falls further, beyond the spread
    text = (f"{env_id}: {a} falls less from its peak than {b}, which collapses (≥ "
            f"{COLLAPSE:.0%} beyond the seed spread): {cell(mine, '.0%')} against "
            f"{cell(other, '.0%')}, "
            + {1: "less", 0: "within the seed spread", -1: "more", None: NOT_JUDGED}[result])
    fell = collapsed(other) == 1
    if result == 1 and not fell:
        text += f", but {b}'s fall is not a collapse beyond the seed spread"
    return pair_parts(runs, env_id, own) + [
        (text, None if result is None else result == 1 and fell)]


PARTS = {"zeta": zeta_parts, "tau": tau_parts, "buffers": buffer_parts, "workers": worker_parts,
         "priority": pair_parts, "kl": kl_parts}


def statement_parts(study: Study, by_env: dict[str, list[tuple[str, list[dict]]]],
                    own: dict[str, list[dict]] | None = None
                    ) -> tuple[list[tuple[str, bool | None]], int]:
    """The parts of the paper's statement the runs present can judge, and how many runs are
    missing; `own`: per task the preset's own runs (the comparison grid's), for the parts
    that need a minimum of learning."""
    parts, missing = [], 0
    for env_id, rows in by_env.items():
        missing += sum(len(study.seeds) - len(r) for _, r in rows)
        runs = {label: r for label, r in rows if r}
        if len(runs) < 2:
            continue
        parts += PARTS[study.name](runs, env_id, (own or {}).get(env_id, []))
    return parts, missing


def holds(study: Study, by_env: dict[str, list[tuple[str, list[dict]]]],
          own: dict[str, list[dict]] | None = None) -> str:
    """Whether the paper's statement holds here, part by part, with the numbers
    (`paper_report.judgement`)."""
    return judgement(*statement_parts(study, by_env, own))


def glance(study: Study, by_env: dict[str, list[tuple[str, list[dict]]]],
           own: dict[str, list[dict]] | None = None) -> str:
    """The study's row of the summary table: the claim, its verdict and how many parts hold."""
    parts, missing = statement_parts(study, by_env, own)
    if not parts:
        here = "too few runs for a verdict yet"
    else:
        state = outcome(parts)
        unjudged = sum(ok is None for _, ok in parts)
        here = (f"{state}: {sum(ok is True for _, ok in parts)} of {len(parts)} parts"
                if state else f"not judged: {unjudged} of {len(parts)} parts rest on one seed "
                "(no spread)")
    if missing:
        here += f" (provisional: {missing} run{'s' * (missing != 1)} missing)"
    return f"| {study.name} | {study.figure} | {CLAIM[study.name]} | {here} |"


def glance_table(all_studies: dict[str, Study], by_study: dict[str, dict],
                 own: dict[str, dict[str, list[dict]]] | None = None) -> str:
    rows = [glance(s, by_study[s.name], (own or {}).get(s.name)) for s in all_studies.values()]
    return "\n".join(["| study | paper | its statement | here, at 1M env steps |",
                      "|---|---|---|---|", *rows])


def rows_of(study: Study, presets: dict[str, dict]) -> dict[str, list[tuple[str, list[dict]]]]:
    """Per task, each cell's label and its runs present."""
    return {env_id: [(c.label, cell_runs(study, env_id, c, presets[env_id]))
                     for c in study.cells] for env_id in study.envs}


def own_runs(study: Study, presets: dict[str, dict]) -> dict[str, list[dict]]:
    """Per task the preset's own runs on the study's seeds (the comparison grid's)."""
    return {env_id: cell_runs(study, env_id, Cell("preset"), presets[env_id])
            for env_id in study.envs}


def own_buffers(study: Study, env_id: str, preset: dict) -> list[str]:
    """A verdict line: where the task's preset sits on the grid, with its runs on the study's
    seeds (the comparison grid's); none while those runs are missing."""
    runs = cell_runs(study, env_id, Cell("preset"), preset)
    if not runs:
        return []
    n_u, n_p = preset["uniform_capacity_steps"], preset["prioritized_capacity"]
    return [f"{env_id}: the preset's own buffers, N_u {n_u:,} steps and N_p {n_p} fragments "
            f"({n_p * preset['fragment_len']:,} steps), on the same seed: "
            f"{statistics.mean(training(runs)):,.0f}"]


def section(study: Study, by_env: dict[str, list[tuple[str, list[dict]]]],
            presets: dict[str, dict], own: dict[str, list[dict]] | None = None) -> str:
    out = [f"## {study.name}: {study.figure}", "",
           textwrap.fill(f"The paper: {PAPER[study.name]}", 98), "",
           f"`python bench/ablate.py --studies {study.name}` "
           f"({seeds(len(study.seeds))}: {', '.join(map(str, study.seeds))})", ""]
    if study.name in NOTES:
        out += [textwrap.fill(NOTES[study.name], 98), ""]
    if not any(runs for rows in by_env.values() for _, runs in rows):
        return "\n".join(out + ["No runs yet."])
    for env_id, rows in by_env.items():
        falls = "fall from peak (return)" if study.name in ("tau", "kl") else ""
        out += [f"**{env_id}**", "", table(rows, falls), ""]
        if study.name != "buffers":  # sixteen curves: the heatmap instead
            image = IMAGES / f"{study.name}-{env_id}.png"
            curves(rows, f"{env_id}: {study.name}", image)
            out.append(f"![{study.name} {env_id}](img/ablation/{image.name})")
        if study.name == "zeta":
            image = IMAGES / f"zeta-policy-loss-{env_id}.png"
            curves(rows, f"{env_id}: policy loss by ζ", image, key="policy_loss",
                   ylabel="policy loss")
            out.append(f"![policy loss {env_id}](img/ablation/{image.name})")
        if study.name == "workers":
            image = IMAGES / f"workers-clock-{env_id}.png"
            clock_figure(rows, f"{env_id}: return against wall-clock", image)
            out.append(f"![workers {env_id}](img/ablation/{image.name})")
        if study.name == "buffers":
            done = {label: statistics.mean(training(runs)) for label, runs in rows if runs}
            top = max(done.values(), default=0.0)
            if top > 0:
                grid = {tuple(part.split("=")[1] for part in label.split(",")): value / top
                        for label, value in done.items()}
                image = IMAGES / f"buffers-heatmap-{env_id}.png"
                heatmap(grid, image)
                out.append(f"![buffers {env_id}](img/ablation/{image.name})")
        out.append("")
    lines = verdict(study, by_env, presets)
    out += ["What the runs say:", "", lines or "- too few runs for a verdict yet."]
    judged = holds(study, by_env, own)
    if judged:
        out += ["", judged]
    return "\n".join(out)


HEADER = """# Ablations: the paper's Section 3.2 and two claims of its abstract

Every run is a real `tpdeb-cluster` (router, replay server, learner, 2 actors × 4 envs unless the
study varies the actors) on a 2-core machine unless the line below says otherwise (the
workers study, timed, always on it), with the task's preset (`deploy/presets/`) and
one setting changed, for 1M env steps. Returns as in RESULTS: the training return is the mean
episodic return over the last 10 % of steps, the evaluation return the final checkpoint's over
10 deterministic episodes; "mean over training" is the mean of the smoothed mean curve (return
per env step); curves are mean ± std over seeds of the 20-point moving average. A run on the
preset's own settings is the comparison grid's (`docs/data/paper/`). Seeds 11–13 (buffers: 11),
never used for tuning. A difference counts where the means differ by more than the larger seed
standard deviation; a trend (gains that diminish) where the change between its ends exceeds their
combined spread (the root sum of squares of the seed standard deviations); a fall from the peak
is a collapse where its mean less its standard deviation is 20 % or more (each seed's smoothed
curve's fall by the end as a fraction of its peak; the tables' "fall from peak" column is the
mean curve's, in return). τ ≥ 0.01 "falls sharply" where more than half of those τ collapse;
the smallest τ is "stable" where its fall's mean plus its standard deviation is under 20 % and
it reached at least half the preset's training return (a run that barely learns has nothing to
fall from); "better sooner" compares the returns where the shortest run's learner clock ends.
A cell with one seed has no spread: its part reads "not judged", never a yes or no by its
direction.

    python bench/ablate.py            # runs what is missing (resumable; many hours)
    python bench/ablate.py --plan     # which runs exist
    python bench/ablate.py --report   # rewrites this page and docs/img/ablation/
"""


def header(doc: Path) -> str:
    """HEADER, with the count bench/provenance.py keeps under the page's title (if the page
    has one) carried over."""
    text = doc.read_text() if doc.exists() else ""
    begin, end = provenance.BEGIN, provenance.END
    if begin not in text or end not in text:
        return HEADER
    block = text[text.index(begin):text.index(end) + len(end)]
    title, rest = HEADER.split("\n", 1)
    return f"{title}\n\n{block}\n{rest}"


def elsewhere(made: list[tuple]) -> str:
    """Which cells' runs were made on another host than the 2-core machine (their files'
    `host`), e.g. " (there: zeta-0 seed 11, …)"; `made`: (run, its result) pairs."""
    named = sorted(f"{r.path.parent.name} seed {r.seed}" for r, m in made if m.get("host"))
    return f" (there: {', '.join(named)})" if named else ""


def report(runs) -> None:
    """Rewrite docs/ABLATIONS.md from the result files present (`runs`: the plan)."""
    IMAGES.mkdir(parents=True, exist_ok=True)
    all_studies = studies()
    presets = {env_id: preset_values(env_id) for s in all_studies.values() for env_id in s.envs}
    made = [(r, json.loads(r.path.read_text())) for r in runs if r.path.exists()]
    codes = sorted({commit_of(m) for _, m in made})
    hosts = Counter(m.get("host", "the 2-core machine (the learner on its CPU)")
                    for _, m in made)
    parts = [header(DOC), f"Runs present: {len(made)} of {len(runs)}"
             + (f", made on commit{'s' * (len(codes) > 1)} {', '.join(codes)} (as each file's "
                f"provenance names it: inferred from its start for runs made before that "
                f"record existed)" if codes else "")
             + "".join(f"; {n} on {host}" for host, n in hosts.most_common())
             + elsewhere(made) + "."]
    by_study = {s.name: rows_of(s, presets) for s in all_studies.values()}
    own = {s.name: own_runs(s, presets) for s in all_studies.values()}
    table = glance_table(all_studies, by_study, own)
    parts += [table] + [section(s, by_study[s.name], presets, own[s.name])
                        for s in all_studies.values()]
    DOC.write_text("\n\n".join(parts) + "\n")
    print(f"wrote {DOC}")
    if replace_between(RESULTS, *SUMMARY, f"{table}\n\nEach row's numbers: [ABLATIONS]"
                       f"(ABLATIONS.md), made by `python bench/ablate.py --report`."):
        print(f"wrote the summary in {RESULTS}")
