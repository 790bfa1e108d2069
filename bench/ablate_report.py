"""docs/ABLATIONS.md and docs/img/ablation/*.png from the ablation grid's result files
(`python bench/ablate.py --report`): per study the paper's statement, a table, curves (mean ±
std over seeds of the 20-point moving average, as the paper plots) and the verdict, computed."""

from __future__ import annotations

import json
import statistics
import textwrap
from collections import Counter
from pathlib import Path

import numpy as np
from ablate import Cell, Study, is_preset, preset_values, studies  # noqa: I001  (bench/ is on sys.path)
from paper import result_path
from paper_report import VERDICT, cell, compare, mean_curve, seeds
from runs import ROOT

from tpdeb.services.plot import band, label_axes, save, smooth

DOC = ROOT / "docs" / "ABLATIONS.md"
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
    "priority": "The abstract: “trajectory-level prioritization captures high-quality samples "
                "more effectively than step-wise methods.”",
    "kl": "The abstract: “KL-regularization enhances stability across asynchronous updates.”",
}


def cell_runs(study: Study, env_id: str, c: Cell, preset: dict) -> list[dict]:
    tag = "paper" if is_preset(c, preset) else f"ablation/{study.name}/{c.slug}"
    paths = [result_path(tag, env_id, "tpdeb", 1_000_000, s) for s in study.seeds]
    return [json.loads(p.read_text()) for p in paths if p.exists()]


def training(runs: list[dict]) -> list[float]:
    return [r["final_return"] for r in runs]


def evaluation(runs: list[dict]) -> list[float]:
    return [r["eval"]["mean_return"] for r in runs if r.get("eval")]


def fall(runs: list[dict]) -> float:
    """How far the smoothed mean curve ends below its peak (0: it ends at its best)."""
    _, mean, _ = mean_curve(runs)
    return float(mean.max() - mean[-1])


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


def marginals(means: dict[str, float], part: int) -> list[tuple[str, float]]:
    """Per value of one buffer axis (0: N_u, 1: N_p), in the study's order, the mean over the
    other axis of the training return divided by the best cell's."""
    top = max(means.values())
    by_value: dict[str, list[float]] = {}
    for label, mean in means.items():
        by_value.setdefault(label.split(",")[part].split("=")[1], []).append(mean / top)
    return [(value, statistics.mean(v)) for value, v in by_value.items()]


def verdict(study: Study, by_env: dict[str, list[tuple[str, list[dict]]]]) -> str:
    """What the runs say of the paper's statement, with the numbers; '' with too few runs."""
    lines = []
    for env_id, rows in by_env.items():
        rows = [(label, runs) for label, runs in rows if runs]
        if len(rows) < 2:
            continue
        means = {label: statistics.mean(training(runs)) for label, runs in rows}
        best = max(means, key=means.get)
        if study.name == "zeta":
            lines.append(f"{env_id}: the best ζ is {best.split('=')[1]} ({means[best]:,.0f}); "
                         + "; ".join(f"{k.split('=')[1]}: {v:,.0f}" for k, v in means.items()))
            runs = dict(rows)
            if "zeta=0.2" in runs and best != "zeta=0.2":
                lines.append(versus(env_id, runs[best], runs["zeta=0.2"],
                                    f"ζ {best.split('=')[1]} against ζ 0.2:"))
        elif study.name == "tau":
            lines.append(f"{env_id}: fall of the mean curve from its peak by the end: "
                         + "; ".join(f"τ {label.split('=')[1]}: {fall(runs):,.0f}"
                                     for label, runs in rows)
                         + f"; the best τ is {best.split('=')[1]} ({means[best]:,.0f})")
        elif study.name == "buffers":
            for part, axis in ((0, "N_u"), (1, "N_p")):
                lines.append(f"{env_id}: mean normalised return by {axis}: " + "; ".join(
                    f"{value} {m:.2f}" for value, m in marginals(means, part)))
            lines.append(f"{env_id}: the best cell is {best} ({means[best]:,.0f})")
        elif study.name == "workers":
            lines.append(f"{env_id}: at 1M steps " + "; ".join(
                f"{label.split('=')[1]} actors {means[label]:,.0f} in "
                f"{statistics.mean(r['wall_s'] for r in runs) / 60:.1f} min"
                for label, runs in rows))
        elif study.name in ("priority", "kl"):
            (a, ours), (b, theirs) = rows[0], rows[1]
            lines.append(versus(env_id, ours, theirs, f"{a} vs {b}:"))
    return "\n".join(f"- {line}" for line in lines)


def section(study: Study, presets: dict[str, dict]) -> str:
    by_env = {env_id: [(c.label, cell_runs(study, env_id, c, presets[env_id]))
                       for c in study.cells] for env_id in study.envs}
    out = [f"## {study.name}: {study.figure}", "",
           textwrap.fill(f"The paper: {PAPER[study.name]}", 98), "",
           f"`python bench/ablate.py --studies {study.name}` "
           f"({seeds(len(study.seeds))}: {', '.join(map(str, study.seeds))})", ""]
    if not any(runs for rows in by_env.values() for _, runs in rows):
        return "\n".join(out + ["No runs yet."])
    for env_id, rows in by_env.items():
        out += [f"**{env_id}**", "", table(rows, "fall from peak" if study.name == "tau" else ""),
                ""]
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
    lines = verdict(study, by_env)
    out += ["What the runs say:", "", lines or "- too few runs for a verdict yet."]
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
standard deviation.

    python bench/ablate.py            # runs what is missing (resumable; many hours)
    python bench/ablate.py --plan     # which runs exist
    python bench/ablate.py --report   # rewrites this page and docs/img/ablation/
"""


def report(runs) -> None:
    """Rewrite docs/ABLATIONS.md from the result files present (`runs`: the plan)."""
    IMAGES.mkdir(parents=True, exist_ok=True)
    all_studies = studies()
    presets = {env_id: preset_values(env_id) for s in all_studies.values() for env_id in s.envs}
    made = [json.loads(r.path.read_text()) for r in runs if r.path.exists()]
    codes = sorted({m.get("code", "?") for m in made})
    hosts = Counter(m.get("host", "the 2-core machine (the learner on its CPU)") for m in made)
    parts = [HEADER, f"Runs present: {len(made)} of {len(runs)}"
             + (f", made on commit{'s' * (len(codes) > 1)} {', '.join(codes)}" if codes else "")
             + "".join(f"; {n} on {host}" for host, n in hosts.most_common()) + "."]
    parts += [section(study, presets) for study in all_studies.values()]
    DOC.write_text("\n\n".join(parts) + "\n")
    print(f"wrote {DOC}")
