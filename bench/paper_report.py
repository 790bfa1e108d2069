"""Tables and figures of the paper comparison from the finished runs in docs/data/{tag}/.

Writes the part of docs/RESULTS.md between its `<!-- paper:begin -->` and `<!-- paper:end -->`
markers (the prose around them is kept) and one PNG of learning curves per task in
docs/img/paper/. Called by `python bench/paper.py --report`.
"""

from __future__ import annotations

import json
import statistics
from pathlib import Path

import numpy as np
import provenance  # noqa: I001  (bench/ is on sys.path)
from runs import ROOT

from tpdeb.services.plot import band, label_axes, save, smooth

# SB3-zoo tuned PPO's published 1M returns, CleanRL PPO's for Humanoid: the bar and the
# Table 2 thresholds.
THRESHOLDS = {"HalfCheetah-v5": 5819, "Hopper-v5": 2410, "Walker2d-v5": 3479, "Ant-v5": 1327,
              "Humanoid-v5": 716, "Swimmer-v5": 282}
# SAC's published returns at 1M env steps, the per-step moonshot and the race's goal: CleanRL's
# SAC (training return, v4, 3 seeds) where it reports the task, rl-baselines3-zoo's SAC model
# (evaluation, v3) elsewhere.
SAC_1M = {"HalfCheetah-v5": (9635, "CleanRL"), "Hopper-v5": (2310, "CleanRL"),
          "Walker2d-v5": (3591, "CleanRL"), "Ant-v5": (4616, "zoo"),
          "Humanoid-v5": (4996, "CleanRL"), "Swimmer-v5": (346, "zoo")}
# what each source's SAC figure is, so a comparison sets like against like
SAC_KIND = {"CleanRL": "training", "zoo": "evaluation"}
NAMES = {"tpdeb": "TPDEB", "impact": "IMPACT", "ppo-per": "PPO+PER"}
WINDOW = 20
BEGIN, END = "<!-- paper:begin -->", "<!-- paper:end -->"


def load(directory: Path) -> list[dict]:
    return [json.loads(p.read_text()) for p in sorted(directory.glob("*.json"))]


def seeds(n: int) -> str:
    return f"{n} seed" + "s" * (n != 1)


def cell(values: list[float], fmt: str = ",.0f") -> str:
    """Mean ± std over seeds (each as `fmt`: returns by default, ".0%" for fractions); a single
    run is its value alone (a spread of one is not zero)."""
    if not values:
        return "—"
    if len(values) == 1:
        return f"{values[0]:{fmt}} (n=1)"
    return (f"{statistics.mean(values):{fmt}} ± {statistics.stdev(values):{fmt}} "
            f"(n={len(values)})")


def mean_curve(runs: list[dict], points: int = 200):
    """(grid, mean, std) over seeds of the runs' smoothed curves on a common env-step grid."""
    end = min(max(s for s, _ in r["curve"]) for r in runs)
    grid = np.linspace(0.0, end, points)
    curves = []
    for r in runs:
        steps, returns = np.array(r["curve"], dtype=np.float64).T
        curves.append(np.interp(grid, steps, smooth(returns, WINDOW)))
    return grid, np.mean(curves, axis=0), np.std(curves, axis=0)


def steps_to(runs: list[dict], threshold: float) -> str:
    grid, mean, _ = mean_curve(runs)
    hit = np.flatnonzero(mean >= threshold)
    return f"{grid[hit[0]] / 1e3:,.0f}k" if hit.size else "not reached"


def tables(results: list[dict], envs: list[str], algos: list[str]) -> str:
    by = {}
    for r in results:
        by.setdefault((r["env_id"], r["algo"]), []).append(r)
    heads = " | ".join(NAMES[a] for a in algos)
    rule = "|---" * (len(algos) + 1) + "|"
    out = [f"Training return (mean episodic return over the last 10 % of steps), mean ± std over "
           f"seeds:\n\n| task | {heads} |\n{rule}"]
    for env_id in envs:
        out.append(f"| {env_id} | " + " | ".join(
            cell([r["final_return"] for r in by.get((env_id, a), [])]) for a in algos) + " |")
    out.append(f"\nEvaluation return (final checkpoint, 10 deterministic episodes), mean ± std "
               f"over seeds:\n\n| task | {heads} |\n{rule}")
    for env_id in envs:
        out.append(f"| {env_id} | " + " | ".join(
            cell([r["eval"]["mean_return"] for r in by.get((env_id, a), []) if r.get("eval")])
            for a in algos) + " |")
    out.append(f"\nEnv steps until the smoothed mean curve reaches the threshold (the paper's "
               f"Table 2 form; {WINDOW}-point moving average):\n\n| task | threshold | {heads} |"
               f"\n{rule}---|")
    for env_id in envs:
        out.append(f"| {env_id} | {THRESHOLDS[env_id]:,} | " + " | ".join(
            steps_to(by[(env_id, a)], THRESHOLDS[env_id]) if (env_id, a) in by else "—"
            for a in algos) + " |")
    return "\n".join(out)


def against(values: list[float], bar: float) -> str:
    """"mean (gap to the bar in per cent)"."""
    mean = statistics.mean(values)
    return f"{mean:,.0f} ({mean / bar - 1:+.0%})"


def bar_table(results: list[dict], envs: list[str]) -> str:
    """TPDEB's mean returns against each task's bar, with the gap in per cent: the evaluation
    return (deterministic, as the zoo's published figures) and the training return."""
    out = ["TPDEB against the bar (mean over seeds; the gap in per cent):\n",
           "| task | bar | TPDEB evaluation | TPDEB training | seeds |", "|---" * 5 + "|"]
    for env_id in envs:
        runs = [r for r in results if r["env_id"] == env_id and r["algo"] == "tpdeb"]
        if not runs:
            continue
        bar = THRESHOLDS[env_id]
        evals = [r["eval"]["mean_return"] for r in runs if r.get("eval")]
        out.append(f"| {env_id} | {bar:,} | {against(evals, bar) if evals else '—'} | "
                   f"{against([r['final_return'] for r in runs], bar)} | {len(runs)} |")
    return "\n".join(out)


def sac_table(results: list[dict], envs: list[str]) -> str:
    """How far TPDEB is from SAC's published 1M return per task, like for like: against
    CleanRL's training return TPDEB's training return, against the zoo's deterministic model
    TPDEB's evaluation return."""
    out = ["Toward SAC at 1M env steps (mean over seeds; the gap in per cent):\n",
           "| task | SAC at 1M | source | TPDEB, like for like | seeds |", "|---" * 5 + "|"]
    for env_id in envs:
        runs = [r for r in results if r["env_id"] == env_id and r["algo"] == "tpdeb"]
        if not runs or env_id not in SAC_1M:
            continue
        bar, source = SAC_1M[env_id]
        kind = SAC_KIND[source]
        ours = ([r["final_return"] for r in runs] if kind == "training"
                else [r["eval"]["mean_return"] for r in runs if r.get("eval")])
        out.append(f"| {env_id} | {bar:,} | {source} ({kind}) | "
                   f"{against(ours, bar) if ours else '—'} | {len(ours)} |")
    return "\n".join(out)


def mean_over_training(runs: list[dict]) -> float:
    """Area under the smoothed mean curve divided by its length: return per env step."""
    _, mean, _ = mean_curve(runs)
    return float(np.mean(mean))


def compare(ours: list[float], theirs: list[float]) -> int | None:
    """+1 where our mean beats theirs by more than the larger seed std, −1 the other way,
    0 within the seed spread; None with a single seed on either side (no spread to judge by)."""
    if len(ours) < 2 or len(theirs) < 2:
        return None
    gap = statistics.mean(ours) - statistics.mean(theirs)
    spread = max(statistics.stdev(ours), statistics.stdev(theirs))
    return (gap > spread) - (gap < -spread)


NOT_JUDGED = "not judged: one seed, no spread"
VERDICT = {1: "higher", 0: "within the seed spread", -1: "lower", None: NOT_JUDGED}


def against_bar(values: list[float], bar: float) -> int | None:
    """+1 where the mean over seeds is above `bar` by more than the seed std, −1 where it is
    below by more, 0 within the spread; None with a single seed (no spread to judge by)."""
    if len(values) < 2:
        return None
    gap, spread = statistics.mean(values) - bar, statistics.stdev(values)
    return (gap > spread) - (gap < -spread)


def difference(ours: list[float], theirs: list[float]) -> tuple[float, float | None]:
    """(mean of ours − mean of theirs, its seed spread): the spread is the root sum of squares
    of the two seed stds; None with a single seed on either side."""
    gap = statistics.mean(ours) - statistics.mean(theirs)
    if len(ours) < 2 or len(theirs) < 2:
        return gap, None
    return gap, (statistics.stdev(ours) ** 2 + statistics.stdev(theirs) ** 2) ** 0.5


def grows(later: tuple[float, float | None], earlier: tuple[float, float | None]
          ) -> tuple[int | None, float | None]:
    """The trend between two differences (`difference`), e.g. a lead at the widest and the
    thinnest link: +1 where `later` exceeds `earlier` by more than their combined spread (the
    root sum of squares of the two spreads, so of all four seed stds), −1 where it falls short
    by more, 0 within it; None where either rests on one seed. With the combined spread."""
    (late, late_spread), (early, early_spread) = later, earlier
    if late_spread is None or early_spread is None:
        return None, None
    spread = (late_spread ** 2 + early_spread ** 2) ** 0.5
    gap = late - early
    return (gap > spread) - (gap < -spread), spread


def gap_cell(gap: tuple[float, float | None]) -> str:
    """A difference (`difference`) as "+982 ± 1,516", its mean alone with one seed."""
    mean, spread = gap
    return f"{mean:+,.0f}" + ("" if spread is None else f" ± {spread:,.0f}")


def spread_test(text: str, a: str, ours: list[float], b: str,
                theirs: list[float]) -> tuple[str, bool | None]:
    """One part of a statement: (`text` with both values, whether `a` is higher than `b` beyond
    the seed spread; None with one seed on a side)."""
    result = compare(ours, theirs)
    return (f"{text}: {a} {cell(ours)} against {b} {cell(theirs)}, {VERDICT[result]}",
            None if result is None else result == 1)


def outcome(parts: list[tuple[str, bool | None]]) -> str | None:
    """'holds here' when every part holds, 'does not hold here' when none does, 'holds in part'
    between; None while a part rests on one seed."""
    outcomes = [ok for _, ok in parts]
    if None in outcomes:
        return None
    return ("holds here" if all(outcomes) else "does not hold here" if not any(outcomes)
            else "holds in part")


def judgement(parts: list[tuple[str, bool | None]], missing: int = 0) -> str:
    """Whether a statement holds, from its parts (text, holds; None: one seed, no spread to
    judge by): 'holds here' when every part does, 'holds in part', 'does not hold here'; no
    verdict while a part rests on one seed (that part reads "not judged", never a yes or no by
    its direction); provisional while `missing` runs are missing."""
    if not parts:
        return ""
    state = outcome(parts)
    head = ("**No verdict yet on the paper's statement** (a part rests on one seed)"
            if state is None else f"**The paper's statement {state}**")
    note = f" (provisional: {missing} run{'s' * (missing != 1)} still missing)" if missing else ""
    return "\n".join([f"{head}{note}:", ""] + [
        f"- {'yes' if ok else 'no' if ok is not None else 'not judged'} — {text}"
        for text, ok in parts])


def claim(title: str, quote: str, lines: list[str], outcomes: list[int], need: str) -> str:
    """One paper claim: what it says, what was measured per task, whether it holds. Each
    comparison counts as a win only where TPDEB is higher beyond the seed spread (`compare`);
    the claim holds where wins are more than half the comparisons (`need` "most") or all of
    them ("all"), and is not judged while a comparison rests on one seed."""
    if not outcomes:
        return f"**{title}** ({quote}): no task has all its runs yet."
    wins, losses = outcomes.count(1), outcomes.count(-1)
    n = len(outcomes)
    holds = {"most": wins > n / 2, "all": wins == n}[need]
    verdict = "no verdict yet: one seed per cell shows no spread" if None in outcomes else (
        "holds here" if holds else "does not hold here") + (
        f": TPDEB is higher beyond the seed spread in {wins} of {n} comparisons, lower in "
        f"{losses}, within the spread in {n - wins - losses}.")
    return f"**{title}** ({quote}) — {verdict}\n\n" + "\n".join(f"- {x}" for x in lines)


def claims(results: list[dict], envs: list[str]) -> str:
    """A paragraph per claim of the paper's comparison, from the runs present: only tasks
    with every algorithm run on the same number of seeds are compared."""
    by = {}
    for r in results:
        by.setdefault((r["env_id"], r["algo"]), []).append(r)
    full = [e for e in envs
            if len({len(by.get((e, a), [])) for a in NAMES}) == 1 and (e, "tpdeb") in by]
    out = []

    def rows(metric, label, tasks, rivals):
        lines, outcomes = [], []
        for e in tasks:
            ours = metric(by[(e, "tpdeb")])
            parts = []
            for a in rivals:
                theirs = metric(by[(e, a)])
                o = compare(ours, theirs)
                outcomes.append(o)
                parts.append(f"{NAMES[a]} {statistics.mean(theirs):,.0f} ({VERDICT[o]})")
            lines.append(f"{e}: TPDEB {statistics.mean(ours):,.0f} against "
                         + ", ".join(parts) + f"; {label}, {seeds(len(ours))}")
        return lines, outcomes

    def curve_means(runs):
        return [mean_over_training([r]) for r in runs]

    def finals(runs):
        return [r["final_return"] for r in runs]

    lines, outcomes = rows(curve_means, "mean return over the 1M steps", full,
                           ["impact", "ppo-per"])
    out.append(claim("Sample efficiency", "Fig 7: \"significantly higher sample efficiency "
                     "than IMPACT and PPO in most tasks\"", lines, outcomes, "most"))
    hard = [e for e in full if e in ("Ant-v5", "Humanoid-v5")]
    lines, outcomes = rows(finals, "training return at 1M", hard, ["impact", "ppo-per"])
    out.append(claim("Hard tasks", "\"in challenging tasks such as Ant and Humanoid, TPDEB "
                     "achieves a higher average return\"", lines, outcomes, "all"))
    lines, outcomes = rows(finals, "training return at 1M", full, ["ppo-per"])
    out.append(claim("Against PPO+PER", "\"TPDEB outperforms it in nearly all tasks\"",
                     lines, outcomes, "most"))
    table2 = []
    for e in full:
        steps = {a: steps_to(by[(e, a)], THRESHOLDS[e]) for a in NAMES}
        table2.append(f"{e}: " + ", ".join(f"{NAMES[a]} {v}" for a, v in steps.items()))
    out.append("**Samples to threshold** (Table 2: \"a sample efficiency advantage in nearly "
               "all tasks\") — described, not judged: where a mean curve crosses a threshold "
               "has no seed spread to judge by. The smoothed mean curves reach the thresholds "
               "at:\n\n" + "\n".join(f"- {x}" for x in table2)
               if table2 else "**Samples to threshold** (Table 2): no task has all its runs yet.")
    return "\n\n".join(out)


def figure(results: list[dict], env_id: str, algos: list[str], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.4, 3.8))
    for n, algo in enumerate(algos):
        runs = [r for r in results if r["env_id"] == env_id and r["algo"] == algo and r["curve"]]
        if not runs:
            continue
        grid, mean, std = mean_curve(runs)
        band(ax, grid, mean, std, f"C{n}", f"{NAMES[algo]} ({seeds(len(runs))})")
    ax.axhline(THRESHOLDS[env_id], color="grey", lw=0.8, ls="--", label="threshold")
    label_axes(ax, env_id, "episodic return")
    save(fig, path)


def replace_between(doc: Path, begin: str, end: str, text: str) -> bool:
    """Put `text` between the markers `begin` and `end` of `doc`; False where it has none."""
    new = provenance.replace_block(doc.read_text(), begin, end, text) if doc.exists() else None
    if new is None:
        return False
    doc.write_text(new)
    return True


def report(directory: Path, envs: list[str], algos: list[str], update_doc: bool = True) -> None:
    """Print the tables, draw the figures beside the data (docs/img/{tag}/); for the reported
    grid (`update_doc`) also rewrite docs/RESULTS.md's generated part."""
    results = load(directory)
    tag = directory.relative_to(ROOT / "docs" / "data")
    if not results:
        print(f"no finished runs in {directory}")
        return
    present = [e for e in envs if any(r["env_id"] == e for r in results)]
    text = "\n\n".join([tables(results, present, algos), bar_table(results, present),
                         sac_table(results, present), claims(results, present)])
    for env_id in present:
        image = ROOT / "docs" / "img" / tag / f"{env_id}.png"
        figure(results, env_id, algos, image)
        text += f"\n\n![{env_id}](img/{tag}/{env_id}.png)"
    print(text)
    doc = ROOT / "docs" / "RESULTS.md"
    if update_doc and replace_between(doc, BEGIN, END, text):
        print(f"\nupdated {doc}")


def tuning_table(directory: Path) -> str:
    """Every tuning run under docs/data/tune/: its settings, return and diagnostics."""
    rows = []
    for path in sorted(directory.glob("*/*.json")):
        r = json.loads(path.read_text())
        d = r.get("diagnostics", {})
        rows.append((r["env_id"], r["total_steps"], path.parent.name, r["seed"], r))
    lines = ["| task | steps | variant | settings | seed | training return | evaluation | "
             "entropy | clipfrac | KL(μ‖π) | policy lag | sample age |", "|---" * 12 + "|"]
    for env_id, steps, name, seed, r in sorted(rows, key=lambda x: (x[0], x[1], x[2], x[3])):
        d = r.get("diagnostics", {})
        overrides = r.get("overrides", [])
        base = "defaults" if "preset=none" in overrides else "preset"
        settings = " + ".join([base, *(o for o in overrides if o != "preset=none")])
        evaluation = (r.get("eval") or {}).get("mean_return")
        lines.append(
            f"| {env_id} | {steps / 1e3:,.0f}k | {name} | {settings} | {seed} | "
            f"{r['final_return']:,.0f} | "
            f"{'—' if evaluation is None else f'{evaluation:,.0f}'} | "
            f"{d.get('losses/entropy', float('nan')):.1f} | "
            f"{d.get('losses/clipfrac', float('nan')):.2f} | "
            f"{d.get('losses/kl_behaviour', float('nan')):.2f} | "
            f"{d.get('actor/param_version_lag', float('nan')):.0f} | "
            f"{d.get('replay/sample_age_updates', float('nan')):.0f} |")
    return "\n".join(lines)
