import struct

import pytest

from tpdeb.services.store.metrics import MetricsWriter, read_metrics
from tpdeb.services.store.tb_events import crc32c


def test_crc32c_known_vector():
    assert crc32c(b"123456789") == 0xE3069283
    assert crc32c(b"") == 0


def test_event_file_framing_and_tensorboard_reads_it(tmp_path):
    writer = MetricsWriter(tmp_path)
    writer.text("hyperparameters", "|param|value|\n|-|-|\n|seed|1|")
    for step in range(5):
        writer.log(step * 100, {"charts/episodic_return": step * 1.5, "losses/value_loss": 0.25})
    writer.log(600, {"charts/SPS": float("nan")})  # non-finite values are dropped
    writer.close()

    rows = read_metrics(tmp_path / "metrics.jsonl")
    assert [r["global_step"] for r in rows] == [0, 100, 200, 300, 400]
    assert rows[3]["charts/episodic_return"] == 4.5

    (events,) = tmp_path.glob("events.out.tfevents.*")
    data = events.read_bytes()
    count, offset = 0, 0
    from tpdeb.services.store.tb_events import _masked_crc
    while offset < len(data):
        (length,) = struct.unpack_from("<Q", data, offset)
        assert struct.unpack_from("<I", data, offset + 8)[0] == _masked_crc(data[offset:offset + 8])
        record = data[offset + 12:offset + 12 + length]
        assert struct.unpack_from("<I", data, offset + 12 + length)[0] == _masked_crc(record)
        offset += 16 + length
        count += 1
    assert count == 1 + 1 + 5  # file version, text, five scalar events

    accumulator = pytest.importorskip(
        "tensorboard.backend.event_processing.event_accumulator")
    acc = accumulator.EventAccumulator(str(tmp_path))
    acc.Reload()
    returns = acc.Scalars("charts/episodic_return")
    assert [e.step for e in returns] == [0, 100, 200, 300, 400]
    assert returns[2].value == pytest.approx(3.0)
    assert "hyperparameters" in acc.Tags()["tensors"]
