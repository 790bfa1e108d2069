"""Flow control between inserts and samples, in steps (Reverb's SampleToInsertRatio).

The learner should replay a fixed number of sampled steps per inserted step (the replay ratio,
`samples_per_insert`) whatever the relative speed of actors and learner, so that results do not
depend on the machine. The limiter tracks

    diff = inserted_steps · samples_per_insert − sampled_steps

and keeps it inside [min_diff, max_diff] = offset ∓ error_buffer around
offset = samples_per_insert · min_size_to_sample: an insert is allowed while it keeps diff ≤
max_diff (actors are not too far ahead), a sample while it keeps diff ≥ min_diff (the learner is
not too far ahead). Before `min_size_to_sample` steps have been inserted, inserts are always
allowed and samples never.

Which settings deadlock, and why they are refused. Once sampling has started, a state where
neither side may act has

    diff + insert_steps·spi > max_diff   and   diff − sample_steps < min_diff,

i.e. max_diff − insert_steps·spi < diff < min_diff + sample_steps. That interval is empty exactly
when 2·error_buffer ≥ insert_steps·spi + sample_steps, so any smaller error_buffer lets both
sides wait on each other forever (in a blocking server: a hang). `insert_steps` and
`sample_steps` are the largest insert (a fragment, T steps) and sample (a batch, B·T steps) the
caller will ask for. On top of that we require error_buffer ≥ sample_steps, so that the first
batch can be sampled as soon as `min_size_to_sample` steps are in, without waiting for extra
inserts. `min_error_buffer` returns the larger of the two bounds. Also refused: a non-positive
or non-finite ratio (diff never moves the right way), sizes below one step, and a buffer
capacity below `min_size_to_sample` (it could never hold enough to start sampling).

A band instead of one ratio (`max_samples_per_insert` above `samples_per_insert`): when inserts
are scarce (a thin link, slow actors) an idle learner may replay more, up to the upper ratio,
instead of waiting. Inserts are then gated at the lower ratio and samples at the upper one:

    diff_lo = inserted_steps · spi_lo − sampled_steps ≤ max_diff = spi_lo · min_size + error_buffer
    diff_hi = inserted_steps · spi_hi − sampled_steps ≥ min_diff = spi_hi · min_size − error_buffer

so the achieved ratio settles anywhere in [spi_lo, spi_hi] (within error_buffer / inserted_steps),
wherever the two sides' speeds put it. The same bound keeps it free of deadlock: with
Δ = spi_hi − spi_lo, diff_hi = diff_lo + inserted_steps·Δ and min_diff = spi_lo·min_size +
min_size·Δ − error_buffer, so both sides refused means

    max_diff − insert_steps·spi_lo < diff_lo < min_diff + sample_steps − inserted_steps·Δ
                                         ≤ spi_lo·min_size − error_buffer + sample_steps

(once sampling has started, inserted_steps ≥ min_size), which is empty under the same
2·error_buffer ≥ insert_steps·spi_lo + sample_steps as for one ratio.

Pure: no clocks, threads or blocking; the caller waits and retries.
"""

from __future__ import annotations

import math
import numbers
from typing import Any

# Slack on both comparisons, relative to the magnitudes involved: inserted_steps·spi is rounded,
# and a boundary case that is exact on paper must not become a one-ulp deadlock.
_RELATIVE_SLACK = 1e-9


def _as_steps(name: str, value: Any) -> int:
    """An integer number of steps >= 1 (numpy integers welcome, bools and floats not)."""
    if not isinstance(value, numbers.Integral) or isinstance(value, bool) or value < 1:
        raise ValueError(f"{name} must be an integer number of steps >= 1, got {value!r}")
    return int(value)


def _as_real(name: str, value: Any) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a real number, got {value!r}") from None


class RateLimiter:
    """Allows inserts and samples so that sampled/inserted steps stays near samples_per_insert.

    Args:
        samples_per_insert: target replay ratio: sampled steps per inserted step (> 0); with
            a band, its lower end (inserts wait for the learner below it).
        max_samples_per_insert: the upper end of a band (samples wait for inserts above it);
            None (or equal to samples_per_insert): one fixed ratio.
        min_size_to_sample: inserted steps required before the first sample.
        error_buffer: tolerance on diff, in sampled steps; at least `min_error_buffer(...)`.
        insert_steps: the largest insert the caller will ask for, in steps (a fragment: T).
        sample_steps: the largest sample the caller will ask for, in steps (a batch: B·T).
        capacity_steps: the buffer's capacity in steps, if bounded; checked against
            min_size_to_sample.
    """

    def __init__(
        self,
        samples_per_insert: float,
        min_size_to_sample: int,
        error_buffer: float,
        *,
        insert_steps: int,
        sample_steps: int,
        capacity_steps: int | None = None,
        max_samples_per_insert: float | None = None,
    ) -> None:
        spi = _as_real("samples_per_insert", samples_per_insert)
        if not (math.isfinite(spi) and spi > 0):
            raise ValueError(
                f"samples_per_insert must be finite and > 0, got {samples_per_insert!r}: with "
                f"no positive ratio, inserting never makes room to sample"
            )
        spi_max = spi if max_samples_per_insert is None else _as_real(
            "max_samples_per_insert", max_samples_per_insert)
        if not (math.isfinite(spi_max) and spi_max >= spi):
            raise ValueError(
                f"max_samples_per_insert={max_samples_per_insert!r} must be finite and >= "
                f"samples_per_insert={spi} (the upper end of the band)"
            )
        self._min_size_to_sample = _as_steps("min_size_to_sample", min_size_to_sample)
        self._insert_steps = _as_steps("insert_steps", insert_steps)
        self._sample_steps = _as_steps("sample_steps", sample_steps)
        if capacity_steps is not None:
            capacity = _as_steps("capacity_steps", capacity_steps)
            if capacity < self._min_size_to_sample:
                raise ValueError(
                    f"capacity_steps={capacity} < min_size_to_sample={self._min_size_to_sample}: "
                    f"the buffer can never hold enough steps to start sampling; lower "
                    f"min_size_to_sample or raise the capacity"
                )
        needed = self.min_error_buffer(spi, self._insert_steps, self._sample_steps)
        buffer = _as_real("error_buffer", error_buffer)
        if not (math.isfinite(buffer) and buffer >= needed):
            raise ValueError(
                f"error_buffer={error_buffer!r} can deadlock with samples_per_insert={spi}, "
                f"insert_steps={self._insert_steps}, sample_steps={self._sample_steps}: it must "
                f"be >= max((insert_steps*samples_per_insert + sample_steps)/2, sample_steps) = "
                f"{needed}; raise error_buffer or use smaller fragments/batches"
            )
        self._samples_per_insert = spi
        self._max_samples_per_insert = spi_max
        self._max_diff = spi * self._min_size_to_sample + buffer  # gates inserts, at spi
        self._min_diff = spi_max * self._min_size_to_sample - buffer  # gates samples, at spi_max
        self._inserted_steps = 0
        self._sampled_steps = 0

    @staticmethod
    def min_error_buffer(samples_per_insert: float, insert_steps: int, sample_steps: int) -> float:
        """The smallest error_buffer that cannot deadlock (see the module docstring)."""
        return max((insert_steps * samples_per_insert + sample_steps) / 2.0, float(sample_steps))

    def _diff(self, ratio: float | None = None) -> float:
        ratio = self._samples_per_insert if ratio is None else ratio
        return self._inserted_steps * ratio - self._sampled_steps

    def _slack(self) -> float:
        scale = self._inserted_steps * self._max_samples_per_insert + self._sampled_steps
        return _RELATIVE_SLACK * (1.0 + scale + abs(self._max_diff))

    def can_insert(self, num_steps: int) -> bool:
        """Whether inserting `num_steps` keeps the learner from falling too far behind."""
        num_steps = self._check_request(num_steps, self._insert_steps, "insert")
        if self._inserted_steps < self._min_size_to_sample:
            return True
        after = self._diff() + num_steps * self._samples_per_insert
        return after <= self._max_diff + self._slack()

    def can_sample(self, num_steps: int) -> bool:
        """Whether sampling `num_steps` keeps the learner from running too far ahead."""
        num_steps = self._check_request(num_steps, self._sample_steps, "sample")
        if self._inserted_steps < self._min_size_to_sample:
            return False
        return (self._diff(self._max_samples_per_insert) - num_steps
                >= self._min_diff - self._slack())

    @staticmethod
    def _check_request(num_steps: int, largest: int, what: str) -> int:
        steps = _as_steps("num_steps", num_steps)
        if steps > largest:
            raise ValueError(
                f"cannot {what} {steps} steps: this limiter was built for at most {largest} "
                f"({what}_steps) and larger requests may deadlock"
            )
        return steps

    def on_insert(self, num_steps: int) -> None:
        """Record an insert (the caller checked `can_insert`, or is forcing it)."""
        self._inserted_steps += _as_steps("num_steps", num_steps)

    def on_restored_insert(self, num_steps: int) -> None:
        """Record an insert whose samples went unrecorded (a restart re-inserting what was
        logged after the saved state), with the samples the ratio let the learner take against
        it: samples_per_insert per step past min_size_to_sample, so diff ends where it stood.
        Counted alone, it would hold every new insert back until the learner had sampled all
        of them again."""
        num_steps = _as_steps("num_steps", num_steps)
        past_min_size = min(num_steps,
                            self._inserted_steps + num_steps - self._min_size_to_sample)
        self._inserted_steps += num_steps
        if past_min_size > 0:
            self._sampled_steps += round(past_min_size * self._samples_per_insert)

    def on_sample(self, num_steps: int) -> None:
        """Record a sample (the caller checked `can_sample`, or is forcing it)."""
        self._sampled_steps += _as_steps("num_steps", num_steps)

    def state_dict(self) -> dict[str, int]:
        return {"inserted_steps": self._inserted_steps, "sampled_steps": self._sampled_steps}

    def load_state_dict(self, state: dict[str, int]) -> None:
        for name in ("inserted_steps", "sampled_steps"):
            value = state[name]
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ValueError(f"{name} must be an integer >= 0, got {value!r}")
        self._inserted_steps = state["inserted_steps"]
        self._sampled_steps = state["sampled_steps"]

    def stats(self) -> dict[str, float | int]:
        achieved = self._sampled_steps / self._inserted_steps if self._inserted_steps else 0.0
        return {
            "inserted_steps": self._inserted_steps,
            "sampled_steps": self._sampled_steps,
            "samples_per_insert_achieved": achieved,
            "samples_per_insert": self._samples_per_insert,
            "max_samples_per_insert": self._max_samples_per_insert,
            "diff": self._diff(),  # against max_diff, which gates inserts
            "max_diff": self._max_diff,
            "upper_diff": self._diff(self._max_samples_per_insert),  # against min_diff: samples
            "min_diff": self._min_diff,
        }
