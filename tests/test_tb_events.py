"""The run dir's metrics: metrics.jsonl and TensorBoard events that TensorBoard itself reads."""

import pytest

from tpdeb.services.store.metrics import MetricsWriter, read_metrics


def test_metrics_reach_jsonl_and_tensorboard_keyed_by_env_steps(tmp_path):
    writer = MetricsWriter(tmp_path)
    writer.text("hyperparameters", "|param|value|\n|-|-|\n|seed|1|")
    for step in range(5):
        writer.log(step * 100, {"charts/episodic_return": step * 1.5, "losses/value_loss": 0.25})
    writer.log(600, {"charts/SPS": float("nan")})  # non-finite values are dropped
    writer.close()

    rows = read_metrics(tmp_path / "metrics.jsonl")
    assert [r["global_step"] for r in rows] == [0, 100, 200, 300, 400]
    assert rows[3]["charts/episodic_return"] == 4.5

    assert len(list(tmp_path.glob("events.out.tfevents.*"))) == 1
    accumulator = pytest.importorskip(
        "tensorboard.backend.event_processing.event_accumulator")
    acc = accumulator.EventAccumulator(str(tmp_path))
    acc.Reload()
    returns = acc.Scalars("charts/episodic_return")
    assert [e.step for e in returns] == [0, 100, 200, 300, 400]
    assert returns[2].value == pytest.approx(3.0)
    assert "charts/SPS" not in acc.Tags()["scalars"]
    assert "hyperparameters/text_summary" in acc.Tags()["tensors"]
