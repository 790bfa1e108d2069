"""Test fakes: a deterministic vector env with scripted episode ends (Acme's fakes idea)."""

from __future__ import annotations

import numpy as np


class ScriptedVectorEnv:
    """obs = [episode number, time in episode, env index]; reward = 1 + 0.1·t.

    Env i's episodes last `lengths[i]` steps and end by termination if `terminates[i]`, else
    by truncation. Autoreset follows gymnasium: SAME_STEP puts the final obs in
    info["final_obs"] and returns the reset obs at once; NEXT_STEP returns the final obs, and the
    following step only resets (action ignored, reward 0, no done flags).
    """

    def __init__(self, lengths, terminates, same_step: bool = True):
        self.num_envs = len(lengths)
        self.lengths = list(lengths)
        self.terminates = list(terminates)
        self.same_step = same_step
        self.steps_taken = 0

    def _obs(self, i):
        return np.array([self.episode[i], self.t[i], i], dtype=np.float64)

    def reset(self, seed=None):
        self.episode = [0] * self.num_envs
        self.t = [0] * self.num_envs
        self.needs_reset = [False] * self.num_envs
        return np.stack([self._obs(i) for i in range(self.num_envs)]), {}

    def step(self, actions):
        assert actions.shape[0] == self.num_envs
        self.steps_taken += 1
        obs, rewards = [], np.zeros(self.num_envs)
        terminated = np.zeros(self.num_envs, bool)
        truncated = np.zeros(self.num_envs, bool)
        final_obs = np.empty(self.num_envs, dtype=object)
        for i in range(self.num_envs):
            if self.needs_reset[i]:  # NEXT_STEP autoreset step
                self.needs_reset[i] = False
                self.episode[i] += 1
                self.t[i] = 0
                obs.append(self._obs(i))
                continue
            rewards[i] = 1.0 + 0.1 * self.t[i]
            self.t[i] += 1
            if self.t[i] == self.lengths[i]:
                terminated[i] = self.terminates[i]
                truncated[i] = not self.terminates[i]
                if self.same_step:
                    final_obs[i] = self._obs(i)
                    self.episode[i] += 1
                    self.t[i] = 0
                else:
                    self.needs_reset[i] = True
            obs.append(self._obs(i))
        info = {"final_obs": final_obs} if self.same_step else {}
        return np.stack(obs), rewards, terminated, truncated, info
