"""The comparison's tables and claim paragraphs (bench/paper_report.py) on made-up results."""

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import paper_report  # noqa: E402


def result(env_id: str, algo: str, seed: int, level: float) -> dict:
    """A run whose curve climbs linearly to `level` over 1M steps."""
    curve = [[s, level * s / 1_000_000] for s in range(0, 1_000_001, 10_000)]
    return {"env_id": env_id, "algo": algo, "seed": seed, "final_return": level,
            "eval": {"mean_return": level}, "curve": curve}


def grid(levels: dict, seeds=(11, 12, 13)) -> list[dict]:
    """levels: {(env, algo): level}; seed s adds s to the level (a spread of ~1)."""
    return [result(e, a, s, level + s) for (e, a), level in levels.items() for s in seeds]


def test_steps_to_reads_the_smoothed_mean_curve():
    runs = grid({("Hopper-v5", "tpdeb"): 3000})
    assert paper_report.steps_to(runs, 1500) != "not reached"
    assert paper_report.steps_to(runs, 10_000) == "not reached"


def test_compare_needs_a_gap_beyond_the_seed_spread():
    assert paper_report.compare([10, 11, 12], [1, 2, 3]) == 1
    assert paper_report.compare([1, 2, 3], [10, 11, 12]) == -1
    assert paper_report.compare([1, 5, 9], [2, 6, 10]) == 0
    assert paper_report.compare([10], [1]) is None  # one seed shows no spread: no verdict


def test_a_mean_is_above_a_bar_only_beyond_its_seed_spread():
    assert paper_report.against_bar([0.3, 0.32, 0.34], 0.2) == 1
    assert paper_report.against_bar([0.0, 0.4, 0.5], 0.2) == 0  # 30 % by its mean alone
    assert paper_report.against_bar([0.0, 0.01, 0.02], 0.2) == -1
    assert paper_report.against_bar([0.9], 0.2) is None


def test_a_trend_grows_only_beyond_the_combined_spread_of_its_ends():
    # the thin-link case: a lead of +982 → +1,589 with the baseline's std at 2,028
    wide = paper_report.difference([5000, 5900, 6900], [3800, 4900, 6150])
    thin = paper_report.difference([4900, 5700, 6250], [1800, 4500, 5800])
    result, spread = paper_report.grows(thin, wide)
    assert result == 0 and spread > thin[0] - wide[0] > 0
    assert paper_report.grows(wide, thin)[0] == 0
    tight_wide = paper_report.difference([5000, 5010, 4990], [4000, 4010, 3990])
    tight_thin = paper_report.difference([5000, 5010, 4990], [2000, 2010, 1990])
    assert paper_report.grows(tight_thin, tight_wide)[0] == 1
    assert paper_report.grows(tight_wide, tight_thin)[0] == -1
    one = paper_report.difference([5000], [1000])
    assert one == (4000, None) and paper_report.grows(one, tight_wide) == (None, None)
    assert paper_report.gap_cell(tight_wide) == "+1,000 ± 14"
    assert paper_report.gap_cell(one) == "+4,000"


def test_claims_count_wins_and_losses_per_task():
    results = grid({
        ("Ant-v5", "tpdeb"): 3000, ("Ant-v5", "impact"): 1000, ("Ant-v5", "ppo-per"): 500,
        ("Hopper-v5", "tpdeb"): 1000, ("Hopper-v5", "impact"): 2000,
        ("Hopper-v5", "ppo-per"): 1000,
    })
    text = paper_report.claims(results, ["Ant-v5", "Hopper-v5"])
    efficiency, hard, ppo, table2 = text.split("\n\n**")
    # Ant: beats both; Hopper: loses to IMPACT, ties PPO+PER → 2 of 4, not "most".
    assert "does not hold here" in efficiency
    assert "higher beyond the seed spread in 2 of 4 comparisons, lower in 1" in efficiency
    hopper = next(line for line in efficiency.splitlines() if line.startswith("- Hopper"))
    assert "IMPACT" in hopper and "(lower)" in hopper and "(within the seed spread)" in hopper
    assert "- Hopper-v5: TPDEB 1,012 against PPO+PER 1,012 (within the seed spread)" in ppo
    assert "holds here" in hard and "in 2 of 2" in hard  # Ant only
    assert "Hopper" not in hard
    assert "in 1 of 2" in ppo and "does not hold" in ppo
    assert "Ant-v5: TPDEB" in table2


def test_one_seed_per_cell_gives_numbers_but_no_verdict():
    results = grid({("Ant-v5", a): 1000 for a in paper_report.NAMES}, seeds=(11,))
    text = paper_report.claims(results, ["Ant-v5"])
    assert text.count("no verdict yet") == 3 and "holds here" not in text
    assert "IMPACT 1,011 (not judged: one seed, no spread)" in text


def test_tasks_without_all_their_runs_are_left_out():
    results = grid({("Ant-v5", "tpdeb"): 3000, ("Ant-v5", "impact"): 1000})  # no PPO+PER
    results += grid({("Ant-v5", "ppo-per"): 1000}, seeds=(11,))
    assert "no task has all its runs yet" in paper_report.claims(results, ["Ant-v5"])


@pytest.mark.parametrize("algos", [["tpdeb", "impact", "ppo-per"], ["tpdeb"]])
def test_tables_hold_every_present_algorithm(algos):
    results = grid({("Swimmer-v5", a): 100 for a in algos})
    text = paper_report.tables(results, ["Swimmer-v5"], list(paper_report.NAMES))
    assert "| Swimmer-v5 | 112 ± 1 (n=3) |" in text
    assert text.count("—") == 2 * (3 - len(algos)) + (3 - len(algos))


def test_bar_table_gives_tpdeb_gap_to_each_tasks_bar():
    results = grid({("Hopper-v5", "tpdeb"): 2398, ("Ant-v5", "tpdeb"): 2642,
                    ("Ant-v5", "impact"): 10})
    table = paper_report.bar_table(results, ["Hopper-v5", "Ant-v5", "Swimmer-v5"])
    rows = [line for line in table.splitlines() if line.startswith("| ") and "-v5" in line]
    assert rows == ["| Hopper-v5 | 2,410 | 2,410 (+0%) | 2,410 (+0%) | 3 |",
                    "| Ant-v5 | 1,327 | 2,654 (+100%) | 2,654 (+100%) | 3 |"]  # no Swimmer runs


def test_the_sac_table_compares_like_for_like():
    results = grid({("Hopper-v5", "tpdeb"): 2000, ("Ant-v5", "tpdeb"): 4000})
    for r in results:  # evaluation 1,000 above training
        r["eval"] = {"mean_return": r["final_return"] + 1000}
    text = paper_report.sac_table(results, ["Hopper-v5", "Ant-v5"])
    # CleanRL reports training returns, the zoo a deterministic model's
    assert "| Hopper-v5 | 2,310 | CleanRL (training) | 2,012 (-13%) | 3 |" in text
    assert "| Ant-v5 | 4,616 | zoo (evaluation) | 5,012 (+9%) | 3 |" in text


def test_a_plateau_table_shows_the_learner_state_per_tenth_and_when_the_return_got_out():
    import plateau
    import runs

    rows = []
    for step in range(1_000, 100_001, 1_000):
        rows.append({"global_step": step, "charts/episodic_return": 400.0 if step <= 60_000
                     else 2_000.0})
        rows.append({"global_step": step, "losses/entropy": 5.0 - step / 10_000,
                     "losses/clipfrac": 0.1})
    result = runs.summarize(rows, 100_000)
    assert set(result["diagnostic_curves"]) == {"losses/entropy", "losses/clipfrac"}
    result.update(env_id="Hopper-v5", seed=1, algo="tpdeb", total_steps=100_000)
    table = plateau.run_table(result, threshold=1_500)
    lines = [line for line in table.splitlines() if line.startswith("| ")]
    assert len(lines) == 1 + 10  # the header and one row per tenth
    assert lines[1].split(" | ")[1] == "400" and lines[-1].split(" | ")[1] == "2,000"
    assert lines[1].split(" | ")[2] == "4.45"  # the mean entropy over the first tenth
    assert "first at or above 1,500 after 64k steps" in table  # 5 episodes, 4 past 60k
    assert plateau.first_passing(result["curve"], 10_000) is None
