"""The learner's update: eager against compiled, against its floor and the machine's limit.

    python bench/update.py                          # 64×64 and 256×256, 3 rounds of 3 s each
    python bench/update.py --sizes 64 256 1024 --rounds 1 --seconds 1   # a quick look
    python bench/update.py --compile-times          # also: first compile, cold and warm cache
    python bench/update.py --before ../before --before-python ../before/.venv/bin/python
                                                    # A/B: the floor of another checkout

On HalfCheetah-v5 batches as the replay ships them (its preset; 8 fragments × 64 steps of a
fresh policy's fragments) with one torch thread, each network size measures, round by round and
alternating:
- `eager`: `Learner.update` on placed batches as the learner service runs it (targets, loss,
  backward, clip, Adam, ceiling, soft target, KL coefficient, priorities);
- `compiled`: the same after `services.compiled` has compiled it;
- `floor`: forward of the policy on the batch's T·B observations and of the value net on its
  (T+1)·B, backward and torch's fused Adam, eager, nothing else;
- `before`, with `--before DIR`: the floor as another checkout (the commit before a change)
  defines and measures it, its own `bench/throughput.py`'s `bench_floor`, run by its own
  interpreter in a subprocess in the same round;
and once per size the update's floating-point work (the matmuls of forward and backward) against
one core's measured `torch.mm` rate, as achieved GFLOP/s and a fraction of that rate. On a GPU
(`--device cuda`) the same, in ms per update with the device synchronised after each timing.
Nothing else should run meanwhile. Writes bench/out/update.json (`--out`).
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import provenance
import torch
from throughput import preset_config, sample_batches

from tpdeb.services.compiled import BackgroundCompile, configure_compiler
from tpdeb.services.net.model_wire import model_for
from tpdeb.tpdeb_core.learner import Learner, place

ROOT = Path(__file__).resolve().parent.parent
ENV_ID = "HalfCheetah-v5"


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def timed(step, seconds: float, device: torch.device, warmup: int = 20) -> float:
    """ms per call of `step`, after a warm-up."""
    for _ in range(warmup):
        step()
    sync(device)
    calls, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        step()
        calls += 1
    sync(device)
    return 1e3 * (time.perf_counter() - start) / calls


def task(hidden: int, seed: int = 1):
    """The preset's configuration with `hidden`×`hidden` networks, its run spec, fragments and
    16 stacked batches."""
    config = preset_config(ENV_ID, 4, seed)
    config.hidden_sizes = (hidden, hidden)
    spec, fragments, batches = sample_batches(config, count=16)
    return config, spec, fragments, batches


def make_learner(config, spec, fragments, device: torch.device) -> Learner:
    torch.manual_seed(config.seed)
    learner = Learner(model_for(spec), config.loss_config(), device)
    for fragment in fragments:  # realistic normaliser statistics
        learner.observe(fragment)
    return learner


def update_step(learner: Learner, placed):
    """What the service does per update: the normaliser, the update, the priorities out."""
    cycle = itertools.cycle(placed)
    pin = learner.device.type != "cpu"

    def step():
        learner.update(next(cycle), learner.normaliser()).to("cpu", non_blocking=pin)
    return step


def floor_step(spec, device: torch.device, placed):
    """Forward of the policy on T·B observations and of the value net on (T+1)·B, backward and
    torch's Adam (fused on the CPU), eager: the floor as this checkout defines it."""
    torch.manual_seed(0)
    model = model_for(spec).to_device(device)
    params = list(model.parameters())
    options = {"fused": True} if device.type == "cpu" else {"foreach": True, "capturable": True}
    optimizer = torch.optim.Adam(params, lr=torch.tensor(1e-3, device=device), eps=1e-5,
                                 **options)
    cycle = itertools.cycle([p.obs for p in placed])

    def step():
        x = next(cycle)
        mean, log_std = model.policy(x[:-1])
        loss = mean.square().mean() + log_std.sum() + model.value(x).square().mean()
        for p in params:
            p.grad = None
        loss.backward()
        optimizer.step()
    return step


def before_floor_ms(before: Path, python: str, hidden: int, seconds: float) -> float:
    """The floor as the checkout `before` defines and measures it (its bench/throughput.py),
    in ms, on the same task, network size and thread count."""
    code = ("import sys, json; sys.path.insert(0, 'bench'); import throughput as t; "
            f"c = t.preset_config({ENV_ID!r}, 4, 1); c.hidden_sizes = ({hidden}, {hidden}); "
            "spec, fragments, batches = t.sample_batches(c, count=16); "
            f"print(json.dumps(t.bench_floor(c, spec, batches, {seconds})))")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    out = subprocess.run([python, "-c", code], cwd=before, env=env, check=True,
                         capture_output=True, text=True).stdout
    return json.loads(out.strip().splitlines()[-1])["update_ms"]


def update_flops(spec, hidden: int) -> float:
    """The matmuls of one update: forward of the policy (T·B rows) and of the target policy
    (T·B), the value net on (T+1)·B + 8 rows (the truncation slots); backward twice the
    forward of the trained nets."""
    steps, count = spec.fragment_len, 8

    def net(rows, sizes):
        return sum(2.0 * rows * a * b for a, b in itertools.pairwise(sizes))
    policy_net = net(steps * count, [spec.obs_dim, hidden, hidden, spec.act_dim])
    value_net = net((steps + 1) * count + 8, [spec.obs_dim, hidden, hidden, 1])
    return 3.0 * (policy_net + value_net) + policy_net


def matmul_gflops(device: torch.device, seconds: float = 2.0) -> float:
    a, b = (torch.randn(1024, 1024, device=device) for _ in range(2))
    ms = timed(lambda: torch.mm(a, b), seconds, device, warmup=3)
    return 2.0 * 1024 ** 3 / (ms * 1e-3) / 1e9


def compile_seconds(hidden: int, cache: str) -> float:
    """Seconds to prepare the compiled update in a fresh process with inductor's cache at
    `cache` (an empty directory: cold; the same again: warm)."""
    code = ("import sys, time; sys.path.insert(0, 'bench'); import update as u, torch; "
            "import numpy as np; torch.set_num_threads(1); "
            f"c, spec, f, b = u.task({hidden}); d = torch.device('cpu'); "
            "lr = u.make_learner(c, spec, f, d); "
            "p = u.place(b[0], np.ones(c.batch_fragments, np.float32), None, d); "
            "k = u.BackgroundCompile(lr); t = time.perf_counter(); k.start(p, lr.normaliser()); "
            "k.done.wait(); assert k.install(), k.error; print(time.perf_counter() - t)")
    env = {**os.environ, "TORCHINDUCTOR_CACHE_DIR": cache}
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, check=True,
                         capture_output=True, text=True).stdout
    return float(out.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="+", default=[64, 256])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--seconds", type=float, default=3.0, help="per round and variant")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--before", type=Path, help="a checkout whose floor to measure beside")
    parser.add_argument("--before-python", default=sys.executable,
                        help="the interpreter that imports that checkout's tpdeb")
    parser.add_argument("--compile-times", action="store_true",
                        help="also time a first compile with an empty and a warm cache")
    parser.add_argument("--out", default=str(ROOT / "bench" / "out" / "update.json"))
    args = parser.parse_args()
    record = provenance.start()
    configure_compiler()
    torch.set_num_threads(1)
    device = torch.device(args.device)
    peak = matmul_gflops(device)
    print(f"torch.mm 1024×1024 on one thread: {peak:,.1f} GFLOP/s", flush=True)
    results: dict = {"matmul_gflops": peak, "device": str(device), "env_id": ENV_ID,
                     "before": str(args.before) if args.before else None, "sizes": {}}
    for hidden in args.sizes:
        config, spec, fragments, batches = task(hidden)
        pin = device.type != "cpu"
        placed = [place(b, np.ones(config.batch_fragments, np.float32), None, device, pin)
                  for b in batches]
        eager = make_learner(config, spec, fragments, device)
        compiled = make_learner(config, spec, fragments, device)
        compiler = BackgroundCompile(compiled)
        compiled.update(placed[0], compiled.normaliser())
        compiler.start(placed[0], compiled.normaliser())
        compiler.done.wait()
        if not compiler.install():
            raise SystemExit(f"compile failed: {compiler.error}")
        steps = {"eager": update_step(eager, placed), "compiled": update_step(compiled, placed),
                 "floor": floor_step(spec, device, placed)}
        if args.before:
            steps["before_floor"] = None
        rounds: dict[str, list[float]] = {name: [] for name in steps}
        for r in range(args.rounds):
            for name in (list(steps) if r % 2 == 0 else list(steps)[::-1]):
                rounds[name].append(
                    before_floor_ms(args.before, args.before_python, hidden, args.seconds)
                    if name == "before_floor" else timed(steps[name], args.seconds, device))
                print(f"  {hidden}×{hidden} {name:12s} round {r + 1}: "
                      f"{rounds[name][-1]:.3f} ms", flush=True)
        median = {name: statistics.median(v) for name, v in rounds.items()}
        flops = update_flops(spec, hidden)
        row = {**{f"{name}_ms": median[name] for name in steps},
               **{f"{name}_rounds_ms": rounds[name] for name in steps},
               "compiled_over_floor": median["compiled"] / median["floor"],
               "eager_over_floor": median["eager"] / median["floor"],
               "update_mflop": flops / 1e6,
               "compiled_gflops": flops / (median["compiled"] * 1e-3) / 1e9,
               "compiled_fraction_of_mm": flops / (median["compiled"] * 1e-3) / 1e9 / peak,
               "compile_s_in_background": compiler.seconds}
        if args.before:
            row["compiled_over_before_floor"] = median["compiled"] / median["before_floor"]
        results["sizes"][f"{hidden}x{hidden}"] = row
    if args.compile_times:
        with tempfile.TemporaryDirectory() as empty:
            cold = compile_seconds(args.sizes[0], empty)
            warm = compile_seconds(args.sizes[0], empty)
        results["compile_s"] = {"cold": cold, "warm": warm, "size": args.sizes[0]}
        print(f"compile at {args.sizes[0]}×{args.sizes[0]}: cold {cold:.1f} s, warm {warm:.1f} s")
    print("\n| network | update eager ms | compiled ms | floor ms | floor before ms | "
          "compiled ÷ floor before | GFLOP/s compiled | of torch.mm |")
    print("|---|---|---|---|---|---|---|---|")
    for key, r in results["sizes"].items():
        before = r.get("before_floor_ms")
        print(f"| {key} | {r['eager_ms']:.3f} | {r['compiled_ms']:.3f} | {r['floor_ms']:.3f} | "
              f"{before if before is None else f'{before:.3f}'} | "
              f"{r.get('compiled_over_before_floor', float('nan')):.2f} | "
              f"{r['compiled_gflops']:.1f} | {r['compiled_fraction_of_mm']:.0%} |")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(provenance.stamp(results, record), indent=1) + "\n")


if __name__ == "__main__":
    main()
