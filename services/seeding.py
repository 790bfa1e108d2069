"""One `--seed` for every random source a process has."""

from __future__ import annotations

import random
import sys

import numpy as np


def seed_everything(seed: int) -> None:
    """Seed Python's and numpy's generators, and torch's where the process has loaded it
    (actors and the replay server never import torch: importing it only to seed it would cost
    them its memory and start-up time)."""
    random.seed(seed)
    np.random.seed(seed)
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.manual_seed(seed)
