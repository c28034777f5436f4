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
    if verbose:
        for detail in report.details:
            console.print(f"  {detail}")
    if report.options.head is None:
        console.print("  no --head given: the program was read and passed through unchanged")
    else:
        hits = report.collisions
        console.print(f"  {s['colliding_blocks_before']:,} colliding blocks "
                      f"({s.get('checked_samples', 0):,} poses checked; deposit: {s.get('deposit_rule')})")
        if hits:
            from rich.table import Table

            shown = hits if verbose else hits[:20]
            table = Table(title=None, box=None, pad_edge=False)
            for name, justify in (("line", "right"), ("bodies", "left"), ("penetration mm", "right"),
                                  ("clearance mm", "right")):
                table.add_column(name, justify=justify)
            for hit in shown:
                table.add_row(str(hit["line"]), ", ".join(hit["bodies"]), f"{hit['penetration_mm']:.3f}",
                              f"{hit['clearance_mm']:.3f}")
            console.print(table)
            if len(shown) < len(hits):
                console.print(f"  … {len(hits) - len(shown)} more colliding blocks (-v or --report lists all)")
    for warning in report.warnings[: None if verbose else 10]:
        console.print(f"  [yellow]warning:[/yellow] {warning}")
    if not verbose and len(report.warnings) > 10:
        console.print(f"  … {len(report.warnings) - 10} more warnings (-v shows all)")
