"""Streaming throughput of the reader/writer: lines/s and peak memory for generated programs.

Run: python bench/stream.py [--sizes 100000 1000000] [--repeat 5]
Prints one table; the baseline in the same process is a bare byte copy of the same file.
"""

from __future__ import annotations

import argparse
import math
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def generate(path: Path, lines: int) -> None:
    """A 5-axis ijk program: motion blocks with comments and modal words, like a real post."""
    with open(path, "w", newline="") as out:
        out.write("%\nO1000 (BENCH)\nG21 G90 G94\nG43.5 H1\n")
        for i in range(lines - 6):
            t = i * 0.001
            tilt = 0.3 * math.sin(t)
            if i % 50 == 0:
                out.write(f"(LAYER {i // 50})\n")
            else:
                out.write(f"N{i} G1 X{50 * math.cos(t):.3f} Y{50 * math.sin(t):.3f} Z{t:.3f} "
                          f"I{math.sin(tilt):.6f} J0. K{math.cos(tilt):.6f} F1200.\n")
        out.write("M30\n%\n")


def child(path: str, mode: str) -> None:
    """Runs in a fresh process so that peak RSS belongs to one run."""
    from ncfix.config import Options
    from ncfix.pipeline import run

    started = time.perf_counter()
    with open(path, "rb") as src, open(os.devnull, "wb") as dst:
        if mode == "copy":
            for line in src:
                dst.write(line)
        else:
            run(src, dst, Options(machine="ijk"), path)
    seconds = time.perf_counter() - started
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"{seconds} {peak_mb}")


def measure(path: Path, mode: str, repeat: int) -> tuple[float, float]:
    times, peaks = [], []
    for _ in range(repeat):
        done = subprocess.run([sys.executable, __file__, "--child", str(path), mode], capture_output=True, text=True,
                              check=True)
        seconds, peak = map(float, done.stdout.split())
        times.append(seconds)
        peaks.append(peak)
    return statistics.median(times), max(peaks)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--sizes", type=int, nargs="+", default=[100_000, 1_000_000])
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child(*args.child)
        return
    print(f"{'lines':>10} {'ncfix s':>9} {'lines/s':>10} {'copy s':>8} {'ratio':>6} {'peak MB':>8} {'copy MB':>8}")
    with tempfile.TemporaryDirectory() as tmp:
        for size in args.sizes:
            path = Path(tmp) / f"bench_{size}.nc"
            generate(path, size)
            t_fix, m_fix = measure(path, "ncfix", args.repeat)
            t_copy, m_copy = measure(path, "copy", args.repeat)
            print(f"{size:>10,} {t_fix:>9.3f} {size / t_fix:>10,.0f} {t_copy:>8.3f} {t_fix / t_copy:>6.1f} "
                  f"{m_fix:>8.1f} {m_copy:>8.1f}")
    print(f"medians of {args.repeat} runs; target ≥ 200,000 lines/s with peak memory flat in size")


if __name__ == "__main__":
    main()
