"""`tpdeb-eval`: run a trained policy deterministically and report its return.

    tpdeb-eval runs/Hopper-v5__tpdeb__1__1700000000            # the run's final checkpoint
    tpdeb-eval runs/…/checkpoints/ckpt_900_288000.pt --episodes 20 --seed 7
    tpdeb-eval RUN_DIR --video hopper.mp4                      # headless, MuJoCo offscreen

The policy acts with its Gaussian mean (clipped to the action bounds) on observations
normalised by the statistics saved in the checkpoint. Episode i starts from `reset(seed=S + i)`,
so the same seed gives the same figures on every repeat. Prints mean ± std return and length;
`--json` prints them as one JSON line instead (for scripts).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
from pathlib import Path

PROG = "tpdeb-eval"


class EvalError(Exception):
    """A reason to stop with one line and exit status 2."""


def find_checkpoint(target: Path) -> Path:
    """A checkpoint file as given, or a run dir's final checkpoint (else its newest one)."""
    from tpdeb.services.store.checkpoint import FINAL, checkpoint_dir, list_checkpoints

    if target.is_file():
        return target
    if not target.is_dir():
        raise EvalError(f"{target}: no such checkpoint or run directory")
    found = list_checkpoints(checkpoint_dir(target))
    if not found:
        raise EvalError(f"{target}: no checkpoints in {checkpoint_dir(target)} (has the learner "
                        "written one yet?)")
    finals = [c for c in found if c.tag == FINAL]
    return (finals or found)[-1].path


def load_policy(path: Path, env_id: str | None, device: str = "cpu"):
    """(model, env_id, env_kwargs) from a checkpoint; refuses one trained on another env than
    `env_id`."""
    from tpdeb.services.store.checkpoint import read_checkpoint
    from tpdeb.tpdeb_core.model import ActorCritic
    from tpdeb.tpdeb_core.policy import dims_of, policy_std_of

    try:
        state = read_checkpoint(path)
    except ValueError as exc:
        raise EvalError(f"{path}: {exc}") from None
    config = state.get("config") or {}
    spec = state.get("spec") or {}
    trained_on = spec.get("env_id") or config.get("env_id")
    if not trained_on:
        raise EvalError(f"{path}: the checkpoint does not say which env it was trained on")
    if env_id and env_id != trained_on:
        raise EvalError(f"{path} was trained on {trained_on}, not {env_id}: pass a checkpoint "
                        f"of {env_id} or drop --env-id")
    weights = state["model"]
    obs_dim, act_dim, hidden = dims_of(weights)
    model = ActorCritic(obs_dim, act_dim, hidden, obs_clip=config.get("obs_clip", 10.0),
                        policy_std=policy_std_of(weights))
    try:
        model.load_state_dict(weights)
    except RuntimeError as exc:
        raise EvalError(f"{path}: the weights do not fit the network its config describes "
                        f"({str(exc).splitlines()[0][:160]})") from None
    from tpdeb.services.config import ConfigError
    from tpdeb.services.device import resolve_device

    try:
        model.to_device(resolve_device(device))
    except ConfigError as exc:
        raise EvalError(str(exc)) from None
    return model, trained_on, config.get("env_kwargs", "")


def make_env(env_id: str, video: bool, env_kwargs: str = ""):
    import gymnasium as gym

    from tpdeb.services.config import ConfigError
    from tpdeb.services.envs import import_env_module, parse_env_kwargs, quiet_mujoco

    quiet_mujoco()
    if video:
        os.environ.setdefault("MUJOCO_GL", "egl")
    try:
        import_env_module(env_id)
        kwargs = parse_env_kwargs(env_kwargs)
        if video:  # only then: an env without rendering need not take render_mode at all
            kwargs["render_mode"] = "rgb_array"
        return gym.make(env_id, **kwargs)
    except (ConfigError, ValueError, TypeError, gym.error.Error) as exc:
        raise EvalError(f"env {env_id!r} cannot be made here: {exc}") from None


def evaluate(model, env, episodes: int, seed: int, frames: list | None = None) -> dict:
    """Deterministic returns and lengths over `episodes` episodes (episode i: seed + i)."""
    import numpy as np

    low, high = env.action_space.low, env.action_space.high
    returns, lengths = [], []
    for episode in range(episodes):
        obs, _ = env.reset(seed=seed + episode)
        total, steps, done = 0.0, 0, False
        while not done:
            action = model.act_deterministic(np.asarray(obs, np.float32)[None])[0]
            obs, reward, terminated, truncated, _ = env.step(np.clip(action, low, high))
            total += float(reward)
            steps += 1
            done = terminated or truncated
            if frames is not None:
                frames.append(env.render())
        returns.append(total)
        lengths.append(steps)
    spread = statistics.pstdev
    return {"episodes": episodes, "seed": seed, "mean_return": statistics.mean(returns),
            "std_return": spread(returns), "mean_length": statistics.mean(lengths),
            "std_length": spread(lengths), "returns": returns, "lengths": lengths}


def write_video(frames: list, path: Path, fps: int) -> None:
    try:
        import imageio.v2 as imageio
        import imageio_ffmpeg  # noqa: F401  (the encoder imageio needs for .mp4)
    except ImportError:
        raise EvalError("--video needs imageio and imageio-ffmpeg: pip install "
                        "'tpdeb[video]' (or imageio imageio-ffmpeg)") from None
    path.parent.mkdir(parents=True, exist_ok=True)
    imageio.mimwrite(path, frames, fps=fps, macro_block_size=1)


def render_check(env) -> None:
    """Fail early, with the reason, where MuJoCo cannot render offscreen."""
    try:
        env.reset(seed=0)
        frame = env.render()
    except Exception as exc:  # GL platform errors come as many types
        raise EvalError(
            f"--video: MuJoCo cannot render offscreen here ({type(exc).__name__}: "
            f"{str(exc).splitlines()[0][:160] if str(exc) else ''}); it needs EGL (libEGL, "
            "MUJOCO_GL=egl) or OSMesa (MUJOCO_GL=osmesa). The returns without --video still "
            "work") from None
    if frame is None:
        raise EvalError("--video: the env returned no frame (it has no rgb_array rendering)")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("target", help="a checkpoint (.pt) or a run directory")
    parser.add_argument("--episodes", type=int, default=10, help="episodes to run (default 10)")
    parser.add_argument("--seed", type=int, default=0, help="episode i starts from seed + i")
    parser.add_argument("--env-id", help="refuse a checkpoint trained on any other env")
    parser.add_argument("--device", default="cpu",
                        help="auto | cpu | cuda | cuda:N: where the policy runs (default cpu: "
                        "one observation at a time is faster there)")
    parser.add_argument("--video", type=Path, help="write the episodes to this .mp4 file")
    parser.add_argument("--fps", type=int, default=0, help="video frame rate (default: the env's)")
    parser.add_argument("--json", action="store_true", help="print one JSON line")
    args = parser.parse_args(argv)
    try:
        if args.episodes < 1:
            raise EvalError(f"--episodes {args.episodes}: must be ≥ 1")
        path = find_checkpoint(Path(args.target))
        import torch

        torch.set_num_threads(1)
        model, env_id, env_kwargs = load_policy(path, args.env_id, args.device)
        env = make_env(env_id, args.video is not None, env_kwargs)
        frames = None
        if args.video is not None:
            render_check(env)
            frames = []
        result = evaluate(model, env, args.episodes, args.seed, frames)
        if frames is not None:
            fps = args.fps or int(env.metadata.get("render_fps", 30))
            write_video(frames, args.video, fps)
        env.close()
    except EvalError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
    result.update(checkpoint=str(path), env_id=env_id)
    if args.json:
        print(json.dumps(result))
        return 0
    print(f"{env_id} | {path} | {args.episodes} episodes from seed {args.seed}")
    print(f"return {result['mean_return']:,.1f} ± {result['std_return']:,.1f} | length "
          f"{result['mean_length']:,.1f} ± {result['std_length']:,.1f}")
    if args.video is not None:
        print(f"video: {args.video} ({len(frames)} frames)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
