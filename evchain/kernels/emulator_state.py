"""State of the DVS emulator's kernels (filter ``emulator``; the event loop in
:mod:`evchain.kernels.emulator`): the layout of a pixel's state, its initialisation, the
prefilter gates, and the records the kernels take (named tuples: numba passes them like their
fields).

Per pixel state: ``l0`` (float64 log level of the first frame), ``n_on``, ``n_off`` (int32
counts of reference moves, at most ``MAX_COUNT`` each), ``last_t`` (float64 µs of the last
emitted event, for the refractory period), ``e_ref`` (float64 exp of the reference, kept by
multiplication), the log cache, and the float32 intensity gates ``hi``/``lo``; all but the
gates are columns ``S_*`` of one 64-byte row per pixel (one cache line), which the kernels
read as the 2-D ``rows`` (``counts``: its int32 view, columns ``C_NON``, ``C_NOFF``). The
thresholds ``c_on``, ``c_off`` (float64, natural log units), ``r_on = exp(c_on)`` and
``r_off = exp(-c_off)`` are rows of ``Pixels.thr``: one row for all pixels, or one per pixel
with threshold mismatch. The reference level is always recomputed from the integer state,
``L_ref = l0 + (n_on*c_on - n_off*c_off)``, so it never drifts.

Set-up (:func:`init_gates`) writes only what the first interval's scan reads: the gates, from
the first frame, which is kept; the rows of a chunk of ``CHUNK`` pixels are filled from that
frame (:func:`init_rows`; ``Pixels.ready`` marks the chunk) when the scan
first finds a candidate in it. A pixel inside its gates cannot fire and reads nothing else, so
its row is never needed before that, and the filled row holds the same values as one filled
at set-up.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from evchain.kernels.veclog import ln

ERR_NONE = 0
ERR_NONFINITE = 1
ERR_NEGATIVE = 2
#: relative margin of the prefilter gates (covers float32 rounding and e_ref drift)
GATE_MARGIN = 1e-6
#: lcache interval index meaning "nothing cached"
NO_CACHE = -10.0
#: minus the smallest normal float32: the OFF gate when no OFF level is reachable
LO_NONE = -1.1754944e-38
#: float64 slots of a pixel's state row (64 bytes: one cache line)
ROW = 8
#: columns of a pixel's state row (``rows``: float64 [H*W, ROW]): l0, e_ref, last_t, the
#: counts (two int32), the log cache (4 columns)
S_L0, S_EREF, S_LAST, S_CNT, S_LC = range(5)
#: columns of n_on and n_off in the rows' int32 view (``counts``: int32 [H*W, 2 ROW])
C_NON, C_NOFF = 2 * S_CNT, 2 * S_CNT + 1
#: the most reference moves of one polarity a pixel can make (int32 counts; beyond it
#: ``emulate`` raises OverflowError)
MAX_COUNT = 2**31 - 1
#: rows of ``Scratch.cv``, per candidate: its state row's log cache (4 columns), ``l0``, the
#: counts and thresholds (gathered from the rows), then the rule's first pass: L at the
#: interval's end and start, the piece's end slopes (times the interval), the end slope, the
#: first event's level
(CV_LC0, CV_LC1, CV_LC2, CV_LC3, CV_L0, CV_NON, CV_NOFF, CV_CON, CV_COFF,
 CV_LB, CV_LA, CV_M0, CV_M1, CV_DB, CV_LEV) = range(15)
CV_ROWS = 15
#: ``Scratch.kind``: no crossing (gates to refresh), one ON event, one OFF event, anything else
#: (several crossings: the general loop)
K_NONE, K_ON, K_OFF, K_MORE = 0, 1, -1, 2
#: float64 slots added to each row of the per-candidate 2-D work arrays (``logs``, ``cv``):
#: their lengths (a strip's pixels, ``cv``'s capacity) are multiples of 512 slots, 4 KiB,
#: and rows that far apart fall into the same set of the core's first-level cache, so that a
#: pass over more rows than its ways (8) evicted its own lines (the gather 10x slower); 72
#: slots stagger them by 9 lines
ROW_PAD = 72
#: candidates ``Scratch.cv`` has room for at first (grown in steps of 512 when a strip and
#: interval has more): sized to the strip, its 15 rows (10 MB) made sparse-640x480 0.85x
CV_START = 4096
#: pixels per chunk of the candidate scan, and per fill of state rows
CHUNK = 64
#: most pixels per strip: the event loop runs a block of intervals on one strip before the
#: next, so that the strip's state (gates 8 bytes, state row 64 bytes per pixel: 2.25 MiB)
#: stays in a core's second-level cache from one interval to the next; the filter cuts an
#: image into strips of equal length (320x240: three of 25 600 pixels)
STRIP = 32768
#: frame intervals run strip by strip at a time: their events wait in a list until every strip
#: is done, so the list holds a block's events
BLOCK = 8


def strip_length(npix: int, most: int = STRIP) -> int:
    """Pixels per strip: ``npix`` cut into the fewest strips of at most ``most`` pixels (a
    multiple of ``CHUNK``; another ``most`` is rounded up to one), all of one length in whole
    chunks (the last one shorter by less than a chunk per strip)."""
    strip = -(-npix // -(-npix // most))
    return strip + (-strip % CHUNK)


class Rule(NamedTuple):
    """The emulator's parameters as the kernels read them (:func:`make_rule`)."""

    cubic: bool             #: monotone cubic Hermite interpolation between frames (else linear)
    eps: float              #: L = ln(I + eps)
    tol: float              #: tie tolerance, natural log units
    refractory_us: float    #: an event less than this after the pixel's last one is dropped
    cap: int                #: crossings per pixel per interval (-1: no cap)
    k_hi: float             #: gate factors of the tolerance (:func:`gate_factors`)
    k_lo: float
    strip: int              #: pixels per strip (a multiple of the scan's chunk, 64)
    block: int              #: frame intervals run strip by strip at a time


class Pixels(NamedTuple):
    """Every pixel's state (H*W pixels, flat index y W + x)."""

    rows: np.ndarray        #: float64 [H*W, ROW]: the state row of each pixel, columns ``S_*``
    counts: np.ndarray      #: int32 [H*W, 2 ROW]: the same memory, for the counts (``C_*``)
    hi: np.ndarray          #: float32 [H*W]: ON gate of the prefilter
    lo: np.ndarray          #: float32 [H*W]: OFF gate of the prefilter
    first: np.ndarray       #: float32 [H*W]: the first frame (rows are filled from it)
    thr: np.ndarray         #: float64 [m, 4]: c_on, c_off, r_on, r_off of pixel i in row
    #:                         min(i, m - 1) (m = 1: all pixels share them; else m = H*W)
    ready: np.ndarray       #: int64 [ceil(H*W / CHUNK) + 1]: 1 once the chunk's rows are
    #:                         filled; the last entry counts the filled chunks


class FrameList(NamedTuple):
    """The frames :func:`emulate` reads: ``held`` then ``cur``, at ``times``."""

    held: np.ndarray        #: float32 [h, H, W]: frames kept from earlier calls
    cur: np.ndarray         #: float32 [m, H, W]: the new frames
    times: np.ndarray       #: int64 [h + m]: their times, µs
    j_base: int             #: global index of held[0]
    total: int              #: frames known (h + m; the cubic's look-ahead stops there)


class Noise(NamedTuple):
    """Background noise events: those of interval j_first + k are ``[off[k]:off[k + 1]]``."""

    off: np.ndarray         #: int64 [intervals + 1]
    y: np.ndarray           #: uint16 [events]
    x: np.ndarray           #: uint16 [events]
    t: np.ndarray           #: float64 [events], µs
    p: np.ndarray           #: int8 [events], polarity +-1


class Scratch(NamedTuple):
    """Work arrays of :func:`emulate` (:func:`new_scratch`), kept between calls and grown when
    needed: per candidate pixel of a strip (``cand``: their indices; ``g0``, ``gm``, ``gp``:
    their values in three frames; ``logs`` [5, strip]: their logarithms; ``unc``: those
    without cached logs), per event of a call (``ui``, ``utf``, ``up_``: pixel, float time and
    polarity; ``lst``: one interval's events by their place in that list; ``ub``: their
    rounded times; ``perm``: their sorted order), per crossing of a strip and interval
    (``piece`` [7, n]: its interpolation piece), ``buckets`` of the counting sort, and per
    candidate its state and the rule's first pass (``cv`` [CV_ROWS, capacity + ROW_PAD]: rows
    ``CV_*``;
    ``kind``: what the pixel does, ``K_*``)."""

    cand: np.ndarray
    g0: np.ndarray
    gm: np.ndarray
    gp: np.ndarray
    ui: np.ndarray
    utf: np.ndarray
    up_: np.ndarray
    ub: np.ndarray
    piece: np.ndarray
    perm: np.ndarray
    buckets: np.ndarray
    logs: np.ndarray
    unc: np.ndarray
    lst: np.ndarray
    cv: np.ndarray
    kind: np.ndarray


@njit(cache=True)
def gates(e_ref, r_on, r_off, eps, k_hi, k_lo):
    """Conservative float32 gates (hi, lo) from e_ref = exp(L_ref)."""
    hi = np.float32(e_ref * r_on * k_hi - eps)
    lo = e_ref * r_off * k_lo - eps
    if lo < 0:
        return hi, np.float32(LO_NONE)
    return hi, np.float32(lo)


@njit(cache=True)
def gate_factors(tol):
    """(k_hi, k_lo): exp(-tol) and exp(tol) widened by the gate margin."""
    return np.exp(-tol) * (1.0 - GATE_MARGIN), np.exp(tol) * (1.0 + GATE_MARGIN)


@njit(cache=True)
def make_rule(cubic, eps, tol, refractory_us, cap, strip=STRIP, block=BLOCK):
    """The :class:`Rule` of these parameters (its gate factors computed here)."""
    k_hi, k_lo = gate_factors(tol)
    return Rule(cubic, eps, tol, refractory_us, cap, k_hi, k_lo, strip, block)


@njit(cache=True)
def threshold_rows(con, coff):
    """``Pixels.thr`` of the thresholds con, coff (float64 [m], natural log units): their
    rows with r_on = exp(c_on), r_off = exp(-c_off)."""
    thr = np.empty((con.shape[0], 4))
    for i in range(con.shape[0]):
        thr[i, 0] = con[i]
        thr[i, 1] = coff[i]
        thr[i, 2] = np.exp(con[i])
        thr[i, 3] = np.exp(-coff[i])
    return thr


@njit(cache=True)
def init_gates(frame, rule, pixels):
    """Set-up: check the first frame, keep it (``pixels.first``) and write every pixel's gates
    from it; the rows stay unfilled until :func:`init_rows`.

    Parameters
    ----------
    frame : ndarray, float32 [H, W]
        The first frame, linear intensity >= 0.
    rule : Rule
        Its ``eps``, ``k_hi`` and ``k_lo`` are read.
    pixels : Pixels
        Written: ``first``, ``hi``, ``lo``; read: ``thr``.

    Returns
    -------
    err, y, x : int
        ``ERR_NONFINITE`` or ``ERR_NEGATIVE`` and the first such pixel, else ``ERR_NONE``.
    """
    h, w = frame.shape
    eps = rule.eps
    k_hi = rule.k_hi
    k_lo = rule.k_lo
    first = pixels.first
    hi = pixels.hi
    lo = pixels.lo
    thr = pixels.thr
    mt = thr.shape[0] - 1
    for y in range(h):
        for x in range(w):
            v = frame[y, x]
            if not np.isfinite(v):
                return ERR_NONFINITE, y, x
            if v < 0:
                return ERR_NEGATIVE, y, x
            i = y * w + x
            first[i] = v
            t = min(i, mt)
            a, b = gates(np.float64(v) + eps, thr[t, 2], thr[t, 3], eps, k_hi, k_lo)
            hi[i] = a
            lo[i] = b
    return ERR_NONE, 0, 0


@njit(cache=True)
def init_rows(pixels, c, eps):
    """Fill the state rows of chunk c (pixels ``c*CHUNK`` .. ``c*CHUNK + CHUNK - 1``) from the
    first frame, and mark it ready: the state its pixels had since
    set-up (their gates came from the same values)."""
    rows = pixels.rows
    counts = pixels.counts
    first = pixels.first
    for i in range(c * CHUNK, min(c * CHUNK + CHUNK, first.shape[0])):
        v = np.float64(first[i])
        rows[i, S_L0] = ln(v + eps)
        counts[i, C_NON] = 0
        counts[i, C_NOFF] = 0
        rows[i, S_LAST] = -1e300
        rows[i, S_EREF] = v + eps
        rows[i, S_LC] = NO_CACHE
    pixels.ready[c] = 1
    pixels.ready[-1] += 1


@njit(cache=True)
def new_scratch(npix, ucap):
    """The :class:`Scratch` of ``emulate`` for ``npix`` pixels per strip and room for ``ucap``
    events (it grows when needed). The filter keeps it between calls (fresh memory costs a
    page fault per 4 KiB, ~2.7 µs each on the benchmark machine)."""
    return Scratch(np.empty(npix, np.int64), np.empty(npix, np.float32),
                   np.empty(npix, np.float32), np.empty(npix, np.float32),
                   np.empty(ucap, np.int64), np.empty(ucap, np.float64), np.empty(ucap, np.int8),
                   np.empty(ucap, np.int64), np.empty((7, ucap)), np.empty(ucap, np.int64),
                   np.zeros(1, np.int64), np.empty((6, npix + ROW_PAD)), np.empty(npix, np.int64),
                   np.empty(ucap, np.int64), np.empty((CV_ROWS, min(npix, CV_START) + ROW_PAD)),
                   np.empty(npix, np.int8))

