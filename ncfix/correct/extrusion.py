"""The material and the feed follow a fix: E words and inverse-time F of moves whose length it changed.

With ``--pivot tip`` a re-oriented block moves its programmed point P, so the moves into and out of
it get longer or shorter. Each such depositing move gets E in proportion to its new length, then
one factor keeps the episode's material exact at the printed decimals (no line after it changes);
a G93 move gets F·L/L′ and keeps its feed rate. With ``--pivot point`` P stays and none of this runs
(the printed words' rounding alone would otherwise rewrite E). Design: docs/correction.md,
"Extrusion and feed follow the fix".
"""

from __future__ import annotations

import numpy as np

from ncfix.nc.emit import format_value
from ncfix.nc.lexer import decimals_of, parse_number, split_eol, word_spans

# Length changes below this (mm) are no change: the printed words' rounding moves P by more.
LENGTH_TOL_MM = 1e-6
# An episode whose E per mm must move by more than this (a fraction) to keep its total is reported.
RATE_WARN = 0.01


def follow(stage, first: int, last: int) -> None:
    """Rewrite the E and G93 F words of the moves of the episode ``first .. last`` (stage rows,
    already written into the table) whose length the fix changed. A move's length is the straight
    distance between its start and end points P in the workpiece frame (the path the controller
    drives with TCP on; rotary motion adds nothing: ncfix never re-orients arcs). The moves of an
    episode are those ending at its rows and the move after its last row (it starts at one)."""
    r = stage.rows
    end = min(last + 1, len(r) - 1)
    rows = np.arange(first, end + 1)
    moves = stage.moves(first, end + 1)
    known = moves.known_start
    if not known.any():
        return
    programmed_start = r.programmed[rows - 1] if first > 0 else np.vstack(
        [stage.prev_programmed[None, :] if stage.prev_programmed is not None else moves.w_start[:1],
         r.programmed[rows[1:] - 1]])
    tcp_start = np.concatenate([r.tcp[first - 1:first] if first > 0 else r.tcp[first:first + 1], r.tcp[rows[1:] - 1]])
    L0 = _lengths(stage.path, programmed_start, r.programmed[rows], tcp_start, r.tcp[rows], known)
    L1 = _lengths(stage.path, moves.w_start, moves.w_end, tcp_start, r.tcp[rows], known)
    moved = known & (np.abs(L1 - L0) > LENGTH_TOL_MM) & (L0 > LENGTH_TOL_MM) & (L1 > LENGTH_TOL_MM)
    if not moved.any():
        return
    blocks = [_Block(stage, int(row)) for row in rows]
    texts: dict[int, dict[str, str]] = {}
    for part in _parts(stage, blocks):
        _extrusion(stage, [blocks[i] for i in part], L0[part], L1[part], moved[part], texts)
    _inverse_time(blocks, L0, L1, moved, texts)
    for i, new in texts.items():
        _record(stage, blocks[i], new)


class _Block:
    """One row's line: its chunk, index, raw text and extrusion/feed facts."""

    def __init__(self, stage, row: int):
        r = stage.rows
        self.row = row
        self.chunk = stage.held[int(r.chunk[row]) - stage.first_serial]
        self.index = int(r.row[row])
        self.line = int(r.line[row])
        self.raw = self.chunk.lines[self.index].decode("latin-1")
        spans = {}
        for span in word_spans(split_eol(self.raw)[0]):
            spans.setdefault(span.address, span.value)
        self.spans = spans
        c, i = self.chunk, self.index
        self.e_delta = float(c.e_delta[i])
        self.e_relative = bool(c.e_relative[i])
        self.feed = int(c.motion[i]) in (1, 2, 3)
        self.inverse_time = int(c.feed_mode[i]) == 93


def _lengths(path, w_start, w_end, tcp_start, tcp_end, known) -> np.ndarray:
    """(n,) straight distance between the start and end points P (mm); NaN where the start is not known."""
    out = np.full(len(w_end), np.nan)
    if known.any():
        P0, _, _ = path.forward(w_start[known], tcp_start[known])
        P1, _, _ = path.forward(w_end[known], tcp_end[known])
        out[known] = np.linalg.norm(P1 - P0, axis=1)
    return out


def _parts(stage, blocks: list[_Block]) -> list[np.ndarray]:
    """Runs of consecutive blocks that no line between them splits: a line that sets E (``G92 E``,
    a retraction without a move, an M82/M83 switch) splits the episode; each part keeps its own total."""
    letter = stage.profile.extrusion_letter
    cuts = [0]
    for k in range(1, len(blocks)):
        a, b = blocks[k - 1], blocks[k]
        if a.e_relative != b.e_relative or any(letter in _addresses(line)
                                               for line in _lines_between(stage, a.line, b.line)):
            cuts.append(k)
    cuts.append(len(blocks))
    return [np.arange(s, e) for s, e in zip(cuts[:-1], cuts[1:]) if e > s]


def _lines_between(stage, a: int, b: int):
    """The raw lines strictly between input lines a and b (both in held chunks)."""
    for chunk in stage.held:
        lo, hi = chunk.first_lineno, chunk.first_lineno + len(chunk.lines)
        for lineno in range(max(lo, a + 1), min(hi, b)):
            yield chunk.lines[lineno - lo].decode("latin-1")


def _addresses(raw: str) -> set[str]:
    return {span.address for span in word_spans(split_eol(raw)[0])}


def _extrusion(stage, blocks: list[_Block], L0, L1, moved, texts: dict) -> None:
    """New E texts of one part of the episode, into ``texts`` (block index → texts).

    Each depositing move whose length changed gets E in proportion to its new length (its
    programmed E per mm), then all of them are scaled by one factor so that the part's E stays what
    the program gives: the absolute E of its last E word (M82) is unchanged, or the sum of its
    relative E words (M83) is, exact at the printed decimals. Moves whose length did not change keep
    their E. Absolute E words between the first and the last rescaled move carry the shift (reason
    ``extrusion rescaled`` when that is a block's only change). New values take the decimals of the
    part's E words, in each word's own style (``format_value``)."""
    letter = stage.profile.extrusion_letter
    has_e = np.array([letter in b.spans and np.isfinite(b.e_delta) for b in blocks])
    if not has_e.any():
        return
    try:
        values = np.array([parse_number(b.spans[letter]) if h else np.nan for b, h in zip(blocks, has_e)])
    except ValueError:
        return
    delta = np.array([b.e_delta for b in blocks])
    rescaled = moved & has_e & np.array([b.feed for b in blocks]) & (np.nan_to_num(delta) > 0)
    if not rescaled.any():
        return
    decimals = max(decimals_of(blocks[i].spans[letter]) for i in np.nonzero(has_e)[0])
    unit = 10.0 ** decimals
    old = np.rint(delta[rescaled] * unit)  # the programmed increments, in units of the last decimal
    wanted = delta[rescaled] * L1[rescaled] / L0[rescaled]
    factor = old.sum() / unit / wanted.sum()
    wanted *= factor
    new = _round_keeping_sum(wanted * unit, int(old.sum()))
    if (new <= 0).any():
        return  # a move would stop depositing: keep the program's E
    if abs(factor - 1.0) > RATE_WARN:
        stage.report.warnings.append(
            f"lines {blocks[0].line}-{blocks[-1].line}: the fix changes the path length of the moves there by "
            f"{100.0 * (1.0 / factor - 1.0):+.1f}%; their E keeps the total, so it is {100.0 * (factor - 1.0):+.1f}% "
            f"off the programmed E per mm")
    shift = np.zeros(len(blocks))
    shift[rescaled] = new - old
    relative = blocks[0].e_relative
    if relative:
        target = np.where(rescaled, np.nan, 0.0)
        target[rescaled] = new / unit
    else:
        target = (np.rint(values * unit) + np.cumsum(shift)) / unit
    for i in np.nonzero(has_e)[0].tolist():
        if relative and not rescaled[i]:
            continue
        if not relative and shift[: i + 1].sum() == 0 and not rescaled[i]:
            continue
        like = blocks[i].spans[letter]
        text = format_value(float(target[i]), decimals, like)
        if text != like:
            texts.setdefault(i, {})[letter] = text


def _round_keeping_sum(values: np.ndarray, total: int) -> np.ndarray:
    """``values`` rounded to integers whose sum is ``total`` (largest remainders round up; ties
    to the earlier block, so the result is deterministic)."""
    low = np.floor(values)
    short = int(total - low.sum())
    order = np.argsort(-(values - low), kind="stable")
    out = low.copy()
    if short > 0:
        out[order[:short]] += 1
    elif short < 0:
        out[order[::-1][: -short]] -= 1
    return out


def _inverse_time(blocks: list[_Block], L0, L1, moved, texts: dict) -> None:
    """New F texts of the G93 moves whose length changed: F·L/L′ (F is 1/minutes, so the move keeps
    its programmed feed rate in mm/min; reason ``feed rescaled`` when that is the block's only change)."""
    todo = [i for i, b in enumerate(blocks) if moved[i] and b.inverse_time and b.feed and "F" in b.spans]
    if not todo:
        return
    decimals = max(decimals_of(b.spans["F"]) for b in blocks if b.inverse_time and "F" in b.spans)
    for i in todo:
        like = blocks[i].spans["F"]
        try:
            feed = parse_number(like)
        except ValueError:
            continue
        text = format_value(feed * float(L0[i]) / float(L1[i]), decimals, like)
        if text != like:
            texts.setdefault(i, {})["F"] = text


def _record(stage, block: _Block, new: dict[str, str]) -> None:
    """Give the writer the new texts; a block the fix did not change otherwise is reported."""
    chunk, i = block.chunk, block.index
    chunk.new_text[i] = {**chunk.new_text.get(i, {}), **new}
    if i in chunk.new_words:
        return
    reason = "extrusion rescaled" if stage.profile.extrusion_letter in new else "feed rescaled"
    chunk.reasons[i] = reason
    stage.report.changes.append({
        "line": block.line, "before": block.raw.rstrip("\r\n"), "after": None, "reason": reason,
        "tilt_deg": 0.0, "step_deg": None, "bodies": [], "clearance_before_mm": None, "clearance_after_mm": None,
        "note": "the moves around it changed length: " + ("its E keeps the episode's extrusion"
                                                          if reason == "extrusion rescaled"
                                                          else "its inverse-time F keeps the programmed feed rate"),
    })
    stage.report.summary["changed_blocks"] += 1
