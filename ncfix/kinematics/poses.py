"""Poses: a motion block's words → programmed point P, unit tool vector N and head rotation R.

Every stage that needs where the head is (the checker, the corrector, the program's box, the
path cost) reads poses here, so the profile's kinematics, its TCP rule and the tool-vector
normalisation are applied in one way. ``program_poses`` walks a program's interpreted chunks and
yields the poses of its motion blocks whose words are all known.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import numpy as np

from ncfix.profiles import Profile


class PoseMap:
    """A profile's words ↔ pose map: ``forward`` for rows of words, ``tcp`` for the TCP state the
    profile gives each block (``tcp = "never" | "always" | "program"``)."""

    def __init__(self, profile: Profile) -> None:
        self.kin = profile.kinematics
        self.is_vector = profile.is_vector
        self.tcp_mode = profile.tcp

    def normalise(self, words: np.ndarray) -> np.ndarray:
        """Words with the tool-vector components scaled to a unit vector (a copy; a zero or NaN
        vector becomes NaN, which no pose is read from). Rotary words are returned as they are."""
        if self.is_vector:
            v = words[:, 3:6]
            norm = np.linalg.norm(v, axis=1, keepdims=True)
            words = words.copy()
            words[:, 3:6] = np.divide(v, norm, out=np.full_like(v, np.nan), where=norm > 0)
        return words

    def forward(self, words: np.ndarray, tcp: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Programmed point P (n, 3), tool vector N (n, 3) and rotation R (n, 3, 3) of (n, k)
        normalised words, each row with its own TCP flag."""
        n = len(words)
        P, N, R = np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3, 3))
        for flag in (False, True):
            sel = tcp == flag
            if sel.any():
                P[sel], N[sel], R[sel] = self.kin.forward(words[sel], tcp=bool(flag))
        return P, N, R

    def tcp(self, chunk, rows: np.ndarray) -> np.ndarray:
        """Whether TCP is on at each of ``rows`` of a chunk: the profile's fixed rule, or the
        program's own switch (G43.4/M128/TRAORI... as the interpreter read it)."""
        if self.tcp_mode == "never":
            return np.zeros(len(rows), dtype=bool)
        if self.tcp_mode == "always":
            return np.ones(len(rows), dtype=bool)
        return chunk.tcp[rows].astype(bool)


@dataclass
class ChunkPoses:
    """The poses of one chunk's checkable motion blocks (every word known), in program order."""

    lines: np.ndarray  # 1-based input line of each block
    rows: np.ndarray  # the blocks' rows in their chunk
    words: np.ndarray  # normalised words
    tcp: np.ndarray
    P: np.ndarray
    N: np.ndarray
    R: np.ndarray


def program_poses(chunks: Iterable, poses: PoseMap) -> Iterator[tuple[object, ChunkPoses]]:
    """(chunk, its poses) for every interpreted chunk with a checkable motion block."""
    for chunk in chunks:
        rows = np.nonzero(chunk.motion >= 0)[0]
        rows = rows[np.isfinite(chunk.words[rows]).all(axis=1)]
        if not len(rows):
            continue
        words = poses.normalise(chunk.words[rows])
        tcp = poses.tcp(chunk, rows)
        P, N, R = poses.forward(words, tcp)
        yield chunk, ChunkPoses(chunk.first_lineno + rows, rows, words, tcp, P, N, R)
