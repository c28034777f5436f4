"""The human summary on standard error (rich); standard output carries only the program."""

from __future__ import annotations

from typing import Any

from rich.console import Console
from rich.table import Table

from ncfix.report import Report, plural, rescaled_note

ROWS = 20  # table rows shown without -v; the report lists all
LOG_WIDTH = 160  # columns when standard error is not a terminal


def print_summary(report: Report, verbose: bool = False, console: Console | None = None) -> None:
    """What was found and changed, then a one-line verdict with the exit status."""
    if console is None:
        console = Console(stderr=True, highlight=False, soft_wrap=True)
        if not console.is_terminal:
            console.width = LOG_WIDTH  # a log file or a pipe: do not wrap the tables at 80 columns
    s = report.summary
    mode = "check" if report.options.check else "fix"
    console.print(
        f"[bold]ncfix[/bold] {report.input}: {s['lines']:,} lines, {s['motion_blocks']:,} motion blocks "
        f"({report.machine}, {mode}) in {s['seconds']:.2f} s"
    )
    if verbose:
        for detail in report.details:
            console.print(f"  {detail}")
    for note in report.notes:
        console.print(f"  {note}")
    if report.options.head is not None:
        console.print(f"  {plural(s['colliding_blocks_before'], 'colliding block')} found "
                      f"({s.get('checked_samples', 0):,} poses checked; deposit: {s.get('deposit_rule')})")
        after = [e for e in report.collisions if e.get("detected")]
        if after:
            console.print(f"  {len(after):,} of them found after ncfix rewrote blocks before "
                          f"{'it' if len(after) == 1 else 'them'} (--check of the input may not flag "
                          f"{'it' if len(after) == 1 else 'them'}): "
                          + "; ".join(f"line {e['line']}: {e['detected']}" for e in after[:3])
                          + (" …" if len(after) > 3 else ""))
        if report.options.check:
            _table(console, "colliding blocks", report.collisions, verbose,
                   (("line", "right", lambda e: str(e["line"])),
                    ("bodies", "left", lambda e: ", ".join(e.get("bodies", []))),
                    ("where", "left", lambda e: _where(e)),
                    ("penetration mm", "right", lambda e: _mm(e.get("penetration_mm"))),
                    ("clearance mm", "right", lambda e: _mm(e.get("clearance_mm")))))
            if any(e.get("where") == "sweep" for e in report.collisions):
                console.print("  where: 'end' = at the block's end point; 'sweep' = along the move from the block "
                              "before (its end point is free); the clearance is at that pose, the penetration "
                              "the deepest along the move")
        else:
            by_reason = report.changed_by_reason()
            console.print(f"  {plural(s['changed_blocks'], 'block')} changed: {by_reason.get('collision', 0):,} tilted "
                          f"off a collision, {by_reason.get('blend', 0):,} blended into ramps{rescaled_note(by_reason)} "
                          f"(max tilt {s['max_tilt_deg']:.2f}°, max step {s['max_step_deg']:.2f}°; "
                          f"limits {report.options.max_tilt:g}° and {report.options.max_step:g}°)")
            freed = [e for e in report.collisions if e.get("outcome") == "freed"]
            if freed:
                console.print(f"  {plural(len(freed), 'colliding block')} left as programmed: freed by the change "
                              f"of the blocks before {'it' if len(freed) == 1 else 'them'} (lines "
                              + ", ".join(str(e["line"]) for e in freed[:12]) + (" …" if len(freed) > 12 else "")
                              + "; the report's collisions say how)")
            if report.unresolved:
                console.print(f"  [red]{plural(len(report.unresolved), 'block')} could not be fixed[/red] "
                              "and are left as programmed:")
                _table(console, "unresolved blocks", report.unresolved, verbose,
                       (("line", "right", lambda e: str(e["line"])),
                        ("bodies", "left", lambda e: ", ".join(e.get("bodies", []))),
                        ("where", "left", lambda e: _where(e)),
                        ("penetration mm", "right", lambda e: _mm(e.get("penetration_mm"))),
                        ("reason", "left", lambda e: str(e.get("reason") or "not corrected"))))
    for warning in report.warnings[: None if verbose else 10]:
        console.print(f"  [yellow]warning:[/yellow] {warning}")
    if not verbose and len(report.warnings) > 10:
        console.print(f"  … {len(report.warnings) - 10} more warnings (-v shows all)")
    colour = "green" if report.exit_code == 0 else "red"
    console.print(f"[bold {colour}]{report.verdict}[/bold {colour}]")


def _table(console: Console, what: str, entries: list[dict[str, Any]], verbose: bool, columns) -> None:
    if not entries:
        return
    shown = entries if verbose else entries[:ROWS]
    table = Table(box=None, pad_edge=False)
    for name, justify, _ in columns:
        table.add_column(name, justify=justify)
    for entry in shown:
        table.add_row(*(cell(entry) for _, _, cell in columns))
    console.print(table)
    if len(shown) < len(entries):
        console.print(f"  … {len(entries) - len(shown):,} more {what} (-v or --report lists all)")


def _where(entry: dict[str, Any]) -> str:
    return str(entry.get("where") or "–")


def _mm(value: Any) -> str:
    return "–" if value is None else f"{float(value):.3f}"

