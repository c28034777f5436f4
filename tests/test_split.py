"""Batches of poses cut into runs for several threads: the cut, the thread setting, and answers
that do not depend on either."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from ncfix.collision.split import MIN_RUN, map_runs, runs, thread_count
from ncfix.errors import ConfigError

SAMPLES = Path(__file__).resolve().parents[1] / "samples"


@pytest.mark.parametrize("n", [0, 1, 2 * MIN_RUN - 1, 2 * MIN_RUN, 100, 1001, 50_000])
@pytest.mark.parametrize("threads", [1, 2, 3, 8])
def test_runs_cover_the_batch_in_order(n, threads):
    parts = runs(n, threads)
    assert parts[0][0] == 0 and parts[-1][1] == n
    assert all(a[1] == b[0] for a, b in zip(parts, parts[1:]))
    if threads == 1 or n < 2 * MIN_RUN:
        assert parts == [(0, n)]
    else:
        assert len(parts) > 1 and all(hi - lo >= MIN_RUN for lo, hi in parts)


def test_map_runs_keeps_run_order_on_several_threads(monkeypatch):
    monkeypatch.setenv("NCFIX_THREADS", "4")
    got = map_runs(lambda lo, hi: list(range(lo, hi)), 1000)
    assert len(got) > 1 and [i for part in got for i in part] == list(range(1000))


def test_thread_count_from_the_environment(monkeypatch):
    monkeypatch.setenv("NCFIX_THREADS", "3")
    assert thread_count() == 3
    monkeypatch.delenv("NCFIX_THREADS")
    assert thread_count() >= 1
    for bad in ("0", "-2", "two", "1.5"):
        monkeypatch.setenv("NCFIX_THREADS", bad)
        with pytest.raises(ConfigError, match="NCFIX_THREADS"):
            thread_count()


def test_a_bad_thread_setting_is_an_input_error_before_any_output(tmp_path):
    out = tmp_path / "out.nc"
    done = subprocess.run([sys.executable, "-m", "ncfix", str(SAMPLES / "deposit_wall.nc"), "--check", "--head",
                           str(SAMPLES / "deposition_head.stl"), "-o", str(out)],
                          capture_output=True, env={**__import__("os").environ, "NCFIX_THREADS": "many"})
    assert done.returncode == 2
    assert b"NCFIX_THREADS is 'many'" in done.stderr and b"whole number of threads" in done.stderr
    assert not out.exists()
