"""Figures a test measured, kept as data when asked: with `TPDEB_KEEP_FIGURES=DIR` a test that
measures (recovery times after a kill, after a partition) writes them to DIR as one JSON file
per run, with the provenance of the run (bench/provenance.py) taken as the test began. Without
it nothing is written."""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import provenance  # noqa: E402


class Keeper:
    """Takes the run's record when made (the test's start); `keep(name, figures)` writes them."""

    def __init__(self, test_id: str):
        self.folder = os.environ.get("TPDEB_KEEP_FIGURES")
        self.record = provenance.start(["-m", "pytest", test_id]) if self.folder else None

    def keep(self, name: str, figures: dict) -> Path | None:
        """Write `figures` as DIR/NAME__<UTC time>.json; nothing without TPDEB_KEEP_FIGURES."""
        if not self.folder:
            return None
        path = Path(self.folder) / f"{name}__{time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())}.json"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(provenance.stamp({"test": name, **figures}, self.record),
                                   indent=1))
        provenance.written(path)
        return path
