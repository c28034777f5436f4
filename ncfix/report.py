"""What ncfix found and changed: the JSON report (schema 1) and the unified diff of changed blocks."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Any

from ncfix import __version__

if TYPE_CHECKING:
    from ncfix.config import Options
    from ncfix.nc.chunk import Chunk


@dataclass
class Report:
    input: str
    machine: str
    options: "Options"
    summary: dict[str, Any] = field(default_factory=lambda: {
        "lines": 0, "motion_blocks": 0, "colliding_blocks_before": 0, "changed_blocks": 0,
        "unresolved_blocks": 0, "max_tilt_deg": 0.0, "max_step_deg": 0.0, "seconds": 0.0,
    })
    changes: list[dict[str, Any]] = field(default_factory=list)
    unresolved: list[dict[str, Any]] = field(default_factory=list)
    collisions: list[dict[str, Any]] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    details: list[str] = field(default_factory=list)  # shown with -v (e.g. the head model's counts)
    diff_lines: list[tuple[int, str, str]] = field(default_factory=list)  # (line, before, after)

    def count(self, chunk: "Chunk") -> None:
        self.summary["lines"] += len(chunk)
        self.summary["motion_blocks"] += int((chunk.motion >= 0).sum())

    @property
    def exit_code(self) -> int:
        """0: no collision left; 1: collisions remain (CONTRACT.md)."""
        if self.options.check:
            return 1 if self.summary["colliding_blocks_before"] else 0
        return 1 if self.summary["unresolved_blocks"] else 0

    def to_json(self) -> dict[str, Any]:
        settings = {k: v for k, v in asdict(self.options).items() if k not in ("extra",)}
        settings = {k: list(v) if isinstance(v, tuple) else v for k, v in settings.items()}
        return {
            "schema": 1,
            "ncfix": __version__,
            "input": self.input,
            "machine": self.machine,
            "settings": settings,
            "summary": dict(self.summary),
            "changes": self.changes,
            "unresolved": self.unresolved,
            "collisions": self.collisions,
            "warnings": self.warnings,
        }

    def write_json(self, path: str) -> None:
        from ncfix.fileio import atomic_write_text

        atomic_write_text(path, json.dumps(self.to_json(), indent=2) + "\n")

    def unified_diff(self, source: str, target: str) -> str:
        """A unified diff of the changed lines (one hunk each, no context: lines never move)."""
        if not self.diff_lines:
            return ""
        out = [f"--- {source}\n", f"+++ {target}\n"]
        for line, before, after in self.diff_lines:
            out.append(f"@@ -{line},1 +{line},1 @@\n")
            out.append("-" + _with_newline(before))
            out.append("+" + _with_newline(after))
        return "".join(out)


def _with_newline(text: str) -> str:
    body = text.rstrip("\r\n")
    return body + "\n" if body == text else body + "\n"
