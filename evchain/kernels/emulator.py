"""Numba kernels of the DVS emulator (filter ``emulator``); see ``docs/explanation/emulator.md``.
The pixels' state, its layout and the records the kernels take:
:mod:`evchain.kernels.emulator_state`; crossing times: :mod:`evchain.kernels.emulator_crossings`.

Firing rule (non-strict, tie tolerance ``tol`` in log units): with ``L1 = ln(float64(I1) + eps)``
an ON event fires when ``L1 >= L_ref + c_on - tol``, an OFF event when
``L1 <= L_ref - c_off + tol``. Both sides are deterministic functions of the input and the
integer state, so whether a pixel that returns exactly to a level fires never depends on
rounding in a running sum. The float32 gates are only a conservative prefilter (a relative
margin of 1e-6 below/above the exact intensity thresholds): a pixel with ``lo < I1 < hi`` cannot
fire, which costs two float32 compares and no logarithm per pixel and frame.

A call runs in blocks of ``rule.block`` intervals, each block strip by strip (``rule.strip``
pixels; :func:`_pixel_events`), so that a strip's state stays in cache from one interval to the
next; the intervals' events are then merged in pixel order and sorted by rounded time
(:func:`emulate`). Per strip and interval: pass 1 scans chunks of ``CHUNK`` pixels (the
frame prefetched ``PREFETCH_AHEAD`` pixels ahead) with a branch-free, vectorised bit mask
of the pixels outside their gates and lists these candidates from the set bits, in pixel
order; pass 2 gathers their values of the other frames (independent loads, so cache misses
overlap) and copies their state into contiguous arrays; pass 2b computes the logarithms the
rule needs in vectorised passes over the candidates (``veclog.log_pass``, within 1 ulp of
libm; ``l0`` comes from the same function, ``veclog.ln``, so a pixel back at its first
intensity has exactly its first level); pass 3a (:func:`_first_crossings`, branch-free and
vectorised) finds each candidate's interpolation piece and whether it makes no event, one or
more; pass 3b writes the state and lists the events, running the general rule (level after
level) only for pixels with several crossings. ``lcache`` keeps, per pixel, the logs of the
last interval it was examined in and (cubic) its end slope, so a pixel active in consecutive
intervals computes one new logarithm instead of four and one limited slope instead of two (the
next interval's start slope has the same operands, hence the same bits). The scan also prefetches
the look-ahead frame (cubic), whose values the gather reads for every candidate. Every value
is computed by the same float64 operations as before, so events and float times do not depend
on these shortcuts.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from evchain.kernels.emulator_crossings import _times, slope3
from evchain.kernels.emulator_state import (
    C_NOFF,
    C_NON,
    CHUNK,
    CV_COFF,
    CV_CON,
    CV_DB,
    CV_L0,
    CV_LA,
    CV_LB,
    CV_LC0,
    CV_LC1,
    CV_LC2,
    CV_LC3,
    CV_LEV,
    CV_M0,
    CV_M1,
    CV_NOFF,
    CV_NON,
    ERR_NEGATIVE,
    ERR_NONE,
    ERR_NONFINITE,
    K_MORE,
    K_NONE,
    K_OFF,
    K_ON,
    MAX_COUNT,
    NO_CACHE,
    ROW_PAD,
    S_EREF,
    S_L0,
    S_LAST,
    S_LC,
    Scratch,
    gates,
    init_rows,
)
from evchain.kernels.intrinsics import cttz, prefetch
from evchain.kernels.veclog import log_pass

#: pixels ahead of the scan whose frame values are prefetched (4 KiB)
PREFETCH_AHEAD = 1024


class Interval(NamedTuple):
    """One frame interval as :func:`_interval` reads it: frames flat [H*W] (``f0`` at its start,
    ``f1`` at its end, ``fm`` before, ``fp`` after; the cubic's neighbours) and times (µs)."""

    f0: np.ndarray
    f1: np.ndarray
    fm: np.ndarray
    fp: np.ndarray
    t0: float               #: start
    dt: float               #: length
    hprev: float            #: length of the interval before (1 without one)
    hnext: float            #: length of the interval after (1 without one)
    has_prev: bool          #: fm is a real frame (cubic only)
    has_next: bool          #: fp is a real frame (cubic only)
    jg: int                 #: global index of the interval (its first frame)


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
def _candidates(f1, fp, hi, lo, first, last, cand):
    """Pass 1: the pixels ``first .. last - 1`` outside their gates in frame f1, in pixel order,
    into ``cand``; returns (their number, the first pixel whose value is not finite or
    negative, or -1).

    Chunks of ``CHUNK`` pixels are scanned with a branch-free, vectorised bit mask, the frame
    (and the look-ahead frame fp, which the gather reads at every candidate) prefetched
    ``PREFETCH_AHEAD`` pixels ahead. A pixel's gates change only when the pixel itself is
    processed, so the set is the same as when scanning and processing in one pass."""
    c_start = first - (first % CHUNK)
    nc = 0
    bad = -1
    # the start of the strip, which the prefetches ahead of the scan do not reach
    for q in range(c_start, min(c_start + PREFETCH_AHEAD + CHUNK, last), 16):
        prefetch(f1, q)
        prefetch(fp, q)
    for c0 in range(c_start, last, CHUNK):
        c1 = min(c0 + CHUNK, last)
        # the frame comes from memory: ask for it ahead of the compares (one hint per 64-byte
        # line; 31 -> 23.5 us per 320x240 frame in isolation); likewise the look-ahead frame
        # fp, which the gather reads at every candidate (cubic; bar 1.10x; else fp is f1)
        if c0 + (PREFETCH_AHEAD + CHUNK) <= last:
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
    return nc, bad


@njit(cache=True, error_model="numpy")
def _fill_rows(pixels, eps, cand, nc):
    """The state rows of the candidates' chunks filled where not yet (:func:`init_rows`): a
    pixel's row is needed from the first time it is a candidate. A loop of its own: the test
    inside the scan's loop slowed the scan."""
    ready = pixels.ready
    if ready[-1] == ready.shape[0] - 1:
        return                           # all filled
    prev = -1
    for k in range(nc):
        c = cand[k] // CHUNK
        if c != prev:
            prev = c
            if ready[c] == 0:
                init_rows(pixels, c, eps)


@njit(cache=True, error_model="numpy")
def _gather(iv, sc, pixels, nc):
    """Pass 2: the candidates' values of the interval's other frames, and their state rows
    touched (these loads are independent, so their cache misses overlap), then their state
    (log cache, ``l0``, counts, thresholds) copied from the rows into the contiguous rows of
    ``sc.cv``, so that the passes after it read contiguous arrays (which vectorise)."""
    rows = pixels.rows
    counts = pixels.counts
    thr = pixels.thr
    mt = np.uint64(thr.shape[0] - 1)
    cand = sc.cand
    g0 = sc.g0
    gm = sc.gm
    gp = sc.gp
    cv = sc.cv
    lc0 = cv[CV_LC0]
    lc1 = cv[CV_LC1]
    lc2 = cv[CV_LC2]
    lc3 = cv[CV_LC3]
    l0 = cv[CV_L0]
    non = cv[CV_NON]
    noff = cv[CV_NOFF]
    con = cv[CV_CON]
    coff = cv[CV_COFF]
    f0 = iv.f0
    fm = iv.fm
    fp = iv.fp
    touch = 0.0
    for k in range(np.uint64(nc)):
        r = np.uint64(cand[k])
        g0[k] = f0[r]
        gm[k] = fm[r]
        gp[k] = fp[r]
        touch += rows[r, S_L0] + rows[r, S_LC]
    if touch == 1e308:
        g0[0] = 0.0                      # never: keeps the loads
    # the rows are in cache now: copied in a loop of their own (stores in the loop above
    # filled the store buffer, so that fewer of its cache misses overlapped: 4x slower)
    for k in range(np.uint64(nc)):
        r = np.uint64(cand[k])
        lc0[k] = rows[r, S_LC]
        lc1[k] = rows[r, S_LC + 1]
        lc2[k] = rows[r, S_LC + 2]
        lc3[k] = rows[r, S_LC + 3]
        l0[k] = rows[r, S_L0]
        non[k] = counts[r, C_NON]
        noff[k] = counts[r, C_NOFF]
        t = min(r, mt)
        con[k] = thr[t, 0]
        coff[k] = thr[t, 1]


@njit(cache=True, error_model="numpy")
def _scatter(src, idx, dst, n):
    """``dst[idx[q]] = src[q]`` for q < n."""
    for q in range(np.uint64(n)):
        dst[np.uint64(idx[q])] = src[q]


@njit(cache=True, error_model="numpy")
def _logs(iv, rule, sc, nc):
    """Pass 2b: the logarithms the rule needs, in vectorised passes (``log_pass``; ~3x the
    libm calls' throughput) into ``sc.logs`` rows (lb, la, lm, lp, then two rows of scratch),
    indexed by candidate: the look-ahead frame's log of every candidate (cubic), the current
    frame's of every candidate (linear: its cache keeps only la), then for the candidates
    without cached logs (listed branch-free in ``sc.unc``) those of the interval's other
    frames, computed on their values compacted into a scratch row and put back at their
    candidates (the other candidates' entries are left as they were: the rule takes their
    cached values)."""
    cubic = rule.cubic
    eps = rule.eps
    cand = sc.cand
    unc = sc.unc
    logs = sc.logs
    lc0 = sc.cv[CV_LC0]
    f1 = iv.f1
    gm = sc.gm
    g0 = sc.g0
    gp = sc.gp
    jm = np.float64(iv.jg - 1)
    llb = logs[0]
    lla = logs[1]
    llm = logs[2]
    llp = logs[3]
    lx = logs[4]
    ly = logs[5]
    if iv.has_next:
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
        nu += np.uint64(lc0[k] != jm)
    if cubic:
        for q in range(nu):
            lx[q] = np.float64(f1[np.uint64(cand[np.uint64(unc[q])])]) + eps
        log_pass(lx, ly, nu)
        _scatter(ly, unc, llb, nu)
    if iv.has_prev:
        for q in range(nu):
            lx[q] = np.float64(gm[np.uint64(unc[q])]) + eps
        log_pass(lx, ly, nu)
        _scatter(ly, unc, llm, nu)
    for q in range(nu):
        lx[q] = np.float64(g0[np.uint64(unc[q])]) + eps
    log_pass(lx, ly, nu)
    _scatter(ly, unc, lla, nu)


@njit(cache=True, inline="always", error_model="numpy")
def _kind(lb, k_on, k_off, base, con, coff, tol, more):
    """(what the rule does, ``K_*``; the first event's level with the tolerance) for a pixel
    at L = lb with counts k_on, k_off (float64) and ``more`` if a second crossing would be
    taken: the general loop's first two steps, by the same operations, as selects."""
    lon = base + ((k_on + 1.0) * con - k_off * coff)
    loff = base + (k_on * con - (k_off + 1.0) * coff)
    none = (lb < lon - tol) & (lb > loff + tol)
    on = lb >= lon - tol
    off = (lb <= loff + tol) & (not on)
    # the state after the first event, and whether a second one fires
    kon1 = k_on + (1.0 if on else 0.0)
    koff1 = k_off + (1.0 if off else 0.0)
    lon2 = base + ((kon1 + 1.0) * con - koff1 * coff)
    loff2 = base + (kon1 * con - (koff1 + 1.0) * coff)
    second = (lb >= lon2 - tol) | (lb <= loff2 + tol)
    one = (on | off) & ((not second) | (not more))
    kd = K_ON if on else K_OFF
    kd = kd if one else K_MORE
    return (K_NONE if none else kd), (lon - tol if on else loff + tol)


@njit(cache=True, error_model="numpy")
def _first_crossings(iv, rule, sc, nc):
    """Pass 3a: per candidate k, the interpolation piece (``sc.cv`` rows ``CV_LB`` ..
    ``CV_DB``) and what the rule does (``sc.kind[k]``, ``K_*``): no crossing, exactly one ON
    or OFF event (its level with the tolerance in row ``CV_LEV``), or anything else (several
    crossings, left to the general loop of :func:`_interval`). Over contiguous rows only
    (:func:`_gather` copied the state) and branch-free (the log cache's hits, the polarity
    and the slopes' limits are selects), so that it vectorises: the divisions of several
    pixels run together, and pixels of random polarity and cache state cost no mispredicted
    branches. The values are those the general loop computes, by the same operations
    (counts as float64: exact, as they are below 2^31)."""
    logs = sc.logs
    llb = logs[0]
    lla = logs[1]
    llm = logs[2]
    llp = logs[3]
    cv = sc.cv
    lc0 = cv[CV_LC0]
    lc1 = cv[CV_LC1]
    lc2 = cv[CV_LC2]
    lc3 = cv[CV_LC3]
    l0 = cv[CV_L0]
    non = cv[CV_NON]
    noff = cv[CV_NOFF]
    vcon = cv[CV_CON]
    vcoff = cv[CV_COFF]
    vlb = cv[CV_LB]
    vla = cv[CV_LA]
    vm0 = cv[CV_M0]
    vm1 = cv[CV_M1]
    vdb = cv[CV_DB]
    vlev = cv[CV_LEV]
    kind = sc.kind
    cubic = rule.cubic
    tol = rule.tol
    more = rule.cap < 0 or rule.cap > 1     # a second crossing would be taken
    dt = iv.dt
    hprev = iv.hprev
    hnext = iv.hnext
    has_prev = iv.has_prev
    has_next = iv.has_next
    jm = np.float64(iv.jg - 1)
    if not cubic:
        # linear: the piece is the secant (its cache keeps only la)
        for k in range(np.uint64(nc)):
            c0 = lc0[k]
            c2 = lc2[k]
            lb = llb[k]
            ua = lla[k]
            la = c2 if c0 == jm else ua
            kd, lev = _kind(lb, non[k], noff[k], l0[k], vcon[k], vcoff[k], tol, more)
            kind[k] = kd
            vlb[k] = lb
            vla[k] = la
            vm0[k] = lb - la
            vm1[k] = lb - la
            vlev[k] = lev
        return
    for k in range(np.uint64(nc)):
        # every load first, then selects (a load inside a conditional keeps the loop scalar)
        c0 = lc0[k]
        c1 = lc1[k]
        c2 = lc2[k]
        c3 = lc3[k]
        ub = llb[k]
        ua = lla[k]
        lm = llm[k]
        lp = llp[k]
        # logs of this pixel from the previous interval (frames jg-1 .. jg+1): the same
        # float64 values, computed once
        cached = c0 == jm
        lb = c3 if cached else ub
        la = c2 if cached else ua
        sec = (lb - la) / dt
        # cached: the slope at frame jg the previous interval computed as its end slope (the
        # same operands: hprev here = its dt, dt here = its hnext)
        sm = slope3((la - lm) / hprev, sec, hprev, dt)
        sm = sm if np.isfinite(lm) else sec
        sm = c1 if cached else sm
        da = sm if has_prev else sec
        sp = slope3(sec, (lp - lb) / hnext, dt, hnext)
        sp = sp if np.isfinite(lp) else sec
        db = sp if has_next else sec
        kd, lev = _kind(lb, non[k], noff[k], l0[k], vcon[k], vcoff[k], tol, more)
        kind[k] = kd
        vlb[k] = lb
        vla[k] = la
        vm0[k] = da * dt
        vm1[k] = db * dt
        vdb[k] = db
        vlev[k] = lev


@njit(cache=True, error_model="numpy")
def _interval(iv, rule, pixels, nc, sc, u):
    """Events of one frame interval ``iv`` for the ``nc`` candidates ``sc.cand[:nc]`` (listed
    by :func:`_candidates`), appended to the scratch's ``ui`` (flat pixel index), ``utf``,
    ``up_`` from position ``u`` (their pieces in ``piece`` from column 0). A pixel's state is
    committed only when all its events fit, so on a full buffer the call stops before that
    pixel. The log cache (row columns ``S_LC`` ..
    ``S_LC + 3``) holds (jg, slope at frame jg+1 [cubic], L of frames jg+1, jg+2 [cubic]) of
    the last interval jg in which the pixel was examined. The state is read through the 2-D
    ``rows`` with an unsigned row index: one address computation per pixel for all fields
    (strided 1-D views per field cost one multiply, a wraparound test and, with so many
    arrays, stack reloads of their pointers and strides per access); the thresholds from the
    pixel's row of ``pixels.thr`` (one row for all pixels without mismatch). Raises
    OverflowError when a pixel's count of reference moves would pass ``MAX_COUNT``.

    Passes (after :func:`_candidates`): :func:`_gather`, :func:`_logs`, then the exact rule per
    candidate, written out here (as an inlined helper its interpolation piece ran 1.5x
    slower): crossings are listed first (``piece`` rows: level, la, lb, m0, m1; row 6 the
    pixel's ``last_t``) and timed together by ``_times``, which also applies the refractory
    period.

    Returns ``(u, resume)``: ``resume`` is -1 when done, else the candidate to restart from
    after growing the buffers. (numpy error model: every divisor here is a frame
    interval > 0, so the python model's zero test per division only cost time, ~2 %.)
    """
    rows = pixels.rows
    counts = pixels.counts
    thr = pixels.thr
    mt = np.uint64(thr.shape[0] - 1)
    hi = pixels.hi
    lo = pixels.lo
    cand = sc.cand
    ui = sc.ui
    utf = sc.utf
    up_ = sc.up_
    piece = sc.piece
    logs = sc.logs
    cubic = rule.cubic
    eps = rule.eps
    tol = rule.tol
    k_hi = rule.k_hi
    k_lo = rule.k_lo
    cap = rule.cap
    t0 = iv.t0
    dt = iv.dt
    cap_u = min(ui.shape[0], u + piece.shape[1])
    u_in = u
    jg = iv.jg
    has_next = iv.has_next
    llp = logs[3]
    _gather(iv, sc, pixels, nc)
    _logs(iv, rule, sc, nc)
    kind = sc.kind
    vlb = sc.cv[CV_LB]
    vla = sc.cv[CV_LA]
    vm0 = sc.cv[CV_M0]
    vm1 = sc.cv[CV_M1]
    vdb = sc.cv[CV_DB]
    vlev = sc.cv[CV_LEV]
    _first_crossings(iv, rule, sc, nc)
    # pass 3b: the candidates' state and events
    for k in range(nc):
        i = cand[k]
        r = np.uint64(i)                 # unsigned: no wraparound test per state access
        kd = kind[k]
        t = min(r, mt)
        k_on = np.int64(counts[r, C_NON])
        k_off = np.int64(counts[r, C_NOFF])
        ron = thr[t, 2]
        roff = thr[t, 3]
        if kd == K_NONE:
            # prefilter false alarm: refresh the gates exactly
            e = np.exp(rows[r, S_L0] + (k_on * thr[t, 0] - k_off * thr[t, 1]))
            rows[r, S_EREF] = e
            hi[r], lo[r] = gates(e, ron, roff, eps, k_hi, k_lo)
            continue
        lb = vlb[k]
        la = vla[k]
        m0 = vm0[k]
        m1 = vm1[k]
        if cubic:
            if has_next:
                rows[r, S_LC] = jg
                rows[r, S_LC + 1] = vdb[k]
                rows[r, S_LC + 2] = lb
                rows[r, S_LC + 3] = llp[k]
            else:
                rows[r, S_LC] = NO_CACHE
        else:
            rows[r, S_LC] = jg
            rows[r, S_LC + 2] = lb
        e = rows[r, S_EREF]
        if kd != K_MORE:
            # one event, its polarity and level from the first pass (no branch on them)
            if u >= cap_u:
                # pixel i not committed
                return _times(u_in, u, cubic, t0, dt, rule.refractory_us, ui, utf, up_,
                              piece, rows), k
            on = kd == K_ON
            k_on += np.int64(on)
            k_off += np.int64(not on)
            e *= ron if on else roff
            ui[np.uint64(u)] = i
            up_[np.uint64(u)] = kd
            v = np.uint64(u - u_in)
            piece[0, v] = vlev[k]
            piece[1, v] = la
            piece[2, v] = lb
            piece[3, v] = m0
            piece[4, v] = m1
            piece[6, v] = rows[r, S_LAST]
            u += 1
        else:
            con = thr[t, 0]
            coff = thr[t, 1]
            base = rows[r, S_L0]
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
                    return _times(u_in, u, cubic, t0, dt, rule.refractory_us, ui, utf, up_,
                                  piece, rows), k
                ui[np.uint64(uu)] = i
                up_[np.uint64(uu)] = pol
                v = np.uint64(uu - u_in)
                piece[0, v] = lev
                piece[1, v] = la
                piece[2, v] = lb
                piece[3, v] = m0
                piece[4, v] = m1
                piece[6, v] = rows[r, S_LAST]
                uu += 1
            u = uu
        if k_on > MAX_COUNT or k_off > MAX_COUNT:
            raise OverflowError("emulator: a pixel made more than 2^31 - 1 reference moves "
                                "of one polarity")
        counts[r, C_NON] = k_on
        counts[r, C_NOFF] = k_off
        rows[r, S_EREF] = e
        hi[r], lo[r] = gates(e, ron, roff, eps, k_hi, k_lo)
    return _times(u_in, u, cubic, t0, dt, rule.refractory_us, ui, utf, up_, piece, rows), -1


@njit(cache=True)
def _frame(frames, j):
    """Frame j of ``held`` + ``cur``, flat."""
    nh = frames.held.shape[0]
    return (frames.held[j] if j < nh else frames.cur[j - nh]).ravel()


@njit(cache=True)
def _interval_of(frames, j, cubic):
    """The :class:`Interval` from frame j to frame j + 1 (j: an index into the frame list)."""
    times = frames.times
    f0 = _frame(frames, j)
    f1 = _frame(frames, j + 1)
    has_prev = cubic and j >= 1
    has_next = cubic and j + 2 < frames.total
    fm = f0
    fp = f1
    if has_prev:
        fm = _frame(frames, j - 1)
    if has_next:
        fp = _frame(frames, j + 2)
    t0 = np.float64(times[j])
    t1 = np.float64(times[j + 1])
    dt = t1 - t0
    hprev = t0 - np.float64(times[j - 1]) if has_prev else 1.0
    hnext = np.float64(times[j + 2]) - t1 if has_next else 1.0
    return Interval(f0, f1, fm, fp, t0, dt, hprev, hnext, has_prev, has_next, frames.j_base + j)


@njit(cache=True)
def _grow_events(sc, n):
    """``sc`` with room for at least n events in the event list (kept) and twice the crossings
    per :func:`_interval` call (``piece``: its columns are dead between calls)."""
    return Scratch(sc.cand, sc.g0, sc.gm, sc.gp, _grow(sc.ui, n), _grow(sc.utf, n),
                   _grow(sc.up_, n), _grow(sc.ub, n), np.empty((sc.piece.shape[0],
                                                                 2 * sc.piece.shape[1])),
                   sc.perm, sc.buckets, sc.logs, sc.unc, _grow(sc.lst, n), sc.cv, sc.kind)


@njit(cache=True)
def _grow_cv(sc, n):
    """``sc`` with room for at least n candidates in ``cv`` (its contents are dead between
    :func:`_interval` calls): twice the room, in multiples of 512 (see ``ROW_PAD``)."""
    m = max(2 * (sc.cv.shape[1] - ROW_PAD), n)
    m = (m + 511) // 512 * 512
    return Scratch(sc.cand, sc.g0, sc.gm, sc.gp, sc.ui, sc.utf, sc.up_, sc.ub, sc.piece,
                   sc.perm, sc.buckets, sc.logs, sc.unc, sc.lst,
                   np.empty((sc.cv.shape[0], m + ROW_PAD)), sc.kind)


@njit(cache=True)
def _sort_order(sc, u, it0, nb):
    """The order of the interval's u events by rounded time ``sc.ub`` (relative to it0, in
    [0, nb)): a stable counting sort over the generation order, or a stable merge sort when
    the interval is long next to its events. Returns (``sc`` with its ``perm`` and
    ``buckets`` grown if needed, the order)."""
    ub = sc.ub
    perm = sc.perm
    buckets = sc.buckets
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
            perm = np.empty(sc.ui.shape[0], np.int64)
        for q in range(u):
            b = ub[q]
            perm[buckets[b]] = q
            buckets[b] += 1
    else:
        perm = np.argsort(ub[:u], kind="mergesort")
    return Scratch(sc.cand, sc.g0, sc.gm, sc.gp, sc.ui, sc.utf, sc.up_, ub, sc.piece, perm,
                   buckets, sc.logs, sc.unc, sc.lst, sc.cv, sc.kind), perm


@njit(cache=True)
def _pixel_events(frames, j_first, j_last, rule, pixels, sc):
    """Pass A of :func:`emulate`: every pixel's events of intervals ``j_first .. j_last - 1``,
    strip by strip (``rule.strip`` pixels): all intervals of one strip before the next, so the
    strip's state (gates, state rows, log cache) stays in cache from one interval to the next
    and each frame comes from memory once. A pixel's events depend only on its own state and
    values, so the order of strips and intervals does not change them.

    Returns ``(sc, seg, u, err_k, err_pixel)``: the events of strip s in interval
    ``j_first + k`` are ``sc.ui[seg[s, k]:seg[s, k + 1]]`` (``seg[s, nk]`` = start of strip
    s + 1), ``u`` their total, and the first bad pixel value in interval order then pixel
    order (``err_k`` = -1 if none; later intervals are then not all processed)."""
    npix = pixels.hi.shape[0]
    strip = rule.strip
    ns = (npix + strip - 1) // strip
    nk = j_last - j_first
    seg = np.empty((ns, nk + 1), np.int64)
    u = 0
    err_k = nk                              # intervals before err_k are needed
    err_pixel = 0
    for st in range(ns):
        p0 = st * strip
        p1 = min(p0 + strip, npix)
        for k in range(nk):
            seg[st, k] = u
            if k >= err_k:
                # a bad pixel in an earlier strip (so at a lower index) or an earlier interval
                # comes first
                continue
            iv = _interval_of(frames, j_first + k, rule.cubic)
            nc, bad = _candidates(iv.f1, iv.fp, pixels.hi, pixels.lo, p0, p1, sc.cand)
            if nc > sc.cv.shape[1] - ROW_PAD:
                sc = _grow_cv(sc, nc)
            _fill_rows(pixels, rule.eps, sc.cand, nc)
            while nc > 0:
                u, resume = _interval(iv, rule, pixels, nc, sc, u)
                if resume < 0:
                    break
                # the candidates not done to the front, after growing the buffers
                sc = _grow_events(sc, u + 1)
                cand = sc.cand
                for q in range(nc - resume):
                    cand[q] = cand[resume + q]
                nc -= resume
            if bad >= 0:
                err_k = k
                err_pixel = bad
        seg[st, nk] = u
    return sc, seg, u, (err_k if err_k < nk else -1), err_pixel


@njit(cache=True, nogil=True)    # renders of the scene source's threads go on meanwhile
def emulate(frames, j_first, j_last, rule, pixels, noise, cap_hint, carry, keep_tf, scratch):
    """Emit the events of frame intervals ``j_first .. j_last - 1`` (interval j runs from frame
    j to frame j + 1 of the frame list).

    Events of each interval are ordered by rounded time (stable counting sort over the
    generation order: row, column, then time order at one pixel; noise last).

    Parameters
    ----------
    frames : FrameList
        The frames (float32 linear intensity) and their times (µs); ``total`` frames are
        known (look-ahead for the cubic; a missing neighbour falls back to the interval's
        secant slope).
    j_first, j_last : int
        The intervals, as indices into the frame list.
    rule : Rule
        The parameters (:func:`make_rule`).
    pixels : Pixels
        Every pixel's state (rows, columns ``S_*``; the log cache, columns ``S_LC`` .., holds
        log values reused between consecutive intervals, ``NO_CACHE`` initially) and its
        float32 gates; updated.
    noise : Noise
        Noise events of interval ``j_first + k``: ``[noise.off[k]:noise.off[k + 1]]``.
    cap_hint : int
        Expected number of output events (the output grows beyond it when needed).
    carry : tuple of ndarray
        (x, y, t, tf, p): events held from the previous call, which start the output.
    keep_tf : bool
        Keep the float times (else ``tf`` is empty).
    scratch : Scratch
        :func:`new_scratch`'s work arrays; returned grown if needed.

    Returns
    -------
    tuple
        ``(x, y, t, tf, p, n, err, err_frame, err_y, err_x, scratch)``: the first n entries of
        uint16 x, y, int64 t (µs, ``floor(tf + 0.5)``), float64 tf and int8 p are the events;
        ``err`` (``ERR_*``) names the first bad pixel value, at (err_y, err_x) of frame
        err_frame.
    """
    nh = frames.held.shape[0]
    w = frames.held.shape[2] if nh > 0 else frames.cur.shape[2]
    times = frames.times
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
    n = nc0
    sc = scratch
    inv_w = 1.0 / w
    for jb in range(j_first, j_last, rule.block):
        je = min(jb + rule.block, j_last)
        sc, seg, u, err_k, ep = _pixel_events(frames, jb, je, rule, pixels, sc)
        if err_k >= 0:
            jf = jb + err_k + 1
            err = ERR_NONFINITE if not np.isfinite(_frame(frames, jf)[ep]) else ERR_NEGATIVE
            return ox, oy, ot, otf, op, n, err, jf, ep // w, ep % w, sc
        # the block's noise after the pixels' events, as one more strip
        k0 = jb - j_first
        k1 = je - j_first
        nnoise = noise.off[k1] - noise.off[k0]
        if u + nnoise > sc.ui.shape[0]:
            sc = _grow_events(sc, u + nnoise)
        ui = sc.ui
        utf = sc.utf
        up_ = sc.up_
        for q in range(noise.off[k0], noise.off[k1]):
            ui[u] = np.int64(noise.y[q]) * w + noise.x[q]
            utf[u] = noise.t[q]
            up_[u] = noise.p[q]
            u += 1
        ns = seg.shape[0]
        noise0 = seg[ns - 1, je - jb] - noise.off[k0]   # noise event q is at noise0 + q
        for k in range(je - jb):
            # pass B: the interval's events in generation order (strips in pixel order, then
            # its noise), listed by their place in the event list, sorted by rounded time
            j = jb + k
            lst = sc.lst
            ub = sc.ub
            it0 = np.int64(times[j])
            m = 0
            for st in range(ns):
                for b in range(seg[st, k], seg[st, k + 1]):
                    lst[m] = b
                    m += 1
            for b in range(noise0 + noise.off[k0 + k], noise0 + noise.off[k0 + k + 1]):
                lst[m] = b
                m += 1
            if m == 0:
                continue
            for q in range(np.uint64(m)):
                ub[q] = np.int64(np.floor(utf[lst[q]] + 0.5)) - it0
            nb = np.int64(times[j + 1]) - it0 + 2
            if n + m > ox.shape[0]:
                ox = _grow(ox, n + m)
                oy = _grow(oy, n + m)
                ot = _grow(ot, n + m)
                if keep_tf:
                    otf = _grow(otf, n + m)
                op = _grow(op, n + m)
            sc, perm = _sort_order(sc, m, it0, nb)
            for r in range(np.uint64(m)):        # unsigned indices: no wraparound tests
                qq = np.uint64(perm[r])
                q = np.uint64(lst[qq])
                pos = np.uint64(n) + r
                i = ui[q]
                # row i // w by the reciprocal, corrected to exact (an integer division
                # per event cost ~10 % of the bar's time)
                yy = np.int64(np.float64(i) * inv_w)
                yy -= np.int64(yy * w > i)
                yy += np.int64((yy + 1) * w <= i)
                ox[pos] = i - yy * w
                oy[pos] = yy
                ot[pos] = ub[qq] + it0
                if keep_tf:
                    otf[pos] = utf[q]
                op[pos] = up_[q]
            n += m
    return ox, oy, ot, otf, op, n, ERR_NONE, 0, 0, 0, sc
