"""Where a figure came from, and the verdicts judged on it.

Every bench that writes a data file calls `start()` when its run begins and stamps the record
into the file it writes (`stamp`): the commit checked out at the start, whether tracked code
outside `docs/` differed from it (and the sha256 of that diff; the diff itself, when small, is
kept under `docs/data/diffs/` once the run's data file lands under `docs/data/`: `written`),
the versions of the packages that move the figures, the machine (CPU model, cores, memory,
GPU), the exact command line, and start and end times.

A verdict is never rewritten: `add_verdict` appends one (its rule's name and version, the
outcome, the reasons and when and on which commit it was judged) to the file's `verdicts`, so a
rule changed after a run makes a second verdict beside the first.

    python bench/provenance.py --check     # each JSON under docs/data/: commit, dirty, machine;
                                           # exit 1 where one has none or a page's count is stale
    python bench/provenance.py --infer     # files with no record: the commit inferred (marked so)
    python bench/provenance.py --pages     # the counts of recorded/inferred/unknown on the pages

Files made before this record existed carry `"provenance": {"status": "inferred", ...}`: the
commit is the last one made before the run started, from the start time the file records or,
lacking that, from the time the file was first committed less the run's own wall time (an upper
bound on its start, so the commit named is the latest it can have run on; where the file
recorded the commit checked out when the run *ended*, never later than that one). Whether such
a tree was dirty, and on what machine beyond the core count the file recorded, is not known.
"""

from __future__ import annotations

import argparse
import datetime as dt
import hashlib
import importlib.metadata
import json
import os
import platform
import re
import shutil
import subprocess
import sys
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "docs" / "data"
FIELD = "provenance"
PACKAGES = ("torch", "mujoco", "gymnasium", "eclipse-zenoh", "numpy")
DIFF_KEEP_BYTES = 256 * 1024  # a larger diff is recorded by its hash alone
STATUSES = ("recorded", "inferred", "unknown")


# ----------------------------------------------------------------------------- the record

def git(*args: str, cwd: Path | None = None) -> str | None:
    """A git command's stdout (in the project's checkout unless `cwd`), or None outside a
    checkout or without git."""
    try:
        proc = subprocess.run(["git", *args], cwd=cwd or ROOT, capture_output=True, text=True,
                              timeout=30)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return proc.stdout if proc.returncode == 0 else None


def code_state(cwd: Path | None = None, keep_diff: bool = True) -> dict:
    """The commit checked out and how the tracked code differs from it (the diff kept under
    `docs/data/diffs/` when small and `keep_diff`). Pages and data (`docs/`) are not code: a
    grid that writes result files while it runs is not dirty."""
    head = git("rev-parse", "HEAD", cwd=cwd)
    if head is None:
        return {"commit": None, "commit_date": None, "dirty": None, "diff_sha256": None,
                "diff_file": None}
    diff = git("diff", "HEAD", "--binary", "--", ".", ":(exclude)docs", cwd=cwd) or ""
    state = {"commit": head.strip(), "commit_date": commit_date(head.strip(), cwd),
             "dirty": bool(diff), "diff_sha256": None, "diff_file": None}
    if diff:
        digest = hashlib.sha256(diff.encode()).hexdigest()
        state["diff_sha256"] = digest
        if keep_diff and len(diff.encode()) <= DIFF_KEEP_BYTES:
            # staged under bench/out/ (not kept); `written` copies it beside the data when a
            # data file naming it lands under docs/data/
            staged = staged_diff(f"{digest[:16]}.diff")
            if not staged.exists():
                staged.parent.mkdir(parents=True, exist_ok=True)
                staged.write_text(diff)
            state["diff_file"] = f"docs/data/diffs/{digest[:16]}.diff"
    return state


def staged_diff(name: str) -> Path:
    """Where a run's diff waits (bench/out/, not kept) until its data file lands."""
    return ROOT / "bench" / "out" / "diffs" / name


def commit_date(sha: str, cwd: Path | None = None) -> str | None:
    """A commit's date (UTC, ISO 8601), kept in the record so that nothing read later needs
    the history (a shallow clone has none)."""
    out = git("show", "-s", "--format=%ct", sha, cwd=cwd)
    if not out or not out.strip().isdigit():
        return None
    return dt.datetime.fromtimestamp(int(out), dt.timezone.utc).isoformat(timespec="seconds")


def packages() -> dict[str, str | None]:
    versions = {"python": platform.python_version()}
    for name in PACKAGES:
        try:
            versions[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            versions[name] = None
    return versions


def machine() -> dict:
    """CPU model, cores (and those this process may use), memory and GPUs, without importing a
    framework."""
    cpu = platform.processor() or None
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    memory_gib = None
    try:
        kib = int(re.search(r"MemTotal:\s+(\d+)", Path("/proc/meminfo").read_text()).group(1))
        memory_gib = round(kib / 2**20, 1)
    except (OSError, AttributeError):
        pass
    gpus = []
    if shutil.which("nvidia-smi"):
        try:
            out = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"],
                                 capture_output=True, text=True, timeout=30).stdout
            gpus = [line.strip() for line in out.splitlines() if line.strip()]
        except (OSError, subprocess.TimeoutExpired):
            pass
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
    return {"cpu": cpu, "cores": os.cpu_count(), "usable_cores": usable,
            "memory_gib": memory_gib, "gpus": gpus, "host": platform.node(),
            "os": platform.platform()}


def now() -> str:
    return dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds")


def start(argv: list[str] | None = None) -> dict:
    """The record of a run, taken as it begins."""
    return {"status": "recorded", **code_state(), "packages": packages(), "machine": machine(),
            "command": [sys.executable, *(sys.argv if argv is None else argv)],
            "started_at": now(), "ended_at": None}


def stamp(result: dict, record: dict) -> dict:
    """`result` with the run's record, its end time set now; returned for chaining."""
    result[FIELD] = {**record, "ended_at": now()}
    return result


def commit_of(data: dict) -> str:
    """The commit a data file's run began on, short ('1a2b3c4', '-dirty' where its record says
    so; '?' without one), from its provenance (recorded or inferred)."""
    return short(data.get(FIELD))


def short(record: dict | None) -> str:
    """'1a2b3c4' / '1a2b3c4-dirty' / '?' for a record (any status)."""
    if not record or not record.get("commit"):
        return "?"
    return record["commit"][:7] + ("-dirty" if record.get("dirty") else "")


# ----------------------------------------------------------------------------- verdicts

def add_verdict(result: dict, rule: str, version: int, passed: bool, reasons: list[str],
                note: str = "", details: dict | None = None, judged_on: str | None = None
                ) -> dict:
    """Append a verdict to `result["verdicts"]` (never replacing one) and return it. `rule`
    names the function in the bench that judged, `version` its rule's version there;
    `judged_on` the code that judged (today's checkout unless said)."""
    verdict = {"rule": rule, "rule_version": version, "verdict": "PASS" if passed else "FAIL",
               "reasons": list(reasons), "judged_at": now(),
               "judged_on": judged_on or short(code_state(keep_diff=False))}
    if note:
        verdict["note"] = note
    if details:
        verdict["details"] = details
    result.setdefault("verdicts", []).append(verdict)
    return verdict


# ----------------------------------------------------------------------------- inference

def commit_times() -> list[tuple[int, str]]:
    """(commit time, sha) of every commit reachable from HEAD, oldest first."""
    out = git("log", "--format=%ct %H", "HEAD") or ""
    return sorted((int(t), sha) for t, sha in (line.split() for line in out.splitlines()))


# The measured figures of a run: a version of a file is the same run where these are equal.
FIGURES = ("final_return", "wall_s", "steps", "train_s", "episodes", "audit", "return", "series",
           "marks", "ingest", "forwarding", "learner", "cluster", "fragments_per_s", "result")


def first_committed(path: Path, data: dict) -> int | None:
    """When the run `data` holds was first committed at `path` (following renames): the
    oldest version whose measured figures equal today's, so a run made again in place dates
    from its remake, and a field added to a file later does not move its date."""
    out = git("log", "--follow", "--format=@%ct %H", "--name-only", "--",
              str(path.relative_to(ROOT))) or ""
    versions = []  # (time, commit, path then), newest first
    for block in out.split("@")[1:]:
        lines = [line for line in block.splitlines() if line.strip()]
        if len(lines) >= 2:
            when, sha = lines[0].split()
            versions.append((int(when), sha, lines[1]))
    keys = [k for k in FIGURES if k in data]
    first = None
    for when, sha, old_path in versions:
        try:
            then = json.loads(git("show", f"{sha}:{old_path}") or "null")
        except ValueError:
            break
        if not isinstance(then, dict) or any(then.get(k) != data.get(k) for k in keys):
            break
        first = when
    return first


def recorded_start(data: dict) -> int | None:
    """A start time the file itself records (a soak's `meta.started`, in UTC)."""
    started = (data.get("meta") or {}).get("started")
    if isinstance(started, str):
        try:
            return int(dt.datetime.fromisoformat(started).replace(
                tzinfo=dt.timezone.utc).timestamp())
        except ValueError:
            return None
    return None


def recorded_cores(data: dict) -> int | None:
    for key in ("cpus", "cores", "cpu_count"):
        if isinstance(data.get(key), int):
            return data[key]
    for nest in ("meta", "machine"):
        inner = data.get(nest)
        if isinstance(inner, dict):
            for key in ("cpu_count", "cores"):
                if isinstance(inner.get(key), int):
                    return inner[key]
    return None


def run_seconds(data: dict) -> float | None:
    """How long the run lasted at least, from what the file records (its wall time, or the end
    of its last fault)."""
    wall = data.get("wall_s")
    if isinstance(wall, (int, float)) and wall == wall and wall > 0:
        return float(wall)
    ends = [f.get("end_s") for f in data.get("faults") or [] if isinstance(f, dict)]
    ends = [e for e in ends if isinstance(e, (int, float))]
    return max(ends) if ends else None


def infer(path: Path, data: dict, commits: list[tuple[int, str]]) -> dict:
    """The inferred (or unknown) provenance of a file written before records existed."""
    record = {"status": "unknown", "commit": None, "dirty": None, "machine": None}
    cores = recorded_cores(data)
    if isinstance(data.get("machine"), dict):
        record["machine"] = {**data["machine"], "status": "recorded by the run"}
    elif cores:
        record["machine"] = {"cores": cores, "status": "cores recorded by the run"}
    start_t, basis = recorded_start(data), "the start time the file records"
    if start_t is None:
        added = first_committed(path, data)
        if added is None:
            record["why"] = "the file is not committed and records no start time"
            return record
        when = f"{dt.datetime.fromtimestamp(added, dt.timezone.utc):%Y-%m-%d %H:%M} UTC"
        wall = run_seconds(data)
        if wall:
            start_t = int(added - wall)
            basis = f"the file's first commit ({when}) less the run's {wall:,.0f} s"
        else:
            start_t, basis = added, f"the file's first commit ({when})"
    before = [sha for t, sha in commits if t < start_t]
    if not before:
        record["why"] = "no commit before the run's start"
        return record
    commit = before[-1]
    code = data.get("code")  # what files made before the record said: HEAD when the run ended
    if isinstance(code, str) and code:
        ended_on = (git("rev-parse", "--verify", "--quiet",
                        code.removesuffix("-dirty") + "^{commit}") or "").strip()
        # a run cannot start on a commit made after the one it ended on (`before` is in time
        # order, so an earlier index is an earlier commit)
        if ended_on in before and before.index(ended_on) < len(before) - 1:
            commit = ended_on
            basis += f", bounded by the commit recorded at its end ({code})"
    record.update(status="inferred", commit=commit, commit_date=commit_date(commit),
                  basis=f"last commit before {basis}")
    if isinstance(code, str) and code.endswith("-dirty"):
        record["dirty_at_end"] = True  # the tree differed from its commit when the run ended
    return record


def write_like(path: Path, text: str, data: dict) -> None:
    """Rewrite a data file in the layout it had (indented or on one line)."""
    indent = None
    match = re.match(r"\{\n( +)", text)
    if match:
        indent = len(match.group(1))
    path.write_text(json.dumps(data, indent=indent)
                    + ("\n" if text.endswith("\n") else ""))


def backfill(paths: list[Path]) -> Counter:
    """Give every file without a record an inferred (or unknown) one, in the file (and a
    record that names its commit but not that commit's date, the date)."""
    commits, counts = commit_times(), Counter()
    for path in paths:
        text = path.read_text()
        data = json.loads(text)
        if not isinstance(data, dict):
            continue
        record = data.get(FIELD)
        if isinstance(record, dict):
            if record.get("commit") and not record.get("commit_date"):
                record["commit_date"] = commit_date(record["commit"])
                write_like(path, text, data)
                counts["dated"] += 1
            continue
        data[FIELD] = infer(path, data, commits)
        write_like(path, text, data)
        counts[data[FIELD]["status"]] += 1
    return counts


# ----------------------------------------------------------------------------- the check

def data_files(root: Path | None = None) -> list[Path]:
    return sorted((root or DATA).rglob("*.json"))


def problem(data) -> str | None:
    """Why a data file's provenance does not stand, or None."""
    if not isinstance(data, dict):
        return "not a JSON object"
    record = data.get(FIELD)
    if not isinstance(record, dict):
        return "no provenance"
    status = record.get("status")
    if status not in STATUSES:
        return f"provenance status {status!r} is none of {', '.join(STATUSES)}"
    if status == "recorded":
        missing = [k for k in ("commit", "dirty", "machine", "command", "started_at",
                               "packages") if record.get(k) in (None, "", [])]
        if missing:
            return f"recorded provenance lacks {', '.join(missing)}"
    if record.get("diff_file") and not (ROOT / record["diff_file"]).is_file():
        return f"the diff its record names, {record['diff_file']}, is missing"
    if status == "inferred" and not (record.get("commit") and record.get("basis")):
        return "inferred provenance lacks its commit or its basis"
    if status == "unknown" and not record.get("why"):
        return "unknown provenance does not say why"
    return None


def machine_text(record: dict) -> str:
    m = record.get("machine") or {}
    if not m:
        return "unknown"
    parts = [m.get("cpu"), f"{m['cores']} cores" if m.get("cores") else None,
             ", ".join(m.get("gpus") or []) or m.get("device")]
    return " / ".join(p for p in parts if p) or "unknown"


def listing(paths: list[Path]) -> tuple[list[str], Counter, list[str]]:
    """One line per file, the counts by status and the files that fail the check."""
    lines, counts, bad = [], Counter(), []
    for path in paths:
        name = str(path.relative_to(ROOT))
        try:
            data = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            bad.append(f"{name}: unreadable ({exc})")
            continue
        why = problem(data)
        if why:
            bad.append(f"{name}: {why}")
            continue
        record = data[FIELD]
        counts[record["status"]] += 1
        dirty = {True: "dirty", False: "clean", None: "dirty?"}[record.get("dirty")]
        commit = (record.get("commit") or "—")[:10]
        lines.append(f"{record['status']:8s} {commit:10s} {dirty:6s} "
                     f"{machine_text(record)[:48]:48s} {name}")
    return lines, counts, bad


# ----------------------------------------------------------------------------- the pages

# Which data each page's figures come from (prefixes under docs/data/).
PAGES = {
    "docs/RESULTS.md": ("paper/", "race/", "race-tune/", "race-superseded/", "race-pace/", "tune/",
                        "check/", "superseded/", "thinlink/"),
    "docs/ABLATIONS.md": ("ablation/", "paper/Ant-v5__tpdeb", "paper/Hopper-v5__tpdeb",
                          "tune/hc-long-klt0.2/", "chaos-30-fixed-kl"),
    "docs/RELIABILITY.md": ("chaos-", "soak", "crowd/", "faults/", "partition/",
                            "replay-snapshot", "fuzz", "tune/hc-long-klt0.2/"),
    "docs/BENCHMARKS.md": ("gpu/", "capacity/", "crowd/", "learner/", "eval/"),
}
BEGIN, END = "<!-- provenance:begin -->", "<!-- provenance:end -->"
GRID_RESULTS = "docs/RESULTS.md"


def page_counts(page: str, paths: list[Path]) -> tuple[Counter, list[str]]:
    counts, unknown = Counter(), []
    for path in paths:
        rel = str(path.relative_to(DATA))
        if not rel.startswith(PAGES[page]):
            continue
        record = json.loads(path.read_text()).get(FIELD) or {}
        status = record.get("status", "none")
        counts[status] += 1
        if status == "unknown":
            unknown.append(rel)
    return counts, unknown


def page_block(page: str, paths: list[Path]) -> str:
    """The line under a page's title that counts its data files by provenance."""
    counts, unknown = page_counts(page, paths)
    total = sum(counts.values())
    return (f"*Provenance of this page's {total} data files (`docs/data/`: "
            f"{', '.join(f'`{p}`' for p in PAGES[page])}): {counts['recorded']} record the "
            f"commit, tree and machine they were made on; {counts['inferred']} were made before "
            f"that record existed and carry the commit inferred from their start "
            f"(`\"status\": \"inferred\"`: the last commit before it); {counts['unknown']} "
            f"unknown" + (f" ({', '.join(unknown)})" if unknown else "") + ". "
            "`python bench/provenance.py --check` lists each.*")


GRID = "paper/"  # the comparison grid, whose commits RESULTS tabulates
GRID_BEGIN, GRID_END = "<!-- grid-commits:begin -->", "<!-- grid-commits:end -->"
NAMES = {"tpdeb": "TPDEB", "impact": "IMPACT", "ppo-per": "PPO+PER"}


def commit_table(paths: list[Path], prefix: str = GRID) -> str:
    """The commits a grid's runs ran on, a row per commit (oldest first) with the runs made on
    it by task and algorithm, from each file's provenance."""
    rows: dict[str, list[dict]] = {}
    for path in paths:
        if not str(path.relative_to(DATA)).startswith(prefix):
            continue
        data = json.loads(path.read_text())
        record = data.get(FIELD) or {}
        rows.setdefault(record.get("commit") or "unknown", []).append({**data, FIELD: record})
    dates = {sha: min((r[FIELD].get("commit_date") or "") for r in runs)
             for sha, runs in rows.items()}
    lines = ["| commit | its date | provenance | tree | runs |", "|---|---|---|---|---|"]
    for sha in sorted(rows, key=lambda c: (dates[c] or "~", c)):
        runs = rows[sha]
        date = dates[sha][:16].replace("T", " ")
        status = "/".join(sorted({r[FIELD].get("status", "none") for r in runs}))
        tree = "; ".join(sorted({tree_text(r) for r in runs}))
        cells: dict[tuple[str, str], list[int]] = {}
        for r in runs:
            cells.setdefault((r.get("env_id", "?"), r.get("algo", "?")), []).append(r.get("seed"))
        what = "; ".join(f"{env.removesuffix('-v5')} {NAMES.get(algo, algo)} "
                         f"{', '.join(str(s) for s in sorted(seeds))}"
                         for (env, algo), seeds in sorted(cells.items()))
        lines.append(f"| {sha[:7]} | {date} | {status} | {tree} | {len(runs)}: {what} |")
    return "\n".join(lines)


def tree_text(data: dict) -> str:
    record = data[FIELD]
    if record.get("dirty") is not None:
        return "dirty" if record["dirty"] else "clean"
    return "dirty when it ended" if record.get("dirty_at_end") else "not known"


def replace_block(text: str, begin: str, end: str, inner: str) -> str | None:
    """`text` with `inner` between the markers `begin` and `end` (what lay between them gone);
    None where `begin` is not in it."""
    if begin not in text:
        return None
    head, rest = text.split(begin, 1)
    tail = rest.split(end, 1)[1] if end in rest else ""
    return f"{head}{begin}\n{inner}\n{end}{tail}"


def rendered_pages(paths: list[Path]) -> dict[str, str]:
    """Each page's text as the files say it should read: its count under the title (put there
    when the page has none yet) and, on RESULTS, the grid's commit table."""
    pages = {}
    for page in PAGES:
        text = (ROOT / page).read_text()
        block = page_block(page, paths)
        new = replace_block(text, BEGIN, END, block)
        if new is None:
            title, _, rest = text.partition("\n")
            new = f"{title}\n\n{BEGIN}\n{block}\n{END}\n{rest}"
        if page == GRID_RESULTS:
            new = replace_block(new, GRID_BEGIN, GRID_END, commit_table(paths)) or new
        pages[page] = new
    return pages


def stale_pages(paths: list[Path]) -> list[str]:
    """Pages whose counts (or commit table) differ from what the files say."""
    return [page for page, new in rendered_pages(paths).items()
            if new != (ROOT / page).read_text()]


def write_pages(paths: list[Path]) -> list[str]:
    """Bring every stale page up to date; the pages changed."""
    changed = []
    for page, new in rendered_pages(paths).items():
        if new != (ROOT / page).read_text():
            (ROOT / page).write_text(new)
            changed.append(page)
    return changed


def keep_diff(path: Path) -> None:
    """Copy the diff a data file's record names from where its run staged it to
    docs/data/diffs/, where the record says it lies."""
    try:
        record = json.loads(Path(path).read_text()).get(FIELD) or {}
    except (OSError, ValueError, AttributeError):
        return
    name = record.get("diff_file")
    if not name:
        return
    kept = ROOT / name
    staged = staged_diff(kept.name)
    if not kept.exists() and staged.is_file():
        kept.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(staged, kept)


def written(path: Path) -> None:
    """A bench wrote a data file at `path`: where it lies under docs/data/, the pages' counts
    (and RESULTS' table of the grid's commits) follow it, so a result committed as it comes
    leaves no page stale."""
    try:
        Path(path).resolve().relative_to(DATA.resolve())
    except ValueError:
        return
    keep_diff(path)
    changed = write_pages(data_files())
    if changed:
        print(f"provenance: counts updated in {', '.join(changed)}", flush=True)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    mode = p.add_mutually_exclusive_group(required=True)
    mode.add_argument("--check", action="store_true",
                      help="list every data file's provenance; exit 1 where one has none")
    mode.add_argument("--infer", action="store_true",
                      help="write an inferred (or unknown) record into files that have none")
    mode.add_argument("--pages", action="store_true", help="rewrite the pages' provenance counts")
    p.add_argument("--data", type=Path, help=argparse.SUPPRESS)  # tests: another data dir
    p.add_argument("-q", "--quiet", action="store_true", help="only the counts and problems")
    args = p.parse_args(argv)
    paths = data_files(args.data)
    if args.infer:
        counts = backfill(paths)
        print(f"provenance: {sum(counts.values())} files given a record: "
              + ", ".join(f"{n} {s}" for s, n in sorted(counts.items())))
        return 0
    if args.pages:
        changed = write_pages(paths)
        print("provenance: " + (f"updated {', '.join(changed)}" if changed else "pages up to date"))
        return 0
    lines, counts, bad = listing(paths)
    if not args.quiet:
        print("status   commit     tree   machine" + " " * 42 + "file")
        print("\n".join(lines))
    print(f"provenance: {len(paths)} data files: " + ", ".join(
        f"{counts[s]} {s}" for s in STATUSES) + f"; {len(bad)} without a record")
    for line in bad:
        print(f"  NO PROVENANCE: {line}")
    if bad:
        print("  (a file made before the record existed: python bench/provenance.py --infer; a "
              "missing diff: it is copied from bench/out/diffs/ when its bench writes the file, "
              "so run the bench again or restore docs/data/diffs/)")
    stale = stale_pages(paths) if args.data is None else []
    for page in stale:
        print(f"  STALE: {page}'s provenance counts differ from the files "
              "(python bench/provenance.py --pages)")
    prefixes = tuple(p for page in PAGES.values() for p in page)
    unpaged = [path for path in paths if args.data is None
               and not str(path.relative_to(DATA)).startswith(prefixes)]
    for path in unpaged:
        print(f"  ON NO PAGE: {path.relative_to(ROOT)} (bench/provenance.py's PAGES says which "
              "page counts which files)")
    return 1 if bad or stale or unpaged else 0


if __name__ == "__main__":
    sys.exit(main())
