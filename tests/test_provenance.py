"""Provenance of the data files (bench/provenance.py): every file under docs/data/ says what
code and machine made it (or that it was inferred, or is unknown), a run's record is taken at
its start, a verdict is added beside the earlier ones, and inference picks the last commit made
before the run started."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import provenance  # noqa: E402


def test_every_data_file_has_a_provenance_and_the_pages_count_them(capsys):
    assert provenance.main(["--check", "--quiet"]) == 0, capsys.readouterr().out


def git(repo: Path, *args: str, when: int | None = None) -> str:
    env = {**os.environ, "GIT_AUTHOR_NAME": "t", "GIT_AUTHOR_EMAIL": "t@t",
           "GIT_COMMITTER_NAME": "t", "GIT_COMMITTER_EMAIL": "t@t"}
    if when is not None:
        env["GIT_AUTHOR_DATE"] = env["GIT_COMMITTER_DATE"] = f"{when} +0000"
    return subprocess.run(["git", *args], cwd=repo, env=env, check=True, capture_output=True,
                          text=True).stdout.strip()


@pytest.fixture
def repo(tmp_path, monkeypatch):
    """A project checkout of its own: ROOT and DATA point into it."""
    root = tmp_path / "repo"
    (root / "docs" / "data").mkdir(parents=True)
    git(root, "init", "-q")
    monkeypatch.setattr(provenance, "ROOT", root)
    monkeypatch.setattr(provenance, "DATA", root / "docs" / "data")
    return root


def commit(repo: Path, path: str, text: str, when: int) -> str:
    (repo / path).parent.mkdir(parents=True, exist_ok=True)
    (repo / path).write_text(text)
    git(repo, "add", path)
    git(repo, "commit", "-q", "-m", path, when=when)
    return git(repo, "rev-parse", "HEAD")


def test_a_record_names_the_commit_and_keeps_the_diff_of_a_dirty_tree(repo):
    head = commit(repo, "code.py", "x = 1\n", 1_700_000_000)
    clean = provenance.start(["bench/x.py", "--seed", "3"])
    assert clean["commit"] == head and clean["dirty"] is False
    assert clean["commit_date"] == "2023-11-14T22:13:20+00:00"
    assert clean["command"][1:] == ["bench/x.py", "--seed", "3"]
    assert clean["machine"]["cores"] == os.cpu_count() and clean["started_at"]
    assert set(provenance.PACKAGES) <= set(clean["packages"])
    (repo / "docs" / "data" / "result.json").write_text("{}")  # data is not code
    assert provenance.start()["dirty"] is False
    (repo / "code.py").write_text("x = 2\n")
    dirty = provenance.start()
    assert dirty["dirty"] is True and dirty["commit"] == head
    kept = repo / dirty["diff_file"]
    assert dirty["diff_sha256"].startswith(kept.stem) and not kept.exists()  # staged only
    result = provenance.stamp({"figure": 1.0}, dirty)
    assert "is missing" in provenance.problem(result)
    path = repo / "docs" / "data" / "run.json"
    path.write_text(json.dumps(result))
    provenance.keep_diff(path)  # what `written` does when a data file lands
    assert "+x = 2" in kept.read_text()
    assert result["provenance"]["ended_at"] and provenance.problem(result) is None


def test_the_check_fails_on_a_file_with_no_record_or_a_record_short_of_its_fields(repo, capsys):
    commit(repo, "code.py", "a\n", 1_700_000_000)
    data = repo / "docs" / "data"
    (data / "made.json").write_text(json.dumps(provenance.stamp({}, provenance.start())))
    assert provenance.main(["--check", "--data", str(data)]) == 0
    (data / "bare.json").write_text(json.dumps({"final_return": 1.0}))
    assert provenance.main(["--check", "--data", str(data)]) == 1
    assert "bare.json: no provenance" in capsys.readouterr().out
    (data / "bare.json").write_text(json.dumps({"provenance": {"status": "recorded",
                                                               "commit": "abc"}}))
    assert provenance.main(["--check", "--data", str(data)]) == 1
    (data / "bare.json").write_text(json.dumps({"provenance": {"status": "unknown"}}))
    assert provenance.main(["--check", "--data", str(data)]) == 1  # unknown must say why


def test_inference_takes_the_last_commit_before_the_run_began_not_the_one_that_added_it(repo):
    first = commit(repo, "code.py", "a\n", 1_700_000_000)
    second = commit(repo, "code.py", "b\n", 1_700_001_000)
    commit(repo, "code.py", "c\n", 1_700_004_000)  # made while the run was going on
    result = {"final_return": 5.0, "wall_s": 2_500.0}
    commit(repo, "docs/data/run.json", json.dumps(result), 1_700_004_500)
    path = repo / "docs" / "data" / "run.json"
    record = provenance.infer(path, result, provenance.commit_times())
    assert record["status"] == "inferred" and record["commit"] == second
    assert record["commit_date"] == "2023-11-14T22:30:00+00:00"  # kept: no history needed
    assert "less the run's 2,500 s" in record["basis"]
    # the commit recorded when the run ended bounds it: it cannot have started on a later one
    ended = {**result, "code": first[:7] + "-dirty"}
    record = provenance.infer(path, ended, provenance.commit_times())
    assert record["commit"] == first and record["dirty_at_end"] is True
    # a run made again in place dates from its remake, not from the path's first version
    remade = {"final_return": 7.0, "wall_s": 100.0}
    commit(repo, "docs/data/run.json", json.dumps(remade), 1_700_010_000)
    fourth = git(repo, "rev-parse", "HEAD~1")
    assert provenance.infer(path, remade, provenance.commit_times())["commit"] == fourth
    # backfilled into the file, in its own layout, once
    assert provenance.backfill([path])["inferred"] == 1
    assert json.loads(path.read_text())["provenance"]["commit"] == fourth
    assert provenance.backfill([path]) == {}


def test_a_file_never_committed_and_undated_is_marked_unknown_with_the_reason(repo):
    commit(repo, "code.py", "a\n", 1_700_000_000)
    path = repo / "docs" / "data" / "loose.json"
    path.write_text("{}")
    record = provenance.infer(path, {}, provenance.commit_times())
    assert record["status"] == "unknown" and record["why"]


def test_a_verdict_is_added_beside_the_earlier_one_never_in_its_place():
    result = {}
    provenance.add_verdict(result, "judge", 1, False, ["drift 6 % > 5 %"])
    provenance.add_verdict(result, "judge", 2, True, [], note="judged again")
    assert [(v["rule_version"], v["verdict"]) for v in result["verdicts"]] == [
        (1, "FAIL"), (2, "PASS")]
    assert result["verdicts"][0]["reasons"] == ["drift 6 % > 5 %"]
    assert result["verdicts"][-1]["verdict"] == "PASS"


def test_a_data_file_written_brings_the_pages_counts_with_it(repo):
    commit(repo, "code.py", "a\n", 1_700_000_000)
    for page in provenance.PAGES:
        (repo / page).write_text("# A page\n\nIts text.\n")
    (repo / provenance.GRID_RESULTS).write_text(
        f"# Results\n\n{provenance.GRID_BEGIN}\n{provenance.GRID_END}\n")
    data = repo / "docs" / "data"
    path = data / "ablation" / "run.json"
    path.parent.mkdir(parents=True)
    path.write_text(json.dumps(provenance.stamp({"final_return": 1.0}, provenance.start())))
    assert provenance.stale_pages(provenance.data_files()) != []
    provenance.written(path)
    assert provenance.stale_pages(provenance.data_files()) == []
    assert "this page's 1 data files" in (repo / "docs" / "ABLATIONS.md").read_text()
    provenance.written(repo / "elsewhere.json")  # outside docs/data: nothing to follow


def test_a_tests_figures_are_kept_only_when_asked_with_the_record_of_its_start(
        repo, tmp_path, monkeypatch):
    from tests.figures import Keeper

    commit(repo, "code.py", "a\n", 1_700_000_000)
    monkeypatch.delenv("TPDEB_KEEP_FIGURES", raising=False)
    assert Keeper("t::x").keep("recovery", {"s": 1.0}) is None
    monkeypatch.setenv("TPDEB_KEEP_FIGURES", str(tmp_path / "kept"))
    keeper = Keeper("t::x")  # as the test begins
    started = keeper.record["started_at"]
    kept = json.loads(keeper.keep("recovery", {"s": 1.0}).read_text())
    assert kept["test"] == "recovery" and kept["s"] == 1.0
    assert kept["provenance"]["started_at"] == started
    assert kept["provenance"]["command"][-1] == "t::x" and provenance.problem(kept) is None
