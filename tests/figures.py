"""Figures a test measured, kept as data when asked: with `TPDEB_KEEP_FIGURES=DIR` a test that
measures (recovery times after a kill, after a partition) writes them to DIR as one JSON file
per run, with the provenance of the run (bench/provenance.py). Without it nothing is written."""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def keep_figures(name: str, figures: dict) -> Path | None:
    """Write `figures` as DIR/NAME__<UTC time>.json where TPDEB_KEEP_FIGURES names DIR."""
    folder = os.environ.get("TPDEB_KEEP_FIGURES")
    if not folder:
        return None
    sys.path.insert(0, str(ROOT / "bench"))
    try:
        import provenance
    finally:
        sys.path.pop(0)
    record = provenance.start(["-m", "pytest", os.environ.get("PYTEST_CURRENT_TEST", name)])
    path = Path(folder) / f"{name}__{time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(provenance.stamp({"test": name, **figures}, record), indent=1))
    provenance.written(path)
    return path
