"""One peer run of the race (bench/race.py): Stable-Baselines3's SAC or PPO with
rl-baselines3-zoo's hyperparameters for the task (`sb3-sac`, `sb3-ppo`), or SAC as CleanRL's
single-file script runs it (`cleanrl-sac`, bench/cleanrl_sac.py), trained for a wall-clock
budget on this machine: its training curve against time and the deterministic return of its
policy at each mark.

    python bench/peers.py --system sb3-sac --env-id Hopper-v5 --seed 11 --seconds 900 \\
        --marks 300 600 900 --out docs/data/race/sb3-sac/Hopper-v5__11.json

Needs the bench-only extra: `pip install -e '.[peers]'` (stable-baselines3, sb3-contrib, rl_zoo3).
The hyperparameters are the zoo's own, read from the installed `rl_zoo3/hyperparams/{algo}.yml`
(its MuJoCo entries are for v4; the same task at v5 is run). Settings the zoo writes as Python
text (`policy_kwargs`, `normalize`) are read by a small literal parser (`dict(...)`, numbers,
lists, `nn.ReLU`/`nn.Tanh`), never evaluated; wrappers come only from an allowed list. The
model is built as the zoo builds it (VecNormalize where it says `normalize`, `lin_` schedules,
its `n_envs`) and `learn(n_timesteps)` is called with the zoo's step budget, so every schedule is
the one a zoo user gets; a callback stops it when the wall-clock budget is spent.

The clock starts with `learn()` (building the env and the model is not counted) and the budget
is checked at every env step (PPO finishes the update it is in). At each mark the policy's
parameters and the observation normaliser are copied in memory; a run whose zoo step budget ends
first (PPO on Swimmer: 1M steps in under 5 minutes) holds its final policy at every later mark,
as its user would. After training, outside the budget, each copy is evaluated for 10
deterministic episodes (episode i from `reset(seed=10000 + seed + i)`, as tpdeb-eval is run by
the benches). Nothing is written but the result JSON.
"""

from __future__ import annotations

import argparse
import ast
import copy
import importlib
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from runs import save_json  # noqa: E402

ALGOS = ("sac", "ppo")
SYSTEMS = ("sb3-sac", "sb3-ppo", "cleanrl-sac")
# What the zoo's entries may name as an env wrapper (anything else is refused, not imported).
WRAPPERS = {"sb3_contrib.common.wrappers.TimeFeatureWrapper"}
# Zoo keys that configure the run, not the algorithm's constructor.
RUN_KEYS = {"n_timesteps", "policy", "n_envs", "normalize", "normalize_kwargs", "env_wrapper"}


def literal(text: str):
    """A zoo setting written as Python (`dict(net_arch=[256, 256], activation_fn=nn.ReLU)`):
    literals, lists, `dict(...)` calls and the activations, nothing else."""
    import torch.nn as nn

    names = {"nn.ReLU": nn.ReLU, "nn.Tanh": nn.Tanh, "nn.ELU": nn.ELU, "True": True,
             "False": False, "None": None}

    def value(node):
        if isinstance(node, ast.Constant):
            return node.value
        if isinstance(node, (ast.List, ast.Tuple)):
            return [value(e) for e in node.elts]
        if isinstance(node, ast.Dict):
            return {value(k): value(v) for k, v in zip(node.keys, node.values, strict=True)}
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) \
                and node.func.id == "dict" and not node.args:
            return {k.arg: value(k.value) for k in node.keywords}
        if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub):
            return -value(node.operand)
        dotted = ast.unparse(node)
        if dotted in names:
            return names[dotted]
        raise ValueError(f"zoo setting {text!r}: {dotted!r} is not a literal this bench reads")

    return value(ast.parse(text.strip(), mode="eval").body)


def zoo_hyperparams(algo: str, env_id: str) -> tuple[str, dict]:
    """(the zoo's entry name, its settings) for `env_id` (its v4 or v3 entry for a v5 task)."""
    from importlib import resources

    import yaml

    table = yaml.safe_load((resources.files("rl_zoo3") / "hyperparams" / f"{algo}.yml")
                           .read_text())
    family = env_id.rsplit("-v", 1)[0]
    for key in (env_id, f"{family}-v4", f"{family}-v3"):
        if key in table:
            return key, dict(table[key])
    raise SystemExit(f"peers: rl_zoo3 has no {algo} hyperparameters for {env_id} (or its v4/v3)")


def schedule(value):
    """The zoo's `lin_X`: X·(progress remaining); numbers stay numbers."""
    if isinstance(value, str) and value.startswith("lin_"):
        start = float(value[4:])
        return lambda remaining: remaining * start
    return value


def make_model(algo: str, env_id: str, seed: int, hp: dict):
    """The zoo's model for the task: (model, its VecNormalize or None, the wrapper class)."""
    import stable_baselines3 as sb3
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import VecNormalize

    wrapper = hp.get("env_wrapper")
    if wrapper is not None:
        if wrapper not in WRAPPERS:
            raise SystemExit(f"peers: env_wrapper {wrapper!r} is not one this bench runs")
        module, name = wrapper.rsplit(".", 1)
        wrapper = getattr(importlib.import_module(module), name)
    env = make_vec_env(env_id, n_envs=int(hp.get("n_envs", 1)), seed=seed, wrapper_class=wrapper)
    norm = hp.get("normalize", False)
    norm = literal(norm) if isinstance(norm, str) else norm
    vecnorm = None
    if norm:
        kwargs = norm if isinstance(norm, dict) else {}
        kwargs.update(hp.get("normalize_kwargs") or {})
        env = vecnorm = VecNormalize(env, gamma=float(hp.get("gamma", 0.99)), **kwargs)
    kwargs = {k: schedule(v) for k, v in hp.items() if k not in RUN_KEYS}
    if isinstance(kwargs.get("policy_kwargs"), str):
        kwargs["policy_kwargs"] = literal(kwargs["policy_kwargs"])
    cls = {"sac": sb3.SAC, "ppo": sb3.PPO}[algo]
    return cls(hp.get("policy", "MlpPolicy"), env, seed=seed, verbose=0, **kwargs), vecnorm, wrapper


def budget_callback(seconds: float, marks: list[float], vecnorm, say):
    """Stops `learn()` after `seconds`; records episodes (time, steps, return) and, at each
    mark, a copy of the policy's parameters and the observation normaliser."""
    from stable_baselines3.common.callbacks import BaseCallback

    class Budget(BaseCallback):
        def _on_training_start(self) -> None:
            self.start = self.last_say = time.monotonic()
            self.episodes, self.snapshots, self.pending = [], [], sorted(marks)

        def _on_step(self) -> bool:
            now = time.monotonic()
            t = now - self.start
            for info in self.locals.get("infos", []):
                if "episode" in info:
                    self.episodes.append((round(t, 2), int(self.num_timesteps),
                                          float(info["episode"]["r"])))
            while self.pending and t >= self.pending[0]:
                self.snapshot(self.pending.pop(0), t)
            if now - self.last_say >= 30:
                recent = [r for _, _, r in self.episodes[-10:]]
                say(f"{t:6.0f}/{seconds:.0f} s | {self.num_timesteps:,} steps | return "
                    f"{statistics.mean(recent) if recent else float('nan'):,.1f}")
                self.last_say = now
            return t < seconds

        def _on_training_end(self) -> None:
            """The zoo's step budget spent before the wall-clock's: the final policy is the
            one its user holds at every mark still to come."""
            t = time.monotonic() - self.start
            while self.pending:
                self.snapshot(self.pending.pop(0), t, ended=True)

        def snapshot(self, mark: float, t: float, ended: bool = False) -> None:
            self.snapshots.append({
                "mark": mark, "t_s": round(t, 2), "steps": int(self.num_timesteps),
                "policy": {k: v.detach().clone()
                           for k, v in self.model.policy.state_dict().items()},
                "obs_rms": copy.deepcopy(vecnorm.obs_rms) if vecnorm is not None else None,
                "ended_before": ended})

    return Budget()


def evaluate(model, snapshot: dict, env_id: str, wrapper, vecnorm, seed: int,
             episodes: int) -> dict:
    """The snapshot's deterministic return over `episodes` fresh episodes."""
    model.policy.load_state_dict(snapshot["policy"])
    rms = snapshot["obs_rms"]

    def act(obs):
        if rms is not None and vecnorm.norm_obs:
            obs = np.clip((obs - rms.mean) / np.sqrt(rms.var + vecnorm.epsilon),
                          -vecnorm.clip_obs, vecnorm.clip_obs)
        return model.predict(obs, deterministic=True)[0]

    return rollouts(act, env_id, seed, episodes, wrapper)


def rollouts(act, env_id: str, seed: int, episodes: int, wrapper=None) -> dict:
    """`act(obs) -> action` over `episodes` fresh episodes, episode i from reset(seed + i)."""
    import gymnasium as gym

    returns, lengths = [], []
    for i in range(episodes):
        env = gym.make(env_id)
        env = wrapper(env) if wrapper is not None else env
        obs, _ = env.reset(seed=seed + i)
        total, length, done = 0.0, 0, False
        while not done:
            obs, reward, terminated, truncated, _ = env.step(act(obs))
            total, length = total + float(reward), length + 1
            done = terminated or truncated
        env.close()
        returns.append(total)
        lengths.append(length)
    return {"episodes": episodes, "seed": seed, "mean_return": statistics.mean(returns),
            "std_return": statistics.pstdev(returns), "mean_length": statistics.mean(lengths),
            "returns": returns}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--system", choices=SYSTEMS, required=True)
    parser.add_argument("--env-id", required=True)
    parser.add_argument("--seed", type=int, required=True)
    parser.add_argument("--seconds", type=float, default=900.0)
    parser.add_argument("--marks", type=float, nargs="+", default=[300.0, 600.0, 900.0])
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument("--threads", type=int, default=2,
                        help="torch threads (the machine's cores)")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="change one of the zoo's settings (a diagnostic, not the race; "
                             "sb3 systems)")
    args = parser.parse_args()
    import torch

    torch.set_num_threads(args.threads)

    def say(text: str) -> None:
        print(f"[peers] {args.system} {args.env_id} seed {args.seed}: {text}", flush=True)

    marks = [m for m in args.marks if m <= args.seconds]
    run = run_cleanrl if args.system == "cleanrl-sac" else run_sb3
    result = {"system": args.system, "env_id": args.env_id, "seed": args.seed,
              "budget_s": args.seconds, "threads": args.threads,
              **run(args, marks, say)}
    save_json(args.out, result)


def run_sb3(args, marks: list[float], say) -> dict:
    import yaml

    algo = args.system.split("-", 1)[1]
    key, hp = zoo_hyperparams(algo, args.env_id)
    for item in args.set:
        name, _, value = item.partition("=")
        hp[name.strip()] = yaml.safe_load(value)
    say(f"zoo entry {key}: {hp}")
    model, vecnorm, wrapper = make_model(algo, args.env_id, args.seed, hp)
    callback = budget_callback(args.seconds, marks, vecnorm, say)
    started = time.monotonic()
    model.learn(total_timesteps=int(float(hp.get("n_timesteps", 1e6))), callback=callback)
    train_s = time.monotonic() - started
    say(f"trained {train_s:.0f} s, {model.num_timesteps:,} steps; evaluating "
        f"{len(callback.snapshots)} snapshots")
    evaluated = {}
    for snap in callback.snapshots:
        evaluated[str(int(snap["mark"]))] = {
            "t_s": snap["t_s"], "steps": snap["steps"],
            **({"ended_before": True} if snap["ended_before"] else {}),
            "eval": evaluate(model, snap, args.env_id, wrapper, vecnorm, 10_000 + args.seed,
                             args.eval_episodes)}
        say_mark(say, snap, evaluated)
    return {"zoo_entry": key, "changed": args.set,
            "hyperparams": {k: str(v) for k, v in hp.items()},
            "train_s": round(train_s, 1), "steps": int(model.num_timesteps),
            "episodes": callback.episodes, "marks": evaluated}


def run_cleanrl(args, marks: list[float], say) -> dict:
    import dataclasses

    import cleanrl_sac

    if args.set:
        raise SystemExit("peers: --set changes the zoo's settings; cleanrl-sac has none")
    settings = cleanrl_sac.Settings()
    say(f"settings: {dataclasses.asdict(settings)}")
    out = cleanrl_sac.train(args.env_id, args.seed, args.seconds, marks, say, settings)
    say(f"trained {out['train_s']:.0f} s, {out['steps']:,} steps; evaluating "
        f"{len(out['snapshots'])} snapshots")
    evaluated = {}
    for snap in out["snapshots"]:
        evaluated[str(int(snap["mark"]))] = {
            "t_s": snap["t_s"], "steps": snap["steps"],
            "eval": cleanrl_sac.evaluate(out["actor"], snap, args.env_id, 10_000 + args.seed,
                                         args.eval_episodes)}
        say_mark(say, snap, evaluated)
    return {"hyperparams": {k: str(v) for k, v in dataclasses.asdict(settings).items()},
            "train_s": round(out["train_s"], 1), "steps": out["steps"],
            "episodes": out["episodes"], "marks": evaluated}


def say_mark(say, snap: dict, evaluated: dict) -> None:
    say(f"at {snap['mark']:.0f} s: {snap['steps']:,} steps, evaluation "
        f"{evaluated[str(int(snap['mark']))]['eval']['mean_return']:,.1f}")


if __name__ == "__main__":
    sys.exit(main())
