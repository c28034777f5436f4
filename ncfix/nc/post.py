"""Write a fresh program from tip points and tool vectors through a profile, as a real post would.

Used to make the bundled samples and the benchmarks' generated programs; not on the filter's path
(the filter never re-posts a program, it edits blocks in place).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import numpy as np

from ncfix.nc.dialects import DIALECTS
from ncfix.nc.emit import format_value
from ncfix.profiles import Profile


def post_program(profile: Profile, points: np.ndarray, vectors: np.ndarray, *, title: str, number: int = 1,
                 feed_mm_min: float = 1200.0, approach_mm: float = 20.0,
                 comments: Sequence[tuple[int, str]] = (),
                 deposit_codes: tuple[str, str] | None = None) -> Iterator[str]:
    """Lines (with LF) of a program depositing along ``points`` (n, 3) with tool ``vectors`` (n, 3).

    The head approaches the first point from ``approach_mm`` above it along its vector, deposits
    along the path (feed moves), and retracts. ``comments`` puts ``(index, text)`` comments
    before the block of that point.
    """
    points = np.asarray(points, dtype=np.float64)
    vectors = np.asarray(vectors, dtype=np.float64)
    vectors = vectors / np.linalg.norm(vectors, axis=1, keepdims=True)
    kin = profile.kinematics
    fmt = profile.number_format
    tcp = profile.tcp != "never"
    letters = kin.letters
    decimals = {letter: fmt.linear if letter in ("X", "Y", "Z") else (fmt.vector if profile.is_vector else fmt.angle)
                for letter in letters}
    dialect = DIALECTS[profile.dialect]
    notes = dict(comments)

    def words_line(words: np.ndarray, previous: np.ndarray | None, motion: str, extra: str = "") -> str:
        parts = []
        for letter, value, old in zip(letters, words, previous if previous is not None else [None] * len(letters)):
            text = format_value(value, decimals[letter], None, fmt.force_sign, fmt.force_decimal_point)
            if dialect.post_every_word or profile.is_vector or old is None or text != format_value(
                    old, decimals[letter], None, fmt.force_sign, fmt.force_decimal_point):
                parts.append(f"{letter}{dialect.joiner(letter)}{text}")
        return dialect.post_line(motion == "rapid", profile.is_vector, " ".join(parts), feed_mm_min) + extra

    start = np.zeros(len(letters))
    if profile.is_vector:
        start[3:] = (0.0, 0.0, 1.0)
    approach = points[0] + approach_mm * vectors[0]
    previous = kin.inverse(approach, vectors[0], start, tcp=tcp)
    body = [words_line(previous, None, "rapid")]
    feed_text = f" F{feed_mm_min:.0f}" if dialect.post_rapid_feed is None else ""  # else on every block
    for i, (p, n) in enumerate(zip(points, vectors)):
        if i in notes:
            body.append(dialect.comment(notes[i]))
        words = kin.inverse(p, n, previous, tcp=tcp)
        body.append(words_line(words, previous, "feed", feed_text if i == 0 else ""))
        if i == 0 and deposit_codes:
            body.append(deposit_codes[0])
        previous = words
    if deposit_codes:
        body.append(deposit_codes[1])
    retract = points[-1] + approach_mm * vectors[-1]
    body.append(words_line(kin.inverse(retract, vectors[-1], previous, tcp=tcp), previous, "rapid"))

    yield from dialect.post_frame(body, title, number, profile.is_vector, profile.tcp != "never")
