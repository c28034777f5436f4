"""The only module that wires the stages: read → modal state → window stages → emit → write."""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator
from typing import BinaryIO, Protocol

from ncfix.config import Options
from ncfix.errors import NcfixError
from ncfix.nc.block import Block
from ncfix.nc.modal import Interpreter
from ncfix.nc.writer import Writer
from ncfix.profiles import Profile, load_profile
from ncfix.report import Report


class Stage(Protocol):
    """A streaming stage: takes blocks in order, gives back the blocks it is done with."""

    def push(self, block: Block) -> Iterable[Block]: ...

    def flush(self) -> Iterable[Block]: ...


def read_lines(stream: BinaryIO) -> Iterator[str]:
    """Lines of a binary stream as latin-1 text (one character per byte: lossless), ends kept."""
    for raw in stream:
        yield raw.decode("latin-1")


def build_stages(options: Options, profile: Profile, report: Report) -> list[Stage]:
    if options.head is not None:
        raise NcfixError("collision checking with --head is not available in this version of ncfix",
                         fix="run without --head to read and pass the program through")
    return []


def run(src: BinaryIO, dst: BinaryIO, options: Options, source: str = "<stdin>") -> Report:
    """Stream ``src`` to ``dst`` through the stages; returns the report (also for --check)."""
    started = time.perf_counter()
    profile = load_profile(options.machine)
    report = Report(input=source, machine=profile.name, options=options)
    interpreter = Interpreter(profile, source, options.deposit_codes)
    stages = build_stages(options, profile, report)
    writer = Writer(profile)
    write = dst.write
    pending: list[bytes] = []

    def emit(blocks: Iterable[Block]) -> None:
        for block in blocks:
            report.count(block)
            pending.append(writer.render(block).encode("latin-1"))
            if len(pending) >= 512:
                write(b"".join(pending))
                pending.clear()

    lineno = 0
    for lineno, line in enumerate(read_lines(src), start=1):
        blocks: Iterable[Block] = (interpreter.feed(lineno, line),)
        for stage in stages:
            blocks = [out for block in blocks for out in stage.push(block)]
        emit(blocks)
    tail: list[Block] = []
    for stage in stages:
        tail = [out for block in tail for out in stage.push(block)] + list(stage.flush())
    emit(tail)
    if pending:
        write(b"".join(pending))
    report.summary["lines"] = lineno
    report.summary["seconds"] = round(time.perf_counter() - started, 3)
    return report
