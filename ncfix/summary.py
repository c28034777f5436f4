"""The human summary on standard error (rich); standard output carries only the program."""

from __future__ import annotations

from rich.console import Console

from ncfix.report import Report


def print_summary(report: Report, verbose: bool = False) -> None:
    console = Console(stderr=True, highlight=False)
    s = report.summary
    mode = "check" if report.options.check else "fix"
    console.print(
        f"[bold]ncfix[/bold] {report.input}: {s['lines']:,} lines, {s['motion_blocks']:,} motion blocks "
        f"({report.machine}, {mode}) in {s['seconds']:.2f} s"
    )
    if report.options.head is None:
        console.print("  no --head given: the program was read and passed through unchanged")
    for warning in report.warnings[: None if verbose else 10]:
        console.print(f"  [yellow]warning:[/yellow] {warning}")
    if not verbose and len(report.warnings) > 10:
        console.print(f"  … {len(report.warnings) - 10} more warnings (-v shows all)")
