"""Which machine profile reads which tool-orientation words: a word the profile does not read is an
error, never ignored, and ``--machine auto`` picks the one profile that reads a program's words.

A program posted for another machine reads wrongly under the wrong profile (Siemens ``A3=`` under
``ijk`` would leave the tool vertical; I J K under an A/C profile would be dropped), so a block
holding an orientation word its profile does not read stops the run naming the line, the word and
the profiles that read it. The rules, and auto-detection's tie-breaks: docs/profiles.md.
"""

from __future__ import annotations

import functools
from collections.abc import Generator, Iterable
from dataclasses import dataclass, field
from typing import BinaryIO

from ncfix.errors import ProgramError
from ncfix.nc.dialects import DIALECTS
from ncfix.nc.lexer import WORD_RE, code_of, parse_number
from ncfix.profiles import Profile, builtin_names, load_profile

# Words that switch on a controller's orientation programming, read by every profile of that dialect.
DIALECT_WORDS = {d.orientation_switch: d.name for d in DIALECTS.values() if d.orientation_switch}
# Block keywords of any dialect (Klartext L, LN, C ...), and those of linear moves: read before the
# profile is known (--machine auto).
_BLOCK_KINDS = frozenset().union(*(d.block_kinds for d in DIALECTS.values()))
_LINEAR_KINDS = frozenset().union(*(d.linear_kinds for d in DIALECTS.values()))
# Siemens orientation words that no built-in profile reads (Euler/RPY angles, lead and tilt).
UNREAD = ("A2", "B2", "C2", "LEAD", "TILT")
# G codes that give I J K another meaning than a tool vector (data, threads, rotations, cycles),
# and those whose axis words are no move (dwell, homing, machine coordinates, G92).
_IJK_PARAMETER_G = {5.0, 5.1, 5.2, 7.1, 10.0, 12.0, 13.0, 33.0, 33.1, 65.0, 66.0, 68.0, 68.1, 68.2, 68.3, 68.4, 76.0,
                    *(81.0 + i for i in range(9)), 4.0, 28.0, 30.0, 53.0, 92.0, 28.1, 30.1, 92.1, 92.2, 92.3}
_DATA_G = {10.0, 65.0, 66.0}
_VECTOR_IJK = ("I", "J", "K")
# auto: the blocks with orientation words it reads before deciding (later blocks are still checked).
AUTO_BLOCKS = 100


@dataclass(frozen=True)
class Owners:
    """The built-in profiles that read one word: as an orientation word, or as their extrusion word."""

    orientation: tuple[str, ...]
    extrusion: tuple[str, ...] = ()


def orientation_words(profile: Profile) -> frozenset[str]:
    """The words that set the tool orientation under ``profile`` (its vector or rotary letters and
    its dialect's switch word)."""
    words = set(profile.kinematics.orientation_letters)
    words.update(w for w, dialect in DIALECT_WORDS.items() if dialect == profile.dialect)
    return frozenset(words)


def owned_words(profile: Profile) -> frozenset[str]:
    """Every word of the vocabulary that ``profile`` reads: its orientation words and its extrusion letter."""
    return orientation_words(profile) | {profile.extrusion_letter}


@functools.lru_cache(maxsize=1)
def builtin_profiles() -> tuple[Profile, ...]:
    return tuple(load_profile(name) for name in builtin_names())


@functools.cache
def _owners_of(word: str) -> Owners:
    profiles = builtin_profiles()
    return Owners(tuple(p.name for p in profiles if word in orientation_words(p)),
                  tuple(p.name for p in profiles if word == p.extrusion_letter))


@functools.lru_cache(maxsize=1)
def vocabulary() -> frozenset[str]:
    """Every orientation word of the built-in profiles, and the words no profile reads."""
    words = set(DIALECT_WORDS) | set(UNREAD)
    for profile in builtin_profiles():
        words |= orientation_words(profile)
    return frozenset(words)


def shown(word: str, assigned: bool) -> str:
    """A word as a programmer writes it: ``A3=`` for a Siemens assignment, else the address."""
    return f"{word}=" if assigned or (len(word) > 1 and word[-1].isdigit()) else word


class BlockWords:
    """Reads the orientation words of one block in context (``orienting``); shared by the
    profile check in the modal interpreter and by ``--machine auto``."""

    def __init__(self, words: frozenset[str]):
        self.words = words

    def suspects(self, pairs: list[tuple[str, str, str, str]]) -> list[tuple[str, str, bool]]:
        """``(address, value, assigned)`` of the vocabulary's words in a block's ``WORD_RE`` pairs."""
        out = []
        for aname, avalue, addr, value in pairs:
            name = (aname or addr).upper()
            if name in self.words:
                out.append((name, avalue if aname else value, bool(aname)))
        return out

    @staticmethod
    def orienting(suspects: list[tuple[str, str, bool]], motion: int | None, gs: list[float],
                  ms: list[float], line_kind: str | None) -> list[tuple[str, bool]]:
        """The suspects that set an orientation on this block: ``motion`` is the motion mode after
        the block's G codes, ``gs`` and ``ms`` its G and M numbers, ``line_kind`` a Heidenhain
        block's keyword (L, LN, C …) or None.

        Some letters are orientation words only in context: I J K are a tool vector only on a G0/G1
        block (on G2/G3 arc centres; with G10, G33, G68.x, G76 or a canned cycle G81-G89 that
        code's parameters); a single letter with no value is no word (Heidenhain's ``C`` arc
        keyword); letters on a block that only calls an M code of 100 or more (``M205 B20000``,
        ``M900 K0.05``: printer firmware settings) or a data code (G10, G65) are its parameters."""
        parameters = (line_kind is None and not gs and any(m >= 100 for m in ms)) or any(g in _DATA_G for g in gs)
        out = []
        for name, value, assigned in suspects:
            if len(name) == 1:
                if parameters or not (value or assigned):
                    continue
                if name in _VECTOR_IJK and (motion not in (0, 1) or any(g in _IJK_PARAMETER_G for g in gs)):
                    continue
            out.append((name, assigned))
        return out


def foreign_word_error(word: str, assigned: bool, profile: Profile, where: str) -> ProgramError:
    """The one-line error for an orientation word that ``profile`` does not read."""
    text = shown(word, assigned)
    owners = _owners_of(word)
    if word in _VECTOR_IJK and owners.orientation:
        what = f"{text} on a G0/G1 block is a tool-vector word of {', '.join(owners.orientation)} " \
               f"(on G2/G3 it is an arc centre), not of {profile.name}"
    elif owners.orientation:
        what = f"{text} is a tool-orientation word of {', '.join(owners.orientation)}"
        if owners.extrusion:
            what += f" (the extrusion word of {', '.join(owners.extrusion)})"
        what += f", not of {profile.name}"
    else:
        return ProgramError(f"{text} is a tool-orientation word that no built-in machine profile reads",
                            where=where, fix="post the program with tool vectors or rotary-axis words, or give "
                            "--machine PATH of a profile that reads it")
    names = (*owners.orientation, *owners.extrusion)
    if len(names) == 1:
        fix = f"use --machine {names[0]}, or --machine auto"
    else:
        fix = "use --machine with the profile of this machine (ncfix --list-machines), or --machine auto"
    return ProgramError(what, where=where, fix=fix)


@dataclass
class Evidence:
    """What ``--machine auto`` saw in the head of a program: the first line of each orientation
    word, of each code that a profile switches TCP with, and whether E words appear."""

    words: dict[tuple[str, bool], int] = field(default_factory=dict)
    codes: dict[str, int] = field(default_factory=dict)
    e_words: bool = False
    reset: set[str] = field(default_factory=set)  # words set by G92 (an extrusion axis is reset so)
    blocks: int = 0  # blocks with orientation words


def scan(lines: Iterable[bytes], watch_codes: frozenset[str],
         block_limit: int = AUTO_BLOCKS) -> Generator[bytes, None, Evidence]:
    """Yields the lines it reads until ``block_limit`` blocks with orientation words were seen;
    the generator's return value (``StopIteration.value``) is the :class:`Evidence`."""
    evidence = Evidence()
    reader = BlockWords(vocabulary())
    motion: int | None = None
    for lineno, raw in enumerate(lines, 1):
        yield raw
        code = code_of(raw.decode("latin-1").rstrip("\r\n"))
        pairs = WORD_RE.findall(code)
        if not pairs:
            continue
        gs, ms = [], []
        line_kind = None
        for aname, _, addr, value in pairs:
            if aname:
                continue
            addr = addr.upper()
            if addr in ("G", "M") and value:
                try:
                    number = parse_number(value)
                except ValueError:
                    continue
                (gs if addr == "G" else ms).append(number)
                if addr == "M":
                    key = f"M{number:g}"
                    if key in watch_codes:
                        evidence.codes.setdefault(key, lineno)
            elif addr == "E" and value:
                evidence.e_words = True
            elif not value and addr in _BLOCK_KINDS and line_kind is None:
                line_kind = addr
        if 92.0 in gs:
            evidence.reset.update((aname or addr).upper() for aname, _, addr, _ in pairs)
        for g in gs:
            key = f"G{g:g}"
            if key in watch_codes:
                evidence.codes.setdefault(key, lineno)
            if g in (0.0, 1.0, 2.0, 3.0):
                motion = int(g)
            elif g == 80.0 or 81.0 <= g <= 89.0:
                motion = None
        if line_kind in _LINEAR_KINDS:
            motion = 1
        suspects = reader.suspects(pairs)
        if not suspects:
            continue
        found = BlockWords.orienting(suspects, motion, gs, ms, line_kind)
        for word, assigned in found:
            evidence.words.setdefault((word, assigned or (len(word) > 1 and word[-1].isdigit())), lineno)
        if found:
            evidence.blocks += 1
            if evidence.blocks >= block_limit:
                break
    return evidence


@dataclass(frozen=True)
class Choice:
    profile: Profile
    note: str  # "machine: auto -> NAME (why)"


def choose(evidence: Evidence, source: str) -> Choice:
    """The one built-in profile that reads every orientation word seen, or a ProgramError naming
    the candidates (none, or several that the program cannot tell apart).

    Candidates: the built-in profiles that read every orientation word seen and at least one of
    them as an orientation word. Then, in this order: a profile whose extrusion letter is among the
    words (the S3 printer's A, another's rotary word) only when the program resets that letter with
    G92; the ones that read the most of the words as orientation words (A/C angles are not the S3
    printer's program); with E words, the profiles extruding on E; a profile that switches TCP by
    codes (LinuxCNC's M428) only when the program uses one, and then over the others. A program
    without orientation words is read as ``ijk`` (the tool stays vertical under any profile)."""
    profiles = builtin_profiles()
    seen = sorted(evidence.words.items(), key=lambda item: (item[1], item[0][0]))
    if not seen:
        ijk = next(p for p in profiles if p.name == "ijk")
        return Choice(ijk, "machine: auto -> ijk (no tool-orientation words: the tool stays vertical)")
    words = {word for word, _ in evidence.words}
    first_line = seen[0][1]
    listing = "/".join(shown(w, a) for (w, a), _ in seen)
    where = f"{source}:{first_line}"
    candidates = [p for p in profiles if words <= owned_words(p) and words & orientation_words(p)]
    # A profile whose extrusion letter is an orientation word elsewhere (S3's A filament) reads a
    # program that resets that axis with G92, as printers do; A/B angles are not such a program.
    candidates = [p for p in candidates
                  if p.extrusion_letter not in words or p.extrusion_letter in evidence.reset]
    # A/C angles are not an S3 ring program (A its filament): prefer the profiles that read the
    # most of the words as orientation words.
    most = max((len(words & orientation_words(p)) for p in candidates), default=0)
    candidates = [p for p in candidates if len(words & orientation_words(p)) == most]
    reasons = []
    if evidence.e_words and any(p.extrusion_letter == "E" for p in candidates):
        candidates = [p for p in candidates if p.extrusion_letter == "E"]
    # A profile that switches TCP by codes reads a program that uses them; without them it would
    # read the whole program with TCP off.
    candidates = [p for p in candidates if p.tcp != "program" or set(p.tcp_on) & set(evidence.codes)]
    switching = [p for p in candidates if set(p.tcp_on) & set(evidence.codes)]
    if switching:
        candidates = switching
        code = min((evidence.codes[c], c) for p in switching for c in p.tcp_on if c in evidence.codes)
        reasons.append(f"{code[1]} on line {code[0]}")
    if len(candidates) == 1:
        why = "; ".join([f"{listing} from line {first_line}", *reasons])
        return Choice(candidates[0], f"machine: auto -> {candidates[0].name} ({why})")
    if not candidates:
        raise ProgramError(f"machine auto: no built-in profile reads {listing} together", where=where,
                           fix="give --machine PATH of a profile file for this machine; "
                               "see the README, Machine profiles")
    names = ", ".join(p.name for p in candidates)
    raise ProgramError(f"machine auto cannot tell which machine reads {listing}: {names} all do", where=where,
                       fix="give --machine NAME")


def watched_codes() -> frozenset[str]:
    """The codes ``choose`` looks for: every built-in profile's TCP switch codes."""
    codes = set()
    for p in builtin_profiles():
        codes.update(p.tcp_on)
        codes.update(p.tcp_off)
    return frozenset(c for c in codes if c[:1] in ("G", "M"))


class Replay:
    """A binary line stream that first gives back the lines already read from it (standard input
    cannot be rewound), then the rest; iterable like the file it wraps."""

    def __init__(self, head: list[bytes], rest: BinaryIO):
        self._head = iter(head)
        self._rest = rest
        self.name = getattr(rest, "name", None)

    def __iter__(self) -> "Replay":
        return self

    def __next__(self) -> bytes:
        for line in self._head:
            return line
        return next(iter(self._rest))

    def seekable(self) -> bool:
        return False


def resolve_auto(stream: BinaryIO, source: str) -> tuple[Choice, BinaryIO]:
    """``--machine auto``: the profile chosen from the head of ``stream`` (see ``scan``), and the
    stream to read the program from (rewound, or replaying the head it read)."""
    try:
        start = stream.tell() if stream.seekable() else None
    except (AttributeError, OSError, ValueError):
        start = None
    head: list[bytes] = []
    scanner = scan(iter(stream), watched_codes())
    while True:
        try:
            line = next(scanner)
        except StopIteration as stop:
            evidence = stop.value
            break
        if start is None:
            head.append(line)
    choice = choose(evidence, source)
    if start is not None:
        stream.seek(start)
        return choice, stream
    return choice, Replay(head, stream)  # type: ignore[return-value]
