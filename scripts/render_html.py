"""Screenshot an ncfix HTML report with headless chromium: `python scripts/render_html.py REPORT_HTML OUT_PNG`.

A developer's check of the HTML report (does it render, does the 3-D script run); the tests use
``dump_dom`` to read the ``data-ok`` attribute the report's script sets when it has run.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

CHROMIUM = "/usr/bin/chromium"
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars", "--virtual-time-budget=3000"]


def screenshot(report_html: str | Path, out_png: str | Path, size: str = "1400,2400", timeout: float = 120) -> None:
    url = Path(report_html).resolve().as_uri()
    subprocess.run([CHROMIUM, *FLAGS, f"--screenshot={Path(out_png).resolve()}", f"--window-size={size}", url],
                   check=True, capture_output=True, timeout=timeout)


def dump_dom(report_html: str | Path, timeout: float = 120) -> str:
    url = Path(report_html).resolve().as_uri()
    done = subprocess.run([CHROMIUM, *FLAGS, "--dump-dom", url], check=True, capture_output=True, timeout=timeout)
    return done.stdout.decode("utf-8", "replace")


def main(argv: list[str]) -> int:
    if len(argv) != 2:
        print(__doc__.splitlines()[0], file=sys.stderr)
        return 2
    if not Path(CHROMIUM).exists():
        print(f"{CHROMIUM} is not installed (Debian: apt-get install chromium)", file=sys.stderr)
        return 2
    screenshot(argv[0], argv[1])
    print(argv[1])
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
