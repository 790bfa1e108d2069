"""The replay's settings by name and its saved form (`DualReplay.state_dict`).

The constructor's string settings (priority_mode × retention, also what format-1 states
recorded) name a sampler and a remover (`strategy_names`). A saved state carries its format:
format 2 keeps each B_p item's priority ("slot_priority") beside the sampler's own values;
format 1 (no "format") kept one "rank" per slot, which was the priority under retention
"priority" but the insertion key under "fifo". `upgraded` reads format 1 where that is lossless
and refuses it, with the reason, where it is not. `check_saved_slots` checks a state before any
of it is used (a snapshot may come from a damaged or foreign run dir).

Pure: numpy and the standard library only.
"""

from __future__ import annotations

from typing import Any

import numpy as np

PRIORITY_MODES = ("trajectory", "step", "none")
RETENTIONS = ("priority", "fifo")
STATE_FORMAT = 2  # of `state_dict()`; 1 had no "format" and kept tree values as "slot_rank"
# The per-slot fields of a saved B_p, one entry per slot each.
_SLOT_FIELDS = ("slot_keys", "slot_steps", "slot_priority", "slot_mass", "step_masses",
                "slot_items")


def strategy_names(priority_mode: str, retention: str) -> tuple[str, str]:
    """(sampler, remover) names for the constructor's settings. Without priorities ("none") B_p
    can only give way by age, whatever the retention."""
    sampler = {"trajectory": "trajectory", "step": "step", "none": "uniform"}[priority_mode]
    remover = "oldest" if retention == "fifo" or sampler == "uniform" else "lowest_priority"
    return sampler, remover


def upgraded(state: dict[str, Any]) -> dict[str, Any]:
    """A format-1 state as format 2. Format 1 kept one "rank" per slot: the priority under
    retention "priority", but the insertion key under "fifo" (and with priority_mode "none"),
    so a prioritized fifo state has lost its priorities and is refused."""
    version = state.get("format", 1)
    if version == STATE_FORMAT:
        return state
    if version != 1:
        raise ValueError(f"saved replay state has format {version!r}, this version reads "
                         f"{STATE_FORMAT} (or 1)")
    config = dict(state["config"])
    mode, retention = config.get("priority_mode"), config.get("retention", "priority")
    if mode not in PRIORITY_MODES or retention not in RETENTIONS:
        raise ValueError(f"the saved replay state (format 1) has priority_mode={mode!r}, "
                         f"retention={retention!r}: not a replay this version knows")
    sampler, remover = strategy_names(mode, retention)
    if sampler != "uniform" and remover == "oldest":
        raise ValueError("the saved replay state is format 1 with retention='fifo', which kept "
                         "insertion keys where the priorities belong: its priorities are lost; "
                         "restore it with the version that wrote it, or start afresh")
    config.update(sampler=sampler, remover=remover)
    slots = len(state["slots"])
    priority = (np.zeros(slots) if sampler == "uniform"
                else np.asarray(state["slot_rank"], dtype=np.float64))
    return {**state, "format": STATE_FORMAT, "config": config, "slot_priority": priority}


def check_saved_slots(state: dict[str, Any], capacity: int) -> None:
    """A saved B_p must be self-consistent before any of it is used: one entry per slot in
    every per-slot field, distinct slots inside the capacity, positive step counts."""
    slots = np.asarray(state["slots"], dtype=np.int64)
    n = len(slots)
    if slots.ndim != 1 or len(set(slots.tolist())) != n or (n and not (
            slots.min() >= 0 and slots.max() < capacity)):
        raise ValueError(f"saved slots {slots.tolist()[:8]}… are not distinct slots below the "
                         f"capacity {capacity}")
    for name in _SLOT_FIELDS:
        if len(state[name]) != n:
            raise ValueError(f"saved {name} has {len(state[name])} entries for {n} slots")
    if n and np.asarray(state["slot_steps"]).min() <= 0:
        raise ValueError("saved slot_steps must be > 0")
    for entry in state["uniform"]:
        if len(entry) != 3:
            raise ValueError(f"a saved uniform entry has {len(entry)} fields, not 3")
