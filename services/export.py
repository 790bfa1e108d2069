"""`tpdeb-export`: a trained policy out of its run, for a control loop that has neither torch
nor TPDEB.

    tpdeb-export runs/Hopper-v5__tpdeb__1__1700000000 -o hopper.onnx     # ONNX (needs onnx)
    tpdeb-export runs/…/checkpoints/final_900_288000.pt -o hopper.npz     # the numpy policy file

The source is a run dir, a checkpoint or a policy file. ONNX: one input `obs` [N, obs_dim]
float32, one output `action` [N, act_dim] float32: the observation normaliser, the mean network
and the clipping to the action bounds are all inside the graph (opset 17), so the model's
output is the action to send. It is the deterministic policy (the Gaussian's mean), equal to
`tpdeb.load_policy(...).act(obs, deterministic=True)` to 1e-5. `.npz`: the file
`tpdeb.load_policy` reads. The output path is checked before the policy is read.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from tpdeb.services.config import Parser
from tpdeb.services.policy_file import (
    Policy,
    PolicyError,
    load_policy,
    policy_bytes,
)
from tpdeb.services.store.diskio import OutputError, writable_path

PROG = "tpdeb-export"
OPSET, IR_VERSION = 17, 8  # IR 8: what every onnxruntime of the last years reads


def onnx_model(policy: Policy):
    """The deterministic policy as an ONNX model (raises PolicyError without `onnx`)."""
    try:
        import onnx
        from onnx import TensorProto, helper, numpy_helper
    except ImportError:
        raise PolicyError("ONNX export needs the onnx package: pip install 'tpdeb[export]' (or "
                          "onnx)") from None
    inits, nodes = [], []

    def const(name: str, value) -> str:
        inits.append(numpy_helper.from_array(np.asarray(value, np.float32), name))
        return name

    def node(op: str, inputs: list[str], out: str) -> str:
        nodes.append(helper.make_node(op, inputs, [out]))
        return out

    x = node("Sub", ["obs", const("obs_mean", policy.obs_mean)], "centred")
    x = node("Mul", [x, const("obs_inv_std", policy.obs_inv_std)], "scaled")
    x = node("Min", [x, const("obs_clip_high", [policy.obs_clip])], "clipped_high")
    x = node("Max", [x, const("obs_clip_low", [-policy.obs_clip])], "obs_normalised")
    last = len(policy.mean_layers) - 1
    for i, (weight_t, bias) in enumerate(policy.mean_layers):
        x = node("MatMul", [x, const(f"layer{i}_weight", weight_t)], f"layer{i}_matmul")
        x = node("Add", [x, const(f"layer{i}_bias", bias)], f"layer{i}_out")
        if i < last:
            x = node("Tanh", [x], f"layer{i}_tanh")
    x = node("Min", [x, const("action_high", policy.high)], "action_below_high")
    node("Max", [x, const("action_low", policy.low)], "action")
    graph = helper.make_graph(
        nodes, "tpdeb_policy",
        [helper.make_tensor_value_info("obs", TensorProto.FLOAT, ["batch", policy.obs_dim])],
        [helper.make_tensor_value_info("action", TensorProto.FLOAT, ["batch", policy.act_dim])],
        inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)],
                              producer_name="tpdeb", doc_string=f"TPDEB policy for "
                              f"{policy.env_id} ({policy.source}): obs → deterministic action")
    model.ir_version = IR_VERSION
    helper.set_model_props(model, {"env_id": policy.env_id, "env_kwargs": policy.env_kwargs})
    onnx.checker.check_model(model)
    return model


def export(source: str | Path, output: Path) -> Path:
    """`source`'s policy written to `output` (.onnx or .npz), whose path is checked first."""
    if output.suffix not in (".onnx", ".npz"):
        raise PolicyError(f"-o {output}: write a .onnx or a .npz file")
    writable_path(output, "-o")
    policy = load_policy(source)
    data = (onnx_model(policy).SerializeToString() if output.suffix == ".onnx"
            else policy_bytes(policy.file_arrays, policy.low, policy.high, policy.meta))
    try:
        output.parent.mkdir(parents=True, exist_ok=True)
        output.write_bytes(data)
    except OSError as exc:
        raise OutputError.of("-o", output, exc) from None
    return output


def main(argv: list[str] | None = None) -> int:
    parser = Parser(prog=PROG, description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("source", help="a run directory, a checkpoint (.pt) or a policy.npz")
    parser.add_argument("-o", "--output", type=Path, required=True,
                        help="policy.onnx (ONNX) or policy.npz (tpdeb.load_policy's file)")
    args = parser.parse_args(argv)
    try:
        path = export(args.source, args.output)
    except (PolicyError, OutputError) as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
    print(f"{PROG}: wrote {path} ({path.stat().st_size:,} bytes)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
