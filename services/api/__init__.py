"""TPDEB: distributed reinforcement learning for continuous control.

    import tpdeb

    run = tpdeb.train("Hopper-v5", total_timesteps=300_000)   # returns a tpdeb.Run
    policy = tpdeb.load_policy(run.run_dir)                   # numpy only
    action = policy.act(obs, deterministic=True)              # the mean (default: a sample)
    tpdeb.evaluate(policy, episodes=10).mean                  # tpdeb-eval's figures

This file is the package `tpdeb` itself (services/api/ in the repository); what it names loads
on first use, so that importing any of its subpackages (every service does) costs nothing here.
"""

from __future__ import annotations

__all__ = ["Evaluation", "Policy", "PolicyError", "Run", "TrainError", "evaluate", "load_policy",
           "train"]


def __getattr__(name: str):
    if name in __all__:
        from tpdeb.services import python_api

        return getattr(python_api, name)
    raise AttributeError(f"module 'tpdeb' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(__all__)
