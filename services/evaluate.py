"""`tpdeb-eval`: run a trained policy deterministically and report its return.

    tpdeb-eval runs/Hopper-v5__tpdeb__1__1700000000            # the run's final checkpoint
    tpdeb-eval runs/…/checkpoints/ckpt_900_288000.pt --episodes 20 --seed 7
    tpdeb-eval runs/…/policy.npz                                # a policy file (tpdeb-export's)
    tpdeb-eval RUN_DIR --video hopper.mp4                      # headless, MuJoCo offscreen

Whatever the source, the policy is the numpy `Policy` that `tpdeb.load_policy` gives: it acts
with its Gaussian mean (clipped to the action bounds) on observations normalised by the saved
statistics. Episode i starts from `reset(seed=S + i)`, so the same seed gives the same figures
on every repeat. Prints mean ± std return and length; `--json` prints them as one JSON line
instead (for scripts). From Python: `tpdeb.evaluate(policy_or_path, episodes=10, seed=0)`.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import statistics
import sys
from pathlib import Path

from tpdeb.services.config import Parser
from tpdeb.services.policy_file import (
    Policy,
    PolicyError,
    find_checkpoint,
)
from tpdeb.services.policy_file import load_policy as load_numpy_policy
from tpdeb.services.store.diskio import OutputError, writable_path

PROG = "tpdeb-eval"


class EvalError(PolicyError):
    """A reason evaluation cannot run (a bad setting, an env that cannot be made here): one line,
    and tpdeb-eval's exit status 2."""


@dataclasses.dataclass(frozen=True)
class Evaluation:
    """The episodes' returns and lengths (episode i from `reset(seed=seed + i)`), and the mean
    and population std of the returns."""

    mean: float
    std: float
    returns: tuple[float, ...]
    lengths: tuple[int, ...]


def evaluate(policy: Policy | str | os.PathLike, env_id: str | None = None, episodes: int = 10,
             seed: int = 0, deterministic: bool = True) -> Evaluation:
    """Run `policy` (a `Policy`, a run dir, a checkpoint or a policy.npz) for `episodes` episodes
    of the env it was trained on, as tpdeb-eval does: the same arguments give the same figures.
    `env_id` refuses a policy trained on another env; `deterministic=False` samples its actions
    (episode i's noise seeded with seed + i). Raises PolicyError, one line, for a source or env
    that cannot be used."""
    if episodes < 1:
        raise EvalError(f"episodes={episodes}: must be ≥ 1")
    policy = load_numpy_policy(policy, env_id)
    env = make_env(policy, video=False)
    try:
        return run_episodes(policy, env, episodes, seed, deterministic)
    finally:
        env.close()


def load_policy(path: Path, env_id: str | None, device: str = "cpu"):
    """(model, env_id, env_kwargs): a checkpoint's torch network on `device`, which the numpy
    `Policy` that tpdeb-eval runs is checked against; refuses one trained on another env than
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


def make_env(policy: Policy, video: bool):
    """The policy's env (with its keyword arguments), refused in one line where it cannot be
    made here or its spaces do not fit the policy."""
    import gymnasium as gym

    from tpdeb.services.config import ConfigError
    from tpdeb.services.envs import import_env_module, parse_env_kwargs, quiet_mujoco

    env_id = policy.env_id
    quiet_mujoco()
    if video:
        os.environ.setdefault("MUJOCO_GL", "egl")
    try:
        import_env_module(env_id)
        kwargs = parse_env_kwargs(policy.env_kwargs)
        if video:  # only then: an env without rendering need not take render_mode at all
            kwargs["render_mode"] = "rgb_array"
        env = gym.make(env_id, **kwargs)
    except (ConfigError, ValueError, TypeError, gym.error.Error) as exc:
        raise EvalError(f"env {env_id!r} cannot be made here: {exc}") from None
    obs, act = env.observation_space.shape, env.action_space.shape
    if (obs, act) != ((policy.obs_dim,), (policy.act_dim,)):
        env.close()
        raise EvalError(f"env {env_id!r} here has observations {obs} and actions {act}, but "
                        f"{policy.source} takes ({policy.obs_dim},) and gives "
                        f"({policy.act_dim},)")
    return env


def run_episodes(policy: Policy, env, episodes: int, seed: int, deterministic: bool = True,
                 frames: list | None = None) -> Evaluation:
    """Returns and lengths over `episodes` episodes (episode i: seed + i), one observation at a
    time: a batch over a vector env would change an episode's actions in their last bits with
    the batch's size (BLAS), and so its figures with --episodes."""
    import numpy as np

    returns, lengths = [], []
    for episode in range(episodes):
        obs, _ = env.reset(seed=seed + episode)
        rng = None if deterministic else np.random.default_rng(seed + episode)
        total, steps, done = 0.0, 0, False
        while not done:
            obs, reward, terminated, truncated, _ = env.step(policy.act(obs, deterministic, rng))
            total += float(reward)
            steps += 1
            done = terminated or truncated
            if frames is not None:
                frames.append(env.render())
        returns.append(total)
        lengths.append(steps)
    return Evaluation(statistics.mean(returns), statistics.pstdev(returns), tuple(returns),
                      tuple(lengths))


def video_writer():
    """imageio with its ffmpeg encoder, checked before the episodes that fill the video."""
    try:
        import imageio.v2 as imageio
        import imageio_ffmpeg  # noqa: F401  (the encoder imageio needs for .mp4)
    except ImportError:
        raise EvalError("--video needs imageio and imageio-ffmpeg: pip install "
                        "'tpdeb[video]' (or imageio imageio-ffmpeg)") from None
    return imageio


def write_video(frames: list, path: Path, fps: int) -> None:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        video_writer().mimwrite(path, frames, fps=fps, macro_block_size=1)
    except OSError as exc:
        raise OutputError.of("--video", path, exc) from None


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


def arguments(argv: list[str] | None) -> argparse.Namespace:
    return build_parser().parse_args(argv)


def build_parser() -> Parser:
    parser = Parser(prog=PROG, description=__doc__,
                    formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("target", help="a checkpoint (.pt), a policy.npz or a run directory")
    parser.add_argument("--episodes", type=int, default=10, help="episodes to run (default 10)")
    parser.add_argument("--seed", type=int, default=0, help="episode i starts from seed + i")
    parser.add_argument("--env-id", help="refuse a policy trained on any other env")
    parser.add_argument("--device", default="cpu",
                        help="accepted as before; the policy acts in numpy on the CPU (one "
                        "observation at a time is fastest there)")
    parser.add_argument("--video", type=Path, help="write the episodes to this .mp4 file")
    parser.add_argument("--fps", type=int, default=0, help="video frame rate (default: the env's)")
    parser.add_argument("--json", action="store_true", help="print one JSON line")
    return parser


def count(n: int, noun: str) -> str:
    return f"{n} {noun}" + ("" if n == 1 else "s")


def main(argv: list[str] | None = None) -> int:
    from tpdeb.services.device import check_device_setting

    args = arguments(argv)
    try:
        if args.episodes < 1:
            raise EvalError(f"--episodes {args.episodes}: must be ≥ 1")
        if problem := check_device_setting(args.device):
            raise EvalError(f"--device {args.device!r}: {problem}")
        if args.video is not None:  # before the episodes, which the video would cost
            video_writer()
            writable_path(args.video, "--video")
        target = Path(args.target)
        path = find_checkpoint(target) if target.is_dir() else target
        policy = load_numpy_policy(path, args.env_id)
        env = make_env(policy, args.video is not None)
        frames = None
        if args.video is not None:
            render_check(env)
            frames = []
        result = run_episodes(policy, env, args.episodes, args.seed, True, frames)
        if frames is not None:
            write_video(frames, args.video, args.fps or int(env.metadata.get("render_fps", 30)))
        env.close()
    except (PolicyError, OutputError) as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
    report(args, result, str(path), policy.env_id, frames)
    return 0


def report(args: argparse.Namespace, result: Evaluation, path: str, env_id: str,
           frames: list | None) -> None:
    spread = statistics.pstdev
    lengths = list(result.lengths)
    if args.json:
        print(json.dumps({
            "episodes": args.episodes, "seed": args.seed, "mean_return": result.mean,
            "std_return": result.std, "mean_length": statistics.mean(lengths),
            "std_length": spread(lengths), "returns": list(result.returns), "lengths": lengths,
            "checkpoint": path, "env_id": env_id}))
        return
    print(f"{env_id} | {path} | {count(args.episodes, 'episode')} from seed {args.seed}")
    print(f"return {result.mean:,.1f} ± {result.std:,.1f} | length "
          f"{statistics.mean(lengths):,.1f} ± {spread(lengths):,.1f}")
    if frames is not None:
        print(f"video: {args.video} ({count(len(frames), 'frame')})")


if __name__ == "__main__":
    sys.exit(main())
