"""(Re)write the expected files of golden cases from what ncfix makes of them now.

    python tests/golden/regen.py                 # every case but the long ones
    python tests/golden/regen.py fix_ sample_    # the cases whose names start so (long ones too)

A case whose input copies a bundled sample (``sample =`` in case.toml) gets the sample's current
bytes first. Review what changed with ``git diff tests/golden`` before committing it.
"""

from __future__ import annotations

import shutil
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import golden_cases  # noqa: E402


def main(argv: list[str]) -> int:
    chosen = [c for c in golden_cases.cases() if (not argv and c.mark != "long") or c.name.startswith(tuple(argv) or "\0")]
    if not chosen:
        print(f"no case starts with {', '.join(argv)}", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory() as scratch:
        for case in chosen:
            if case.sample:
                shutil.copyfile(golden_cases.SAMPLES / case.sample, case.input)
            result = golden_cases.run(case, Path(scratch))
            if result.exit not in (0, 1, 2):  # interrupted (128 + N): nothing to keep
                print(f"{case.name}: exit {result.exit}; its expected files are left as they were", file=sys.stderr)
                return result.exit
            golden_cases.write_expected(case, result)
            print(f"{case.name}: exit {result.exit}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
