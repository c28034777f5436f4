"""Smoothing a corrected run of tool vectors with Bezier curves, never breaking the step limits.

The orientation graph's path holds a lattice direction and then jumps by about the resolution;
``blend`` keeps the levels that must stay and replaces each span between them by a monotone cubic
Bezier ease of the correction offset, falling back span by span (eased, eased-budget, linear,
linear-budget, input) until every step is within its limit. The offsets, the easing and the step
guarantee: docs/correction.md, "Blending".
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ncfix.geometry.frames import angle_between_deg, rotation_between

# The ways a span can end up, by the code stored in BlendResult.method (-1: no free level).
METHODS = ("eased", "eased-budget", "linear", "linear-budget", "input")
_RUNGS = (("eased", "uniform"), ("eased", "budget"), ("linear", "uniform"), ("linear", "budget"))
FALLBACK = len(_RUNGS)
NO_FREE_LEVEL = -1

_X = np.array([1.0, 0.0, 0.0])
_Y = np.array([0.0, 1.0, 0.0])
# Below this |b - (a·b) a| with a·b < 0, two unit vectors count as antipodal (no great circle).
_ANTIPODAL = 1e-12


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("...i,...i->...", a, b)


def _perpendicular(p: np.ndarray) -> np.ndarray:
    """Deterministic unit vectors (..., 3) perpendicular to unit ``p`` (..., 3).

    +X made perpendicular to p, or +Y where p is within ~26° of ±X (so the projection is long).
    """
    helper = np.where(np.abs(p[..., :1]) < 0.9, _X, _Y)
    u = helper - _dot(helper, p)[..., None] * p
    return u / np.linalg.norm(u, axis=-1, keepdims=True)


# -- sphere primitives ---------------------------------------------------------------------------
def slerp(a: np.ndarray, b: np.ndarray, t) -> np.ndarray:
    """Point a fraction ``t`` of the way along the shorter great-circle arc from ``a`` to ``b``.

    a, b : (..., 3) float64 unit vectors; t : scalar or (...,) float (broadcast together; t
    outside [0, 1] extrapolates along the same great circle).
    returns : (..., 3) float64 unit vectors, at angle t·θ from a (θ = angle a→b).

    Exact cases: t == 0 gives a, t == 1 gives b, a == b gives a (bit for bit). Near a == b the
    arc is computed without dividing by sin θ, so it stays accurate down to θ = 0. When a and b
    are antipodal (|b − (a·b)a| ≤ 1e-12 with a·b < 0) every great circle is a shortest arc; the
    one through the deterministic perpendicular of a (+X made perpendicular, or +Y near ±X) is
    used, so the result is still a unit vector at angle t·π from a, and repeatable. Nearly
    antipodal pairs above that threshold use their own (ill-conditioned but valid) great circle.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    shape = np.broadcast_shapes(a.shape[:-1], b.shape[:-1], t.shape)
    a = np.broadcast_to(a, shape + (3,))
    b = np.broadcast_to(b, shape + (3,))
    t = np.broadcast_to(t, shape)
    c = _dot(a, b)
    w = b - c[..., None] * a  # b's part perpendicular to a: the direction of travel
    s = np.linalg.norm(w, axis=-1)
    theta = np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), c)
    antipodal = (s <= _ANTIPODAL) & (c < 0)
    u = np.divide(w, s[..., None], out=np.zeros_like(w), where=(s > 0)[..., None])
    if antipodal.any():
        u = np.where(antipodal[..., None], _perpendicular(a), u)
    angle = t * theta
    out = np.cos(angle)[..., None] * a + np.sin(angle)[..., None] * u
    out = np.where(((t == 0) | np.all(a == b, axis=-1))[..., None], a, out)
    return np.where((t == 1)[..., None], b, out)


def bezier_sphere(control: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Bezier curve on the sphere: de Casteljau's construction with slerp in place of lerp.

    control : (m, 3) float64 unit vectors, m ≥ 1; t : (n,) float in [0, 1].
    returns : (n, 3) float64 unit vectors; control[0] exactly at t == 0 and control[-1] exactly
    at t == 1. Two control points give slerp; m points cost m(m−1)/2 slerps per t.
    """
    control = np.asarray(control, dtype=np.float64)
    t = np.atleast_1d(np.asarray(t, dtype=np.float64))
    if control.ndim != 2 or control.shape[1] != 3 or len(control) == 0:
        raise ValueError(f"control must be (m, 3) with m >= 1, got {control.shape}")
    pts = np.broadcast_to(control, (len(t),) + control.shape)
    for _ in range(len(control) - 1):
        pts = slerp(pts[:, :-1], pts[:, 1:], t[:, None])
    return np.array(pts[:, 0])


def step_deg(N: np.ndarray) -> np.ndarray:
    """Angles in degrees between consecutive vectors: N (L, 3) unit → (L−1,) float64 (entry i is
    the step into level i+1)."""
    N = np.asarray(N, dtype=np.float64)
    return angle_between_deg(N[1:], N[:-1])


# -- offsets in the transported frame ------------------------------------------------------------
def transported_frames(N0: np.ndarray) -> np.ndarray:
    """Orthonormal tangent frames carried along the programmed vectors by parallel transport.

    N0 : (L, 3) float64 unit vectors (the programmed sequence).
    returns : (L, 2, 3) float64: F[i, 0] = e1, F[i, 1] = e2 = N0[i] × e1, both ⟂ N0[i]. Frame 0
    has e1 = the deterministic perpendicular of N0[0] (+X made perpendicular, or +Y near ±X);
    frame i is the minimal rotation N0[i−1] → N0[i] (``rotation_between``) applied to frame i−1.

    Computed without a sequential loop: each level also has its own deterministic reference frame
    (f1, f2); transporting f1 from level i−1 turns it by an angle δ_i within frame i, so frame i
    is the reference frame turned by φ_i = δ_1 + … + δ_i (rotations keep cross products, so one
    angle describes the whole frame).
    """
    N0 = np.asarray(N0, dtype=np.float64)
    f1 = _perpendicular(N0)
    f2 = np.cross(N0, f1)
    phi = np.zeros(len(N0))
    if len(N0) > 1:
        R = rotation_between(N0[:-1], N0[1:])
        g = np.einsum("nij,nj->ni", R, f1[:-1])
        delta = np.arctan2(_dot(g, f2[1:]), _dot(g, f1[1:]))
        phi[1:] = np.cumsum(delta)
    c, s = np.cos(phi)[:, None], np.sin(phi)[:, None]
    return np.stack([c * f1 + s * f2, c * f2 - s * f1], axis=1)


def _log(p: np.ndarray, q: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Log map of q at p in frames F: (n, 3), (n, 3), (n, 2, 3) → (n, 2) radians."""
    c = _dot(p, q)
    w = q - c[:, None] * p
    s = np.linalg.norm(w, axis=1)
    theta = np.arctan2(np.linalg.norm(np.cross(p, q), axis=1), c)
    # θ / |w| → 1 as q → p; w's own rounding (~1e-16) then stays ~1e-16 in d.
    scale = np.divide(theta, s, out=np.zeros_like(s), where=s > 0)
    d = scale[:, None] * np.einsum("nkj,nj->nk", F, w)
    d[(s == 0) & (c < 0)] = (np.pi, 0.0)  # antipodal: any direction; e1 by convention
    d[np.all(p == q, axis=1)] = 0.0  # exactly zero, so that exp gives p back bit for bit
    return d


def _exp(p: np.ndarray, d: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Exp map of offsets d at p in frames F: (n, 3), (n, 2), (n, 2, 3) → (n, 3) unit vectors."""
    r = np.linalg.norm(d, axis=1)
    v = np.einsum("nk,nkj->nj", d, F)
    out = np.cos(r)[:, None] * p + np.sinc(r / np.pi)[:, None] * v  # sinc(r/π) = sin r / r
    zero = r == 0
    out[zero] = p[zero]
    return out


def offsets(N0: np.ndarray, N: np.ndarray) -> np.ndarray:
    """The correction N0 → N as 2-D tangent offsets in the transported frames.

    N0, N : (L, 3) float64 unit vectors. returns : (L, 2) float64 radians, the log map of N[i] at
    N0[i] in ``transported_frames(N0)[i]``: |d[i]| is the angle N0[i]→N[i] (in [0, π]) and its
    direction the way N[i] leans. N[i] == N0[i] gives exactly 0; antipodal N[i] gives (π, 0).
    """
    N0 = np.asarray(N0, dtype=np.float64)
    N = np.asarray(N, dtype=np.float64)
    return _log(N0, N, transported_frames(N0))


def apply_offsets(N0: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Inverse of ``offsets``: N0 (L, 3) unit, d (L, 2) radians in the transported frames →
    (L, 3) float64 unit vectors (exp map). d[i] == 0 gives N0[i] exactly;
    apply_offsets(N0, offsets(N0, N)) == N to ~1e-15 for |d| < π."""
    N0 = np.asarray(N0, dtype=np.float64)
    d = np.asarray(d, dtype=np.float64)
    return _exp(N0, d, transported_frames(N0))


# -- measures ------------------------------------------------------------------------------------
def offset_magnitude_deg(N0: np.ndarray, N: np.ndarray) -> np.ndarray:
    """Angle N0[i]→N[i] in degrees, (L,) float64 (the length of the offset)."""
    return np.degrees(np.linalg.norm(offsets(N0, N), axis=1))


def sign_flips(x: np.ndarray, tol: float = 1e-9) -> int:
    """Reversals of direction in a 1-D series: steps with |step| ≤ tol (holds) are skipped, then
    the number of consecutive remaining steps with opposite signs is counted."""
    s = np.diff(np.asarray(x, dtype=np.float64))
    s = s[np.abs(s) > tol]
    return int(np.count_nonzero(np.sign(s[1:]) != np.sign(s[:-1])))


def jitter(N0: np.ndarray, N: np.ndarray, tol_deg: float = 1e-9) -> int:
    """Sign flips of the step of the offset magnitude (degrees) over the sequence given.

    A clean ramp up, plateau and ramp down scores 1 (the turn at the top); restrict N0, N to the
    levels of one ramp (e.g. ``jitter(N0[:b+1], N[:b+1])``) to count the flips inside it.
    Frames depend on N0's first level, magnitudes do not, so slicing is safe.
    """
    return sign_flips(offset_magnitude_deg(N0, N), tol_deg)


def offset_accel_deg(N0: np.ndarray, N: np.ndarray) -> np.ndarray:
    """Length of the second difference of the offsets, degrees per level², (L−2,) float64: the
    angular acceleration of the correction relative to the programmed motion."""
    d = np.degrees(offsets(N0, N))
    return np.linalg.norm(d[2:] - 2.0 * d[1:-1] + d[:-2], axis=1)


# -- blending ------------------------------------------------------------------------------------
@dataclass
class BlendResult:
    """Blended vectors and how each span was filled.

    N : (L, 3) float64 unit vectors, the result
    start, stop : (S,) int64, the kept levels that bound each span (stop − start ≥ 1)
    method : (S,) int8, index into METHODS, or NO_FREE_LEVEL (−1) when stop == start + 1
    """

    N: np.ndarray
    start: np.ndarray
    stop: np.ndarray
    method: np.ndarray

    def method_names(self) -> list[str]:
        return ["none" if m == NO_FREE_LEVEL else METHODS[m] for m in self.method]


def _easing(t: np.ndarray, alpha: np.ndarray, beta: np.ndarray) -> np.ndarray:
    """1-D cubic Bezier with control values 0, α, 1−β, 1 at t (all (n,))."""
    u = 1.0 - t
    return 3.0 * u * u * t * alpha + 3.0 * u * t * t * (1.0 - beta) + t * t * t


def _end_velocities(dk: np.ndarray, kidx: np.ndarray, L: int) -> tuple[np.ndarray, np.ndarray]:
    """Offset velocity (per level) at each span's ends, seen from outside the span.

    dk (K, 2) offsets of the kept levels kidx (K,). Returns v_start (K−1, 2) at kidx[:-1] and
    v_stop (K−1, 2) at kidx[1:]. The episode ends have velocity 0 (the program beyond is not
    corrected); a kept level whose outer neighbour is kept takes their difference; a kept level
    between two spans takes the central difference of the kept levels on either side (the same
    on both sides, so the curve is C1 there when neither projection is clipped).
    """
    K = len(kidx)
    prev = np.maximum(np.arange(K) - 1, 0)
    nxt = np.minimum(np.arange(K) + 1, K - 1)
    span = np.maximum(kidx[nxt] - kidx[prev], 1)[:, None]
    central = (dk[nxt] - dk[prev]) / span
    left_adjacent = (kidx[prev] == kidx - 1)[:, None]
    right_adjacent = (kidx[nxt] == kidx + 1)[:, None]
    v_left = np.where(left_adjacent, dk - dk[prev], central)
    v_left[kidx == 0] = 0.0
    v_right = np.where(right_adjacent, dk[nxt] - dk, central)
    v_right[kidx == L - 1] = 0.0
    return v_left[:-1], v_right[1:]


def blend_detailed(N0: np.ndarray, N: np.ndarray, keep: np.ndarray, max_step_deg: float,
                   limits_deg: np.ndarray | None = None) -> BlendResult:
    """``blend`` with the spans and the method each one ended with (see the module docstring)."""
    N0 = np.asarray(N0, dtype=np.float64)
    N = np.asarray(N, dtype=np.float64)
    keep = np.array(keep, dtype=bool)
    L = len(N)
    if N0.shape != (L, 3) or N.shape != (L, 3) or keep.shape != (L,):
        raise ValueError(f"N0 {N0.shape}, N {N.shape} must be (L, 3) and keep {keep.shape} (L,)")
    if limits_deg is None:
        limits = np.full(L, float(max_step_deg))
    else:
        limits = np.asarray(limits_deg, dtype=np.float64)
        if limits.shape != (L,):
            raise ValueError(f"limits_deg must be (L,) = ({L},), got {limits.shape}")
    out = N.copy()
    empty = np.zeros(0, dtype=np.int64)
    if L < 3:
        return BlendResult(out, empty, empty, np.zeros(0, dtype=np.int8))
    keep[0] = keep[-1] = True

    kidx = np.flatnonzero(keep)
    start, stop = kidx[:-1], kidx[1:]
    length = stop - start
    method = np.full(len(start), NO_FREE_LEVEL, dtype=np.int8)
    pending = length >= 2
    free = np.flatnonzero(~keep)
    if not pending.any():
        return BlendResult(out, start, stop, method)

    F = transported_frames(N0)
    dk = _log(N0[kidx], N[kidx], F[kidx])
    chord = dk[1:] - dk[:-1]  # (S, 2)
    chord2 = _dot(chord, chord)
    v_start, v_stop = _end_velocities(dk, kidx, L)
    # Handle lengths as fractions of the chord: velocity along the chord × levels / 3 (the
    # Bezier's end derivative is 3α per unit t), clipped to [0, 1/3] so the easing is monotone.
    gain = np.divide(length / 3.0, chord2, out=np.zeros(len(start)), where=chord2 > 0)
    alpha = np.clip(_dot(v_start, chord) * gain, 0.0, 1.0 / 3.0)
    beta = np.clip(_dot(v_stop, chord) * gain, 0.0, 1.0 / 3.0)

    # Step bound: the limit, or N's own step where N already exceeds it (then N is the best known).
    step_n = step_deg(N)
    bound = np.maximum(limits[1:], step_n)
    kept_before = np.cumsum(keep) - 1  # span index of each level (the span its prev kept starts)
    sid = kept_before[free]
    step_span = kept_before[:-1]  # the step into level j belongs to the span of level j-1
    a, b = start[sid], stop[sid]
    t_uniform = (free - a) / (b - a)
    budget = np.maximum(limits[1:] - step_deg(N0), 0.0)
    W = np.concatenate([[0.0], np.cumsum(budget)])
    total = W[b] - W[a]
    t_budget = np.divide(W[free] - W[a], total, out=t_uniform.copy(), where=total > 0)

    for code, (shape, timing) in enumerate(_RUNGS):
        if not pending.any():
            break
        m = pending[sid]
        s = sid[m]
        t = (t_uniform if timing == "uniform" else t_budget)[m]
        e = _easing(t, alpha[s], beta[s]) if shape == "eased" else t
        levels = free[m]
        out[levels] = _exp(N0[levels], dk[s] + chord[s] * e[:, None], F[levels])
        failed = np.zeros(len(start), dtype=bool)
        failed[step_span[step_deg(out) > bound]] = True
        method[pending & ~failed] = code
        pending &= failed
    if pending.any():
        levels = free[pending[sid]]
        out[levels] = N[levels]
        method[pending] = FALLBACK
    return BlendResult(out, start, stop, method)


def blend(N0: np.ndarray, N: np.ndarray, keep: np.ndarray, max_step_deg: float,
          limits_deg: np.ndarray | None = None) -> np.ndarray:
    """Smooth the corrected tool vectors N between the levels that must stay.

    N0 : (L, 3) float64 unit vectors, the programmed orientations (workpiece frame)
    N : (L, 3) float64 unit vectors, the corrector's orientations (e.g. the graph's path)
    keep : (L,) bool, levels copied from N bit for bit (levels 0 and L−1 are always kept)
    max_step_deg : the step limit θ, used for every step when ``limits_deg`` is None
    limits_deg : (L,) float64 or None, limits_deg[i] bounds the step into level i (entry 0, the
        step from before the run, is not used: level 0 is kept)
    returns : (L, 3) float64 unit vectors

    Guarantees: result[keep] == N[keep] exactly; every step satisfies
    ``step_deg(result) <= max(limit, step_deg(N))`` elementwise, i.e. within the limits wherever
    N is; where no smooth curve of a span achieves that, the span's levels are copied from N (so
    the span then is exactly N). N == N0 gives N0 exactly. Deterministic; vectorised, a few O(L)
    passes.
    """
    return blend_detailed(N0, N, keep, max_step_deg, limits_deg).N
