"""Logging: stdout for information, stderr for warnings and errors, levels, and the rate limit
that keeps a flood of bad messages to one line per kind and interval."""

import logging

import pytest

from tpdeb.services.config import ConfigError
from tpdeb.services.config.service import NetConfig
from tpdeb.services.logs import RateLimit, rate_limited, setup_logging


def test_information_goes_to_stdout_warnings_and_errors_to_stderr(capsys):
    setup_logging("info")
    log = logging.getLogger("tpdeb-x")
    log.debug("hidden")
    log.info("serving")
    log.warning("dropped a bad message")
    log.error("error: no such env")
    out, err = capsys.readouterr()
    assert out == "tpdeb-x: serving\n"
    assert err == "tpdeb-x: dropped a bad message\ntpdeb-x: error: no such env\n"
    setup_logging("debug")
    log.debug("details")
    assert capsys.readouterr().out == "tpdeb-x: details\n"
    setup_logging("error")
    log.warning("quiet")
    assert capsys.readouterr() == ("", "")


def test_a_bad_log_level_is_refused_with_the_value():
    with pytest.raises(ValueError, match="'loud'"):
        setup_logging("loud")
    with pytest.raises(ConfigError, match="log_level='loud'"):
        NetConfig(log_level="loud")


def test_the_rate_limit_passes_one_record_per_kind_and_interval_and_counts_the_rest():
    now = [0.0]
    limit = RateLimit(5.0, clock=lambda: now[0])

    def record(kind, msg="bad"):
        r = logging.LogRecord("p", logging.WARNING, "", 0, msg, (), None)
        if kind is not None:
            r.kind = kind
        return r

    assert limit.filter(record("shape"))
    assert not limit.filter(record("shape")) and not limit.filter(record("shape"))
    assert limit.filter(record("dtype"))  # another kind has its own interval
    assert limit.filter(record(None))  # records without a kind are not limited
    now[0] = 5.0
    passed = record("shape", "dropped a bad message")
    assert limit.filter(passed)
    assert passed.getMessage() == "dropped a bad message (+2 more since the last report)"


def test_rate_limited_warnings_reach_stderr_once(capsys):
    setup_logging("info")
    warn = rate_limited(logging.getLogger("tpdeb-replay"))
    for _ in range(50):
        warn("shape", "dropped a bad message from actor 3")
    assert capsys.readouterr().err == "tpdeb-replay: dropped a bad message from actor 3\n"
