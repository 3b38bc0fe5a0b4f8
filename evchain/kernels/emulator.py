"""Numba kernels of the DVS emulator (filter ``emulator``); see ``docs/explanation/emulator.md``.

Per pixel state (all ``[H, W]``): ``l0`` (float64 log level of the first frame), ``n_on``,
``n_off`` (int64 counts of reference moves), ``c_on``, ``c_off`` (float64 thresholds in natural
log units), ``last_t`` (float64 µs of the last emitted event, for the refractory period),
``e_ref`` (float64 exp of the reference, kept by multiplication), ``r_on = exp(c_on)``,
``r_off = exp(-c_off)`` and the float32 intensity gates ``hi``/``lo``; all but the gates are
columns ``S_*`` of one 128-byte row per pixel, which ``emulate`` reads as the 2-D ``rows``
(``irows``: its int64 view for the counts). The reference level is always
recomputed from the integer state, ``L_ref = l0 + (n_on*c_on - n_off*c_off)``, so it never
drifts.

Firing rule (non-strict, tie tolerance ``tol`` in log units): with ``L1 = ln(float64(I1) + eps)``
an ON event fires when ``L1 >= L_ref + c_on - tol``, an OFF event when
``L1 <= L_ref - c_off + tol``. Both sides are deterministic functions of the input and the
integer state, so whether a pixel that returns exactly to a level fires never depends on
rounding in a running sum. The float32 gates are only a conservative prefilter (a relative
margin of 1e-6 below/above the exact intensity thresholds): a pixel with ``lo < I1 < hi`` cannot
fire, which costs two float32 compares and no logarithm per pixel and frame.

Per interval (``_interval``): pass 1 scans chunks of ``CHUNK`` pixels (the frame prefetched
``PREFETCH_AHEAD`` pixels ahead) with a branch-free,
vectorised bit mask of the pixels outside their gates and lists these candidates from the set
bits, in pixel order; pass 2
gathers their values of the other frames (independent loads, so cache misses overlap); pass 2b
computes the logarithms the rule needs in vectorised passes over the candidates
(``veclog.log_pass``, within 1 ulp of libm; ``l0`` comes from the same function, ``veclog.ln``,
so a pixel back at its first intensity has exactly its first level); pass 3
runs the exact rule per candidate. ``lcache`` keeps, per pixel, the logs of the last interval
it was examined in and (cubic) its end slope, so a pixel active in consecutive intervals
computes one new logarithm instead of four and one limited slope instead of two (the next
interval's start slope has the same operands, hence the same bits). The scan also prefetches
the look-ahead frame (cubic), whose values the gather reads for every candidate. Every value
is computed by the same float64 operations as before, so events and float times do not depend
on these shortcuts.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from evchain.kernels.intrinsics import cttz, prefetch
from evchain.kernels.veclog import ln, log_pass

ERR_NONE = 0
ERR_NONFINITE = 1
ERR_NEGATIVE = 2
#: relative margin of the prefilter gates (covers float32 rounding and e_ref drift)
GATE_MARGIN = 1e-6
#: pixels per chunk of the candidate scan
CHUNK = 64
#: lcache interval index meaning "nothing cached"
NO_CACHE = -10.0
#: minus the smallest normal float32: the OFF gate when no OFF level is reachable
LO_NONE = -1.1754944e-38
#: pixels ahead of the scan whose frame values are prefetched (4 KiB)
PREFETCH_AHEAD = 1024
#: bound on the cubic crossing solve's error, in fractions of the frame interval
SOLVE_TOL = 1e-13
#: Newton steps run over all crossings of an interval together before the checked step
NEWTON_LOCKSTEP = 2
#: columns of a pixel's state row (``rows``: float64 [H*W, 16]; ``irows``: its int64 view):
#: l0, c_on, c_off, r_on, r_off, e_ref, last_t, n_on, n_off (int64), the log cache (4 columns)
S_L0, S_CON, S_COFF, S_RON, S_ROFF, S_EREF, S_LAST, S_NON, S_NOFF, S_LC = range(10)


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
def init_state(frame, eps, tol, con_in, coff_in, l0, n_on, n_off, c_on, c_off, r_on, r_off,
               e_ref, hi, lo, last_t, lcache):
    """Initialise every pixel's state from ``frame`` and the thresholds ``con_in``/``coff_in``
    (``[H, W]``, may be broadcast), in one pass; ``lcache`` is ``[H*W, 4]``. Returns
    (err, y, x)."""
    h, w = frame.shape
    k_hi, k_lo = gate_factors(tol)
    # exp of the thresholds only where they change (all pixels share them without mismatch)
    con = np.nan
    coff = np.nan
    ron = 1.0
    roff = 1.0
    for y in range(h):
        for x in range(w):
            v = frame[y, x]
            if not np.isfinite(v):
                return ERR_NONFINITE, y, x
            if v < 0:
                return ERR_NEGATIVE, y, x
            l0[y, x] = ln(np.float64(v) + eps)
            n_on[y, x] = 0
            n_off[y, x] = 0
            last_t[y, x] = -1e300
            if con_in[y, x] != con:
                con = con_in[y, x]
                ron = np.exp(con)
            if coff_in[y, x] != coff:
                coff = coff_in[y, x]
                roff = np.exp(-coff)
            c_on[y, x] = con
            c_off[y, x] = coff
            lcache[y * w + x, 0] = NO_CACHE
            r_on[y, x] = ron
            r_off[y, x] = roff
            e_ref[y, x] = np.float64(v) + eps
            a, b = gates(e_ref[y, x], r_on[y, x], r_off[y, x], eps, k_hi, k_lo)
            hi[y, x] = a
            lo[y, x] = b
    return ERR_NONE, 0, 0


@njit(cache=True, error_model="numpy")
def slope3(d1, d2, h1, h2):
    """Limited three-point slope at a node between secants d1 (width h1) and d2 (width h2).

    Exact for quadratics; zero at extrema; clipped to 3*min(|d1|, |d2|) (Fritsch-Carlson), so
    the cubic Hermite pieces on both sides stay monotone. (numpy error model, as in
    ``_interval``: no zero-divisor test per division; h1 + h2 > 0 as frame times increase.)
    """
    if d1 * d2 <= 0.0:
        return 0.0
    d = (h2 * d1 + h1 * d2) / (h1 + h2)
    m = 3.0 * min(abs(d1), abs(d2))
    if abs(d) > m:
        d = m if d > 0 else -m
    return d


@njit(cache=True)
def solve_crossing(level, la, lb, m0, m1, cubic):
    """Fraction s in [0, 1] of the interval where the (monotone) piece reaches ``level``.

    Linear: (level - la) / (lb - la). Cubic: safeguarded Newton on the monotone Hermite piece
    in power form (Horner), started at the linear solution; bisection whenever Newton leaves
    the bracket. A Newton step d from s lands within (|p''(s)| d^2 / 2 + |p'''| |d|^3 / 6)
    / |p'(s)| of the root (Taylor), so it stops as soon as that bound is below ``SOLVE_TOL``
    (or the step below 1e-10), without a further step to confirm convergence. Levels outside
    [la, lb] clip to 0 or 1 (a level within the tie tolerance just beyond lb gives s = 1; a
    carried-over crossing gives 0).
    """
    if lb == la:
        return 0.0
    s = (level - la) / (lb - la)
    if s <= 0.0:
        return 0.0
    if s >= 1.0:
        return 1.0
    if not cubic:
        return s
    d = lb - la
    # p(s) - level = g + s (m0 + s (c2 + s c3))
    c2 = 3.0 * d - 2.0 * m0 - m1
    c3 = m0 + m1 - 2.0 * d
    g = la - level
    ac3 = 2.0 * abs(c3)
    up = d > 0.0
    a = 0.0
    b = 1.0
    for _ in range(100):
        f = g + s * (m0 + s * (c2 + s * c3))
        if f == 0.0:
            return s
        if (f < 0.0) == up:
            a = s
        else:
            b = s
        df = m0 + s * (2.0 * c2 + 3.0 * c3 * s)
        sn = 0.5 * (a + b)
        if df != 0.0:
            st = f / df
            if a < s - st < b:
                sn = s - st
                ast = abs(st)
                ddf = 2.0 * c2 + 6.0 * c3 * s
                if ast < 1e-10 or (abs(ddf) + ac3 * ast) * ast * ast < 2.0 * SOLVE_TOL * abs(df):
                    return sn
        if b - a < 1e-15:
            return sn
        s = sn
    return s


@njit(cache=True)
def _grow(arr, n):
    out = np.empty(max(2 * arr.shape[0], n), arr.dtype)
    out[:arr.shape[0]] = arr
    return out


@njit(cache=True)
def _chunk_mask(f, hi, lo):
    """Bit q set where pixel q of a chunk (views of CHUNK = 64 pixels) may fire: not
    lo < I < hi (NaN fails both compares, so a chunk holding one is examined and reported).

    Branch-free with a fixed trip count over views (non-negative indices), so that it
    vectorises (compares into masks, ~60 instructions per chunk); the candidates are then
    read off the set bits (``cttz``) without a test per pixel.
    """
    m = np.uint64(0)
    for q in range(CHUNK):
        v = f[q]
        m |= np.uint64(not ((v < hi[q]) & (v > lo[q]))) << np.uint64(q)
    return m


@njit(cache=True, error_model="numpy")
def _fractions(u0, u1, cubic, lev, pa, pb, p0, p1, sv):
    """``sv[q]``: the fraction of the interval where crossing q (u0 <= q < u1) occurs, or -1
    where the cubic needs the safeguarded solver.

    Linear: the clipped linear solution. Cubic: ``NEWTON_LOCKSTEP`` plain Newton steps from
    the linear solution, then one step with the error bound of ``solve_crossing``; -1 when it
    fails the bound or leaves (0, 1). Levels outside [la, lb] clip to 0 or 1 as in
    ``solve_crossing``. Branch-free over separate 1-D rows, writing only ``sv``, with an
    unsigned index (numba then emits no wraparound test per load), so that it vectorises
    (vdivpd) with the same operations per value as the scalar code: no crossing waits on
    another's divisions. (Loops over rows of the 2-D ``piece`` array updating a row in place
    do not vectorise.)
    """
    if not cubic:
        for q in range(np.uint64(u0), np.uint64(u1)):
            la = pa[q]
            lb = pb[q]
            s0 = (lev[q] - la) / (lb - la)
            r = 1.0 if s0 >= 1.0 else s0
            sv[q] = 0.0 if (lb == la) | (s0 <= 0.0) else r
        return
    for q in range(np.uint64(u0), np.uint64(u1)):
        la = pa[q]
        lb = pb[q]
        s0 = (lev[q] - la) / (lb - la)
        d = lb - la
        m0 = p0[q]
        m1 = p1[q]
        c2 = 3.0 * d - 2.0 * m0 - m1
        c3 = m0 + m1 - 2.0 * d
        g = la - lev[q]
        s = s0
        for _ in range(NEWTON_LOCKSTEP):
            f = g + s * (m0 + s * (c2 + s * c3))
            df = m0 + s * (2.0 * c2 + 3.0 * c3 * s)
            s = s - f / df
        # the checked step
        f = g + s * (m0 + s * (c2 + s * c3))
        df = m0 + s * (2.0 * c2 + 3.0 * c3 * s)
        st = f / df
        sn = s - st
        ast = abs(st)
        ddf = 2.0 * c2 + 6.0 * c3 * s
        bound = (abs(ddf) + 2.0 * abs(c3) * ast) * ast * ast
        ok = (sn > 0.0) & (sn < 1.0) & (bound < 2.0 * SOLVE_TOL * abs(df))
        r = sn if ok else -1.0
        r = 1.0 if s0 >= 1.0 else r
        sv[q] = 0.0 if (lb == la) | (s0 <= 0.0) else r


@njit(cache=True, error_model="numpy")
def _times(u0, u1, cubic, t0, dt, refractory_us, ui, utf, up_, piece, rows):
    """Times of the crossings ``u0 .. u1 - 1`` (``piece`` rows: level, la, lb, m0, m1, the
    pixel's ``last_t`` when listed; row 5 is scratch), then the refractory period; returns the
    new end of the event list.

    The fractions come from ``_fractions`` (all crossings together); the few the cubic's
    checked step rejects are solved again by ``solve_crossing``. Events of one pixel are
    consecutive and in time order, so the refractory test runs in list order, against the
    pixel's ``last_t`` copied into the list by the rule (its row is in the cache there, not
    here) or the previous accepted event of the same pixel. (numpy error model: a division by
    zero gives inf or NaN, which the checked step rejects, instead of raising.)
    """
    lev = piece[0]
    pa = piece[1]
    pb = piece[2]
    p0 = piece[3]
    p1 = piece[4]
    sv = piece[5]
    plast = piece[6]
    _fractions(u0, u1, cubic, lev, pa, pb, p0, p1, sv)
    w = np.uint64(u0)                      # unsigned indices: no wraparound tests
    prev = -1
    last = 0.0
    for q in range(np.uint64(u0), np.uint64(u1)):
        s = sv[q]
        if s < 0.0:
            s = solve_crossing(lev[q], pa[q], pb[q], p0[q], p1[q], True)
        tf = t0 + s * dt
        i = ui[q]
        if i != prev:
            prev = i
            last = plast[q]
        if tf - last < refractory_us:
            continue
        last = tf
        rows[np.uint64(i), S_LAST] = tf
        ui[w] = i
        utf[w] = tf
        up_[w] = up_[q]
        w += np.uint64(1)
    return np.int64(w)


@njit(cache=True, error_model="numpy")
def _interval(f0, f1, fm, fp, t0, dt, hprev, hnext, has_prev, has_next, cubic, eps, tol,
              k_hi, k_lo, refractory_us, cap, rows, irows, hi, lo, jg, first, cand, g0, gm, gp, ui,
              utf, up_, piece, u, logs, unc):
    """Events of one frame interval for pixels ``first ..``, appended to ``ui`` (flat pixel
    index), ``utf``, ``up_`` from position ``u``. A pixel's state is committed only when all
    its events fit, so on a full buffer the call stops before that pixel. ``jg`` is the global
    index of the interval (its first frame); the log cache (row columns ``S_LC`` ..
    ``S_LC + 3``) holds (jg, slope at frame jg+1 [cubic], L of frames jg+1, jg+2 [cubic]) of
    the last interval jg in which the pixel was examined. The state is read through the 2-D
    ``rows`` with an unsigned row index: one address computation per pixel for all fields
    (strided 1-D views per field cost one multiply, a wraparound test and, with so many
    arrays, stack reloads of their pointers and strides per access).

    Crossings are listed first (``piece`` rows: level, la, lb, m0, m1; row 6 the pixel's
    ``last_t``) and timed together by ``_times``, which also applies the refractory period.

    Returns ``(u, resume, err, err_pixel)``: ``resume`` is -1 when done, else the pixel to
    restart from after growing the buffers. (numpy error model: every divisor here is a frame
    interval > 0, so the python model's zero test per division only cost time, ~2 %.)
    """
    npix = hi.shape[0]
    cap_u = ui.shape[0]
    u_in = u
    c_start = first - (first % CHUNK)
    jm = np.float64(jg - 1)
    # pass 1: candidates (pixels outside their gates), in pixel order. A pixel's gates change
    # only when the pixel itself is processed, so the set is the same as when scanning and
    # processing in one pass.
    nc = 0
    bad = -1
    for c0 in range(c_start, npix, CHUNK):
        c1 = min(c0 + CHUNK, npix)
        # the frame comes from memory: ask for it ahead of the compares (one hint per 64-byte
        # line; 31 -> 23.5 us per 320x240 frame in isolation); likewise the look-ahead frame
        # fp, which the gather reads at every candidate (cubic; bar 1.10x; else fp is f1)
        if c0 + (PREFETCH_AHEAD + CHUNK) <= npix:
            for q in range(0, CHUNK, 16):
                prefetch(f1, c0 + PREFETCH_AHEAD + q)
                prefetch(fp, c0 + PREFETCH_AHEAD + q)
        if c1 - c0 == CHUNK:
            m = _chunk_mask(f1[c0:c1], hi[c0:c1], lo[c0:c1])
            if m == 0:
                continue
            if c0 < first:
                m &= ~((np.uint64(1) << np.uint64(first - c0)) - np.uint64(1))
            # the candidates from the set bits, in pixel order (a scalar re-scan of the chunk
            # would cost a branch per pixel)
            while m != 0:
                i = c0 + np.int64(cttz(m))
                m &= m - np.uint64(1)
                v1 = f1[i]
                if not np.isfinite(v1) or v1 < 0:
                    bad = i
                    break
                cand[nc] = i
                nc += 1
        else:
            for i in range(max(c0, first), c1):
                v1 = f1[i]
                if v1 < hi[i] and v1 > lo[i]:
                    continue
                if not np.isfinite(v1) or v1 < 0:
                    bad = i
                    break
                cand[nc] = i
                nc += 1
        if bad >= 0:
            break
    # pass 2: gather the candidates' other frame values and touch their state rows; these
    # loads are independent, so their cache misses overlap (one pass per interval instead of
    # one miss after another inside the event loop)
    touch = 0.0
    for k in range(np.uint64(nc)):
        r = np.uint64(cand[k])
        g0[k] = f0[r]
        gm[k] = fm[r]
        gp[k] = fp[r]
        touch += rows[r, S_L0] + rows[r, S_LC]
    if touch == 1e308:
        g0[0] = 0.0                      # never: keeps the loads
    # pass 2b: the logarithms the rule needs, in vectorised passes (``log_pass``; ~3x the
    # libm calls' throughput): the look-ahead frame's log of every candidate (cubic), the
    # current frame's of every candidate (linear: its cache keeps only la), then for the
    # candidates without cached logs (listed branch-free, their values compacted into ``lx``)
    # those of the interval's other frames, indexed by their rank q among the uncached
    llb = logs[0]
    lla = logs[1]
    llm = logs[2]
    llp = logs[3]
    lx = logs[4]
    if has_next:
        for k in range(np.uint64(nc)):
            lx[k] = np.float64(gp[k]) + eps
        log_pass(lx, llp, nc)
    if not cubic:
        for k in range(np.uint64(nc)):
            lx[k] = np.float64(f1[np.uint64(cand[k])]) + eps
        log_pass(lx, llb, nc)
    nu = np.uint64(0)
    for k in range(np.uint64(nc)):
        unc[nu] = k
        nu += np.uint64(rows[np.uint64(cand[k]), S_LC] != jm)
    if cubic:
        for q in range(nu):
            lx[q] = np.float64(f1[np.uint64(cand[np.uint64(unc[q])])]) + eps
        log_pass(lx, llb, nu)
    if has_prev:
        for q in range(nu):
            lx[q] = np.float64(gm[np.uint64(unc[q])]) + eps
        log_pass(lx, llm, nu)
    for q in range(nu):
        lx[q] = np.float64(g0[np.uint64(unc[q])]) + eps
    log_pass(lx, lla, nu)
    q = np.uint64(0)
    # pass 3: the candidates' events
    for k in range(nc):
        i = cand[k]
        r = np.uint64(i)                 # unsigned: no wraparound test per state access
        # logs of this pixel from the previous interval (frames jg-1 .. jg+1 when cubic,
        # jg-1 .. jg when linear): the same float64 values, computed once
        cached = rows[r, S_LC] == jm
        qk = q                           # rank among the uncached
        q += np.uint64(not cached)
        if not cubic:
            lb = llb[k]
        elif cached:
            lb = rows[r, S_LC + 3]
        else:
            lb = llb[qk]
        con = rows[r, S_CON]
        coff = rows[r, S_COFF]
        k_on = irows[r, S_NON]
        k_off = irows[r, S_NOFF]
        base = rows[r, S_L0]
        lev = base + ((k_on + 1) * con - k_off * coff)
        if lb < lev - tol:
            lev = base + (k_on * con - (k_off + 1) * coff)
            if lb > lev + tol:
                # prefilter false alarm: refresh the gates exactly
                e = np.exp(base + (k_on * con - k_off * coff))
                rows[r, S_EREF] = e
                hi[r], lo[r] = gates(e, rows[r, S_RON], rows[r, S_ROFF], eps, k_hi, k_lo)
                continue
        la = rows[r, S_LC + 2] if cached else lla[qk]
        m0 = lb - la
        m1 = lb - la
        if cubic:
            sec = (lb - la) / dt
            da = sec
            db = sec
            if has_prev:
                if cached:
                    # the slope at frame jg the previous interval computed as its end slope:
                    # the same operands (hprev here = its dt, dt here = its hnext), so the
                    # same bits
                    da = rows[r, S_LC + 1]
                else:
                    lm = llm[qk]
                    if np.isfinite(lm):
                        da = slope3((la - lm) / hprev, sec, hprev, dt)
            if has_next:
                lp = llp[k]
                if np.isfinite(lp):
                    db = slope3(sec, (lp - lb) / hnext, dt, hnext)
                rows[r, S_LC] = jg
                rows[r, S_LC + 1] = db
                rows[r, S_LC + 2] = lb
                rows[r, S_LC + 3] = lp
            else:
                rows[r, S_LC] = NO_CACHE
            m0 = da * dt
            m1 = db * dt
        else:
            rows[r, S_LC] = jg
            rows[r, S_LC + 2] = lb
        e = rows[r, S_EREF]
        ron = rows[r, S_RON]
        roff = rows[r, S_ROFF]
        uu = u
        count = 0
        while cap < 0 or count < cap:
            lev = base + ((k_on + 1) * con - k_off * coff)
            if lb >= lev - tol:
                k_on += 1
                e *= ron
                pol = 1
            else:
                lev = base + (k_on * con - (k_off + 1) * coff)
                if lb <= lev + tol:
                    k_off += 1
                    e *= roff
                    pol = -1
                else:
                    break
            count += 1
            # the event time is where the firing rule turns true: L = level -+ tol
            lev = lev - tol if pol > 0 else lev + tol
            if uu >= cap_u:
                # pixel i not committed
                return _times(u_in, u, cubic, t0, dt, refractory_us, ui, utf, up_,
                              piece, rows), i, ERR_NONE, 0
            v = np.uint64(uu)
            ui[v] = i
            up_[v] = pol
            piece[0, v] = lev
            piece[1, v] = la
            piece[2, v] = lb
            piece[3, v] = m0
            piece[4, v] = m1
            piece[6, v] = rows[r, S_LAST]
            uu += 1
        u = uu
        irows[r, S_NON] = k_on
        irows[r, S_NOFF] = k_off
        rows[r, S_EREF] = e
        hi[r], lo[r] = gates(e, ron, roff, eps, k_hi, k_lo)
    u = _times(u_in, u, cubic, t0, dt, refractory_us, ui, utf, up_, piece, rows)
    if bad >= 0:
        v1 = f1[bad]
        return u, -1, (ERR_NONFINITE if not np.isfinite(v1) else ERR_NEGATIVE), bad
    return u, -1, ERR_NONE, 0


@njit(cache=True)
def new_scratch(npix, ucap):
    """Work arrays of ``emulate`` for ``npix`` pixels and ``ucap`` events per interval: (cand,
    g0, gm, gp, ui, utf, up_, ub, piece, perm, buckets, logs, unc). The filter keeps them
    between calls (fresh memory costs a page fault per 4 KiB, ~2.7 µs each on the benchmark
    machine)."""
    return (np.empty(npix, np.int64), np.empty(npix, np.float32), np.empty(npix, np.float32),
            np.empty(npix, np.float32), np.empty(ucap, np.int64), np.empty(ucap, np.float64),
            np.empty(ucap, np.int8), np.empty(ucap, np.int64), np.empty((7, ucap)),
            np.empty(ucap, np.int64), np.zeros(1, np.int64), np.empty((5, npix)),
            np.empty(npix, np.int64))


@njit(cache=True, nogil=True)    # renders of the scene source's threads go on meanwhile
def emulate(held, cur, times, j_first, j_last, total, cubic, eps, tol, refractory_us,
            cap, rows, irows, hi, lo, j_base, noise_off, noise_y, noise_x, noise_t, noise_p,
            cap_hint, carry, keep_tf, scratch):
    """Emit the events of frame intervals ``j_first .. j_last - 1`` (indices into the frame list
    ``held`` + ``cur`` whose times are ``times``; interval j runs from frame j to frame j + 1).

    The per-pixel state is ``rows`` (float64 ``[H*W, 16]``, columns ``S_*``; ``irows`` is its
    int64 view for the counts) and the flat float32 gates ``hi``, ``lo``; the log cache
    (columns ``S_LC`` ..; log values reused between consecutive intervals; ``NO_CACHE``
    initially) is part of the row. ``j_base`` is the global index of frame 0 of ``held``.
    ``total`` is the number of frames known (look-ahead for the cubic; a missing neighbour
    falls back to the interval's secant slope). Noise events of interval ``j_first + k`` are
    ``noise_*[noise_off[k]:noise_off[k+1]]`` (times float µs). Events of each interval are
    ordered by rounded time (stable counting sort over the generation order: row, column, then
    time order at one pixel; noise last). The output starts with the events ``carry`` = (x, y,
    t, tf, p) held from the previous call; float times are kept only if ``keep_tf`` (else
    ``tf`` is empty). ``scratch`` is ``new_scratch``'s tuple, returned grown if needed. Returns
    ``(x, y, t, tf, p, n, err, err_frame, err_y, err_x, scratch)``; ``t = floor(tf + 0.5)``.
    """
    nh = held.shape[0]
    w = held.shape[2] if nh > 0 else cur.shape[2]
    k_hi, k_lo = gate_factors(tol)
    cx, cy, ct, ctf, cp = carry
    nc0 = cx.shape[0]
    cap_n = max(cap_hint, nc0 + 16)
    ox = np.empty(cap_n, np.uint16)
    oy = np.empty(cap_n, np.uint16)
    ot = np.empty(cap_n, np.int64)
    otf = np.empty(cap_n if keep_tf else 0, np.float64)
    op = np.empty(cap_n, np.int8)
    ox[:nc0] = cx
    oy[:nc0] = cy
    ot[:nc0] = ct
    op[:nc0] = cp
    if keep_tf:
        otf[:nc0] = ctf
    cand, g0, gm, gp, ui, utf, up_, ub, piece, perm, buckets, logs, unc = scratch
    n = nc0
    for j in range(j_first, j_last):
        f0 = (held[j] if j < nh else cur[j - nh]).ravel()
        f1 = (held[j + 1] if j + 1 < nh else cur[j + 1 - nh]).ravel()
        has_prev = cubic and j >= 1
        has_next = cubic and j + 2 < total
        fm = f0
        fp = f1
        if has_prev:
            fm = (held[j - 1] if j - 1 < nh else cur[j - 1 - nh]).ravel()
        if has_next:
            fp = (held[j + 2] if j + 2 < nh else cur[j + 2 - nh]).ravel()
        t0 = np.float64(times[j])
        t1 = np.float64(times[j + 1])
        dt = t1 - t0
        hprev = t0 - np.float64(times[j - 1]) if has_prev else 1.0
        hnext = np.float64(times[j + 2]) - t1 if has_next else 1.0
        k = j - j_first
        nnoise = noise_off[k + 1] - noise_off[k]
        u = 0
        resume = 0
        while resume >= 0:
            u, resume, err, ep = _interval(
                f0, f1, fm, fp, t0, dt, hprev, hnext, has_prev, has_next, cubic, eps, tol,
                k_hi, k_lo, refractory_us, cap, rows, irows, hi, lo, j_base + j, resume, cand,
                g0, gm, gp, ui, utf,
                up_, piece, u, logs, unc)
            if err != ERR_NONE:
                return (ox, oy, ot, otf, op, n, err, j + 1, ep // w, ep % w,
                        (cand, g0, gm, gp, ui, utf, up_, ub, piece, perm, buckets, logs, unc))
            if resume >= 0 or u + nnoise > ui.shape[0]:
                ui = _grow(ui, u + nnoise + 1)
                utf = _grow(utf, u + nnoise + 1)
                up_ = _grow(up_, u + nnoise + 1)
                ub = _grow(ub, u + nnoise + 1)
                grown = np.empty((piece.shape[0], ui.shape[0]))
                grown[:, :piece.shape[1]] = piece
                piece = grown
        for q in range(noise_off[k], noise_off[k + 1]):
            ui[u] = np.int64(noise_y[q]) * w + noise_x[q]
            utf[u] = noise_t[q]
            up_[u] = noise_p[q]
            u += 1
        if u == 0:
            continue
        # stable counting sort of this interval's events by rounded time
        it0 = np.int64(times[j])
        nb = np.int64(times[j + 1]) - it0 + 2
        for q in range(u):
            ub[q] = np.int64(np.floor(utf[q] + 0.5)) - it0
        if n + u > ox.shape[0]:
            ox = _grow(ox, n + u)
            oy = _grow(oy, n + u)
            ot = _grow(ot, n + u)
            if keep_tf:
                otf = _grow(otf, n + u)
            op = _grow(op, n + u)
        if nb <= 4 * u + 4096:
            if buckets.shape[0] < nb + 1:
                buckets = np.zeros(nb + 1, np.int64)
            else:
                buckets[:nb + 1] = 0
            for q in range(u):
                buckets[ub[q] + 1] += 1
            for b in range(nb):
                buckets[b + 1] += buckets[b]
            if perm.shape[0] < u:
                perm = np.empty(ui.shape[0], np.int64)
            for q in range(u):
                b = ub[q]
                perm[buckets[b]] = q
                buckets[b] += 1
        else:
            perm = np.argsort(ub[:u], kind="mergesort")
        for r in range(np.uint64(u)):        # unsigned indices: no wraparound tests
            q = np.uint64(perm[r])
            pos = np.uint64(n) + r
            yy = ui[q] // w
            ox[pos] = ui[q] - yy * w
            oy[pos] = yy
            ot[pos] = ub[q] + it0
            if keep_tf:
                otf[pos] = utf[q]
            op[pos] = up_[q]
        n += u
    return (ox, oy, ot, otf, op, n, ERR_NONE, 0, 0, 0,
            (cand, g0, gm, gp, ui, utf, up_, ub, piece, perm, buckets, logs, unc))
