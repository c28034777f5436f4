"""Screenshot an ncfix HTML report with headless chromium: `python scripts/render_html.py REPORT_HTML OUT_PNG`.

A developer's check of the HTML report (does it render, does the 3-D script run); the tests use
``dump_dom`` to read the ``data-ok`` attribute the report's script sets when it has run, and
``dump_dom_and_console`` to read the browser console too (``Uncaught ...`` for a script error).

Chromium runs headless with a fresh profile and without its background traffic (updates, sync,
QUIC): the network here is closed, and without these flags it stalls on connections.
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
from pathlib import Path

CHROMIUM = "/usr/bin/chromium"
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--hide-scrollbars", "--virtual-time-budget=3000"]
# The page's console goes to stderr, one line a message: `...:INFO:CONSOLE:12] "Uncaught ...", source: ...`.
CONSOLE_FLAGS = ["--enable-logging=stderr", "--v=0"]


def run_chromium(args: list[str], timeout: float) -> subprocess.CompletedProcess:
    """Run headless chromium with FLAGS, ``args`` and a fresh profile; the finished process (output as bytes)."""
    with tempfile.TemporaryDirectory(prefix="ncfix-chromium-") as profile:
        return subprocess.run([CHROMIUM, *FLAGS, f"--user-data-dir={profile}", *args],
                              check=True, capture_output=True, timeout=timeout)


def screenshot(report_html: str | Path, out_png: str | Path, size: str = "1400,2400", timeout: float = 120) -> str:
    """Write a PNG of the page at ``size`` (width,height); return the browser console (stderr)."""
    url = Path(report_html).resolve().as_uri()
    done = run_chromium([*CONSOLE_FLAGS, f"--screenshot={Path(out_png).resolve()}", f"--window-size={size}", url],
                        timeout)
    return done.stderr.decode("utf-8", "replace")


def dump_dom_and_console(report_html: str | Path, timeout: float = 120) -> tuple[str, str]:
    """The page's DOM after its scripts ran, and the browser console (stderr)."""
    url = Path(report_html).resolve().as_uri()
    done = run_chromium([*CONSOLE_FLAGS, "--dump-dom", url], timeout)
    return done.stdout.decode("utf-8", "replace"), done.stderr.decode("utf-8", "replace")


def dump_dom(report_html: str | Path, timeout: float = 120) -> str:
    """The page's DOM after its scripts ran."""
    return dump_dom_and_console(report_html, timeout)[0]


def main(argv: list[str]) -> int:
    if len(argv) != 2:
        print(__doc__.splitlines()[0], file=sys.stderr)
        return 2
    if not Path(CHROMIUM).exists():
        print(f"{CHROMIUM} is not installed (Debian: apt-get install chromium)", file=sys.stderr)
        return 2
    console = screenshot(argv[0], argv[1])
    errors = [line for line in console.splitlines() if "Uncaught" in line]
    print("\n".join(errors) if errors else "no script errors in the console", file=sys.stderr)
    print(argv[1])
    return 1 if errors else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
