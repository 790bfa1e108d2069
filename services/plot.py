"""`tpdeb-plot`: learning curves from run directories' metrics.jsonl (no TensorBoard needed).

    tpdeb-plot runs/Hopper-v5__*                   # → curves.png
    tpdeb-plot runs/a runs/b -o cmp.png --metric losses/clipfrac

Runs are grouped into variants by their configuration (config.toml) with the seed, the run dir
and bookkeeping left out; the legend names each variant by the settings that tell it apart (e.g.
`algo=impact`). Each variant is drawn as the mean ± std over its seeds of the curves smoothed by
a 20-point moving average, on a common env-step axis; one panel per env id.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import textwrap
from pathlib import Path

from tpdeb.services.config import Parser, flat
from tpdeb.services.store.diskio import OutputError, writable_path
from tpdeb.services.store.metrics import read_metrics

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

PROG = "tpdeb-plot"
# Settings that do not make a run a different variant.
NOT_A_VARIANT = {"seed", "run_dir", "log_interval_s", "torch_threads", "preset",
                 "total_timesteps", "env_id"}
LEGEND_WIDTH = 42  # characters per legend line: a legend stays inside its panel


class PlotError(Exception):
    pass


@dataclasses.dataclass
class Run:
    path: Path
    env_id: str
    settings: dict
    steps: list[float]
    values: list[float]


def read_run(path: Path, metric: str) -> Run:
    from tpdeb.services.config.train import TrainConfig

    metrics = path / "metrics.jsonl"
    if not metrics.is_file():
        raise PlotError(f"{path}: no metrics.jsonl (not a run directory?)")
    names = {f.name for f in dataclasses.fields(TrainConfig)} - NOT_A_VARIANT
    config: dict = {}
    if (path / "config.toml").is_file():
        try:
            # flat(): its tables in one mapping (a run dir written before they existed is flat)
            config = flat(tomllib.loads((path / "config.toml").read_text()))
        except tomllib.TOMLDecodeError as exc:
            raise PlotError(f"{path}/config.toml: not valid TOML ({exc})") from None
    steps, values = [], []
    for row in read_metrics(metrics):
        value = row.get(metric)
        if isinstance(value, (int, float)) and math.isfinite(value):
            steps.append(float(row["global_step"]))
            values.append(float(value))
    settings = {k: v for k, v in config.items() if k in names}
    return Run(path, str(config.get("env_id", "?")), settings, steps, values)


def smooth(values, window: int):
    """Trailing moving average over `window` points (fewer at the start: no edge dip)."""
    import numpy as np

    values = np.asarray(values, dtype=np.float64)
    sums = np.cumsum(np.insert(values, 0, 0.0))
    idx = np.arange(1, len(values) + 1)
    lo = np.maximum(0, idx - window)
    return (sums[idx] - sums[lo]) / (idx - lo)


def variant_labels(runs: list[Run]) -> list[str]:
    """Each run's variant, named by the settings on which the variants differ (a setting a
    run's config does not hold is left out of its name, not written `=None`)."""
    keys = sorted({k for r in runs for k in r.settings})
    differing = [k for k in keys if len({json.dumps(r.settings.get(k)) for r in runs}) > 1]
    if "algo" in differing:  # what an algorithm fixes follows from its name
        from tpdeb.services.config.presets import ALGORITHMS

        implied = set().union(*(fixed({}) for fixed in ALGORITHMS.values()))
        differing = [k for k in differing if k not in implied]
    labels = []
    for r in runs:
        parts = [f"{k}={r.settings[k]}" for k in differing if r.settings.get(k) is not None]
        labels.append(", ".join(parts) if parts else str(r.settings.get("algo", "run")))
    return labels


def draw(runs: list[Run], metric: str, output: Path, window: int) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    labels = variant_labels(runs)
    envs = sorted({r.env_id for r in runs})
    fig, axes = plt.subplots(1, len(envs), figsize=(5.2 * len(envs), 3.8), squeeze=False)
    lines = []
    for ax, env_id in zip(axes[0], envs, strict=True):
        groups: dict[str, list[Run]] = {}
        for run, label in zip(runs, labels, strict=True):
            if run.env_id == env_id:
                groups.setdefault(label, []).append(run)
        for n, (label, members) in enumerate(sorted(groups.items())):
            end = min(max(r.steps) for r in members)
            grid = np.linspace(0.0, end, 200)
            curves = [np.interp(grid, r.steps, smooth(r.values, window)) for r in members]
            mean, std = np.mean(curves, axis=0), np.std(curves, axis=0)
            seeds = f"{len(members)} seed" + ("s" if len(members) > 1 else "")
            band(ax, grid, mean, std, f"C{n % 10}",
                 textwrap.fill(f"{label} ({seeds})", LEGEND_WIDTH))
            finals = [smooth(r.values, window)[-1] for r in members]
            count = f"{len(members)} run{'s' * (len(members) != 1)}"
            lines.append(f"{env_id} | {label} | {count} | final {metric} "
                         f"{np.mean(finals):,.1f} ± {np.std(finals):,.1f}")
        label_axes(ax, env_id, metric)
    save(fig, output)
    return lines


def band(ax, grid, mean, std, color: str, label: str) -> None:
    """A mean curve with its ± std band."""
    ax.plot(grid, mean, color=color, label=label)
    ax.fill_between(grid, mean - std, mean + std, color=color, alpha=0.2)


def label_axes(ax, title: str, ylabel: str) -> None:
    ax.set_title(title)
    ax.set_xlabel("env steps")
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)


def save(fig, path: Path) -> None:
    import matplotlib.pyplot as plt

    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = Parser(prog=PROG, description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", type=Path, help="run directories")
    parser.add_argument("-o", "--output", type=Path, default=Path("curves.png"),
                        help="PNG file to write (default curves.png)")
    parser.add_argument("--metric", default="charts/episodic_return",
                        help="metrics.jsonl tag on the y axis (default charts/episodic_return)")
    parser.add_argument("--window", type=int, default=20,
                        help="moving-average window in points (default 20, as the paper)")
    args = parser.parse_args(argv)
    try:
        if args.window < 1:
            raise PlotError(f"--window {args.window}: must be ≥ 1")
        writable_path(args.output, "-o")
        runs = [read_run(path, args.metric) for path in args.runs]
        empty = [str(r.path) for r in runs if not r.values]
        if empty:
            raise PlotError(f"no {args.metric!r} values in {', '.join(empty)} (is the tag "
                            "spelled as in metrics.jsonl?)")
        try:
            lines = draw(runs, args.metric, args.output, args.window)
        except ImportError:
            raise PlotError("tpdeb-plot needs matplotlib: pip install 'tpdeb[plot]'") from None
        except OSError as exc:  # the disk refused after the check (full, gone)
            raise OutputError.of("-o", args.output, exc) from None
    except (PlotError, OutputError) as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
    print("\n".join(lines))
    print(f"wrote {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
