"""The thin-link section of docs/BENCHMARKS.md and docs/img/thinlink/*.png from the result files
of `bench/bandwidth.py` (`--report`): per task and link the return each system reached in the
same wall-clock, its env steps and bytes, curves against wall-clock and env steps, the verdict
on the paper's claim and on the replay-ratio band."""

from __future__ import annotations

import json
import statistics
from pathlib import Path

import paper_report  # noqa: I001  (bench/ is on sys.path)
import race_report
from bandwidth import ALGOS, BANDED, LINKS, SEEDS, UNLIMITED, link_name
from paper_report import VERDICT, cell, compare, judgement, replace_between, seeds, spread_test
from provenance import commit_of
from runs import ROOT

from tpdeb.services.plot import band, save

DOC = ROOT / "docs" / "BENCHMARKS.md"
IMAGES = ROOT / "docs" / "img" / "thinlink"
BEGIN, END = "<!-- thinlink:begin -->", "<!-- thinlink:end -->"
# the verdict in one paragraph per task, also in these two (between their own markers)
HEADLINE_DOCS = [ROOT / "docs" / "RESULTS.md", ROOT / "README.md"]
HEADLINE = "<!-- thinlink-verdict:begin -->", "<!-- thinlink-verdict:end -->"
NAMES = {"tpdeb": "TPDEB", "impact": "IMPACT", "ppo-per": "PPO+PER",
         "tpdeb-band": "TPDEB + band", "impact-band": "IMPACT + band"}


def load(directory: Path) -> list[dict]:
    return [json.loads(p.read_text()) for p in sorted(directory.glob("*/*.json"))]


def runs_of(results: list[dict], env_id: str, system: str, link: float) -> list[dict]:
    """The runs of one system on one task behind one link."""
    return [r for r in results if (r["env_id"], r["link"], r["system"]) == (env_id, link, system)]


def band_and_fixed(results: list[dict], env_id: str, algo: str,
                   link: float) -> tuple[list[dict], list[dict]]:
    """The runs of `algo` with the replay-ratio band and with its fixed ratio behind one link."""
    return tuple(runs_of(results, env_id, system, link) for system in (f"{algo}-band", algo))


def band_effect(banded: list[dict], fixed: list[dict]) -> str:
    """What the band changed on the learner's side, medians with the band against the fixed
    ratio: the replay ratio reached, the time spent waiting for a batch, a sample's age and the
    actors' parameter lag; '' for runs that did not record them."""
    parts = []
    for key, what, fmt in (("samples_per_insert", "replay ratio", ".1f"),
                           ("batch_wait", "learner waiting", ".0%"),
                           ("sample_age", "sample age (updates)", ",.0f"),
                           ("lag", "parameter lag", ",.0f")):
        ours, theirs = median(banded, key, fmt), median(fixed, key, fmt)
        if "—" not in (ours, theirs):
            parts.append(f"{what} {ours} against {theirs}")
    return f" ({', '.join(parts)})" if parts else ""


def final(runs: list[dict], what: str = "train") -> list[float]:
    return race_report.at(runs, race_report.final_mark(runs), what) if runs else []


def median(runs: list[dict], key: str, fmt: str) -> str:
    values = [r[key] for r in runs if r.get(key) is not None]
    return format(statistics.median(values), fmt) if values else "—"


def links_of(results: list[dict]) -> list[float]:
    return sorted({r["link"] for r in results}, key=lambda x: -(x or UNLIMITED))


def table(results: list[dict], env_id: str) -> str:
    out = ["| link | system | training return | evaluation | env steps | bytes/step up / down "
           "| parameter lag | replay ratio | learner waiting | seeds |",
           "|---|---|---|---|---|---|---|---|---|---|"]
    for link in links_of(results):
        for system in NAMES:
            runs = runs_of(results, env_id, system, link)
            if runs:
                out.append(
                    f"| {link_name(link)} | {NAMES[system]} | {cell(final(runs))} | "
                    f"{cell(final(runs, 'eval'))} | {median(runs, 'steps', ',.0f')} | "
                    f"{median(runs, 'up_bytes_per_step', ',.0f')} / "
                    f"{median(runs, 'down_bytes_per_step', ',.0f')} | "
                    f"{median(runs, 'lag', '.1f')} | {median(runs, 'samples_per_insert', '.1f')} "
                    f"| {median(runs, 'batch_wait', '.0%')} | {len(runs)} |")
    return "\n".join(out)


def leads(results: list[dict], env_id: str, base: str
          ) -> list[tuple[float, tuple[float, float | None]]]:
    """(link, TPDEB's lead over `base`: the difference of the mean returns and its seed
    spread, `paper_report.difference`) for each link both ran, widest first."""
    out = []
    for link in links_of(results):
        ours, theirs = (final(runs_of(results, env_id, system, link)) for system in ("tpdeb", base))
        if ours and theirs:
            out.append((link, paper_report.difference(ours, theirs)))
    return out


# the lead's trend as a sentence's verb, and as a short verdict
TREND = {1: "grows", 0: "neither grows nor shrinks beyond the seed spread", -1: "shrinks",
         None: "is not judged (one seed, no spread)"}
GROWTH = {1: "grows", 0: "within the seed spread", -1: "shrinks", None: paper_report.NOT_JUDGED}


def lead_trend(gaps: list[tuple[float, tuple[float, float | None]]]) -> tuple[int | None, str]:
    """Whether TPDEB's lead grows as the link thins, and the line that says so. The rule, kept
    conservative: the lead at the thinnest link minus the lead at the widest must exceed their
    combined seed spread (`paper_report.grows`: the root sum of squares of all four seed stds);
    the leads between are shown, not judged. None with one seed on a side (no spread)."""
    (wide, wide_gap), (thin, thin_gap) = gaps[0], gaps[-1]
    result, spread = paper_report.grows(thin_gap, wide_gap)
    between = "".join(f", {paper_report.gap_cell(g)} at {link_name(link)}"
                      for link, g in gaps[1:-1])
    rule = ("" if spread is None else f"; the change {thin_gap[0] - wide_gap[0]:+,.0f} against "
            f"a combined spread of {spread:,.0f}")
    return result, (f"{paper_report.gap_cell(wide_gap)} at {link_name(wide)}{between}, "
                    f"{paper_report.gap_cell(thin_gap)} at {link_name(thin)}{rule}")


def verdict(results: list[dict], env_id: str) -> list[str]:
    """TPDEB against each baseline per link, the gap's trend as the link thins, the band
    against the fixed ratio."""
    lines = []
    for link in links_of(results):
        ours = final(runs_of(results, env_id, "tpdeb", link))
        for base in ALGOS[1:]:
            theirs = final(runs_of(results, env_id, base, link))
            if ours and theirs:
                lines.append(f"{link_name(link)}: TPDEB {cell(ours)} against {NAMES[base]} "
                             f"{cell(theirs)}: {VERDICT[compare(ours, theirs)]}")
        for algo in BANDED:
            banded_runs, fixed_runs = band_and_fixed(results, env_id, algo, link)
            banded, fixed = final(banded_runs), final(fixed_runs)
            if banded and fixed:
                lines.append(f"{link_name(link)}: {NAMES[algo]} with the band {cell(banded)} "
                             f"against the fixed ratio {cell(fixed)}: "
                             f"{VERDICT[compare(banded, fixed)]}"
                             f"{band_effect(banded_runs, fixed_runs)}")
    for base in ALGOS[1:]:
        mine = leads(results, env_id, base)
        if len(mine) >= 2:
            result, text = lead_trend(mine)
            lines.append(f"TPDEB's lead over {NAMES[base]} {TREND[result]} as the link thins: "
                         f"{text}")
    return lines


def claim_parts(results: list[dict], env_id: str) -> tuple[list[tuple[str, bool | None]], int]:
    """The paper's claim, TPDEB ahead "especially under constrained actor–learner bandwidth",
    in parts: at the thinnest link run, TPDEB above each baseline beyond the seed spread, and
    its lead larger there than on the widest link by more than the two leads' combined spread
    (`lead_trend`); with the count of the grid's runs missing."""
    mine = [r for r in results if r["env_id"] == env_id]
    present = {(r["system"], r["link"], r["seed"]) for r in mine}
    missing = sum((a, link, s) not in present for a in ALGOS for link in LINKS for s in SEEDS)
    parts = []
    for base in ALGOS[1:]:
        gaps = leads(mine, env_id, base)
        if not gaps:
            continue
        wide, thin = gaps[0][0], gaps[-1][0]
        parts.append(spread_test(f"TPDEB above {NAMES[base]} at {link_name(thin)}", "TPDEB",
                                 final(runs_of(mine, env_id, "tpdeb", thin)), NAMES[base],
                                 final(runs_of(mine, env_id, base, thin))))
        if len(gaps) >= 2:
            result, text = lead_trend(gaps)
            parts.append((f"TPDEB's lead over {NAMES[base]} larger at {link_name(thin)} than at "
                          f"{link_name(wide)} beyond the seed spread: {text}: "
                          f"{GROWTH[result]}",
                          None if result is None else result == 1))
    return parts, missing


def claim(results: list[dict], env_id: str) -> str:
    return judgement(*claim_parts(results, env_id))


def times(ours: list[float], theirs: list[float]) -> str:
    """'1.39× ' (one decimal from 10×); '' where their mean return is at or below 0, which
    makes a ratio meaningless."""
    theirs_mean = statistics.mean(theirs)
    if theirs_mean <= 0:
        return ""
    ratio = statistics.mean(ours) / theirs_mean
    return f"{ratio:.{1 if ratio >= 10 else 2}f}× "


def headline(results: list[dict], env_id: str) -> str:
    """The verdict in one paragraph for RESULTS and README: the thinnest link's returns and
    ratios, each lead's trend, the band there where it ran."""
    parts, missing = claim_parts(results, env_id)
    mine = [r for r in results if r["env_id"] == env_id]
    links = links_of(mine)
    if not parts or len(links) < 2:
        return f"{env_id}: too few thin-link runs for a verdict yet."
    state = paper_report.outcome(parts) or "no verdict yet (a part rests on one seed)"
    note = f", provisional: {missing} of the grid's runs still missing" if missing else ""
    thin = links[-1]
    ours = final(runs_of(results, env_id, "tpdeb", thin))
    rivals, trends = [], []
    for base in ALGOS[1:]:
        theirs = final(runs_of(results, env_id, base, thin))
        gaps = leads(results, env_id, base)
        if theirs and gaps:
            rivals.append(f"{times(ours, theirs)}{NAMES[base]}'s {cell(theirs)} "
                          f"({VERDICT[compare(ours, theirs)]})")
            result = lead_trend(gaps)[0] if len(gaps) >= 2 else None
            trends.append(f"over {NAMES[base]} {gaps[0][1][0]:+,.0f} → {gaps[-1][1][0]:+,.0f} "
                          f"({GROWTH[result]})")
    minutes = statistics.median(r["budget_s"] for r in mine) / 60
    text = (f"**{env_id}, {minutes:g} minutes of training behind each link, "
            f"{seeds(len({r['seed'] for r in mine}))}** — the paper's claim "
            f"(TPDEB ahead \"especially under constrained actor–learner bandwidth\") {state}"
            f"{note}. At {link_name(thin)} TPDEB reaches {cell(ours)}: " + " and ".join(rivals)
            + f". TPDEB's lead, {link_name(links[0])} → {link_name(thin)}: " * bool(trends)
            + ", ".join(trends) + ".")
    for algo in BANDED:
        banded, fixed = map(final, band_and_fixed(results, env_id, algo, thin))
        if banded and fixed:
            text += (f" With the replay-ratio band, {NAMES[algo]} at {link_name(thin)}: "
                     f"{cell(banded)} against {cell(fixed)} ({VERDICT[compare(banded, fixed)]}).")
    return text


def figure(results: list[dict], env_id: str, path: Path) -> None:
    """Per link (columns): return against wall-clock minutes (top) and env steps (bottom)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    links = links_of([r for r in results if r["env_id"] == env_id])
    fig, axes = plt.subplots(2, len(links), figsize=(4.0 * len(links), 6.4), squeeze=False,
                             sharey="row")
    for col, link in enumerate(links):
        for n, system in enumerate(NAMES):
            runs = [r for r in runs_of(results, env_id, system, link) if r["episodes"]]
            if not runs:
                continue
            label = f"{NAMES[system]} ({seeds(len(runs))})"
            grid, mean, std = race_report.mean_curve(runs)
            band(axes[0][col], grid / 60, mean, std, f"C{n}", label)
            by_steps = [{"curve": [(s, ret) for _, s, ret in r["episodes"]]} for r in runs]
            grid, mean, std = paper_report.mean_curve(by_steps)
            band(axes[1][col], grid, mean, std, f"C{n}", label)
        axes[0][col].set_title(f"{env_id}, link {link_name(link)}")
        axes[0][col].set_xlabel("training minutes")
        axes[1][col].set_xlabel("env steps")
    for row in axes:
        row[0].set_ylabel("episodic return")
    axes[0][0].legend(fontsize=7)
    save(fig, path)


def report(directory: Path) -> None:
    results = load(directory)
    if not results:
        print(f"no finished runs in {directory}")
        return
    budgets = sorted({r["budget_s"] / 60 for r in results})
    codes = sorted({commit_of(r) for r in results})
    parts = [f"Each run: {', '.join(f'{b:g}' for b in budgets)} minutes of training on two "
             f"cores; commit{'s' * (len(codes) > 1)} {', '.join(codes)}. Training return: the "
             "episodes ending in the last 10 % of the budget; evaluation: the final policy, 10 "
             "deterministic episodes; bytes per env step as the link counted them."]
    for env_id in sorted({r["env_id"] for r in results}):
        image = IMAGES / f"{env_id}.png"
        figure(results, env_id, image)
        lines = verdict(results, env_id)
        parts += [f"**{env_id}**", table(results, env_id),
                  "\n".join(f"- {x}" for x in lines) or "- too few runs for a verdict yet.",
                  claim(results, env_id) or "No verdict yet on the paper's claim.",
                  f"![{env_id} behind thin links](img/thinlink/{image.name})"]
    text = "\n\n".join(parts)
    print(text)
    if replace_between(DOC, BEGIN, END, text):
        print(f"\nupdated {DOC}")
    verdicts = "\n\n".join(headline(results, env_id)
                            for env_id in sorted({r["env_id"] for r in results}))
    for doc in HEADLINE_DOCS:
        if replace_between(doc, *HEADLINE, verdicts):
            print(f"updated {doc}")
