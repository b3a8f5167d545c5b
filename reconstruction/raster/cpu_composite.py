"""The fast CPU backend: tile-based compositing in numba with a hand-written backward.

Same maths as :func:`.reference.rasterize_to_pixels_torch` (float32):

1. binning -- each visible Gaussian covers the 16x16 tiles its box (``radii``)
   touches; Gaussians are ordered by depth (ties by index) with a radix sort of
   the depths' bits and a two-pass counting sort lays the (tile, Gaussian)
   intersections out tile by tile, front to back;
2. forward -- parallel over tiles; inside a tile the loop is Gaussian-outer:
   each Gaussian visits only the rows and, per row, the columns where its
   exponent can stay under ``ln(255 * opacity)`` (the ellipse solved in float64,
   widened by 1e-3 pixel), compositing front to back with alpha clamped at 0.99,
   skipped under 1/255, and a pixel stopping before its transmittance would
   reach 1e-4. Along a row, ``exp(-exponent)`` comes from a float64 recurrence
   instead of one ``exp`` per pixel: one pixel to the right changes the exponent
   by an amount that itself grows by the conic's ``a``, so the value is
   multiplied by a ratio that is multiplied by ``exp(-a)`` (two ``exp`` per row;
   a degenerate conic takes one per pixel);
3. backward -- parallel over tiles, back to front, over the forward's rows and
   exp values, transmittance recovered by dividing by (1 - alpha); no atomics: the thread owning a tile writes one
   gradient row per intersection, and a second parallel pass sums the rows of
   each Gaussian. Results are deterministic.
"""

from __future__ import annotations

import math
import weakref

import numba as nb
import numpy as np
import torch
from torch import Tensor

from tacsplat.reconstruction.raster.reference import ALPHA_THRESHOLD, TRANSMITTANCE_THRESHOLD

F32 = np.float32
_HALF = F32(0.5)
_ONE = F32(1.0)
_ZERO = F32(0.0)
_ALPHA_MIN = F32(ALPHA_THRESHOLD)
_T_MIN = F32(TRANSMITTANCE_THRESHOLD)
_LOG_SLACK = F32(1e-3)  # spans reach a little past ln(255 o): no pair with alpha >= 1/255 is left out
_FILL_CHUNK = 8192  # Gaussians per chunk of the parallel counting sort
_TILE_CHUNK = 4  # tiles per scheduling chunk: tile costs vary a lot, so threads take chunks dynamically
N_GRAD = 6  # per-intersection gradient row: d means2d (2), d conic (3), d opacity (1), then d colour (D)


_SPAN_EPS = 1e-3  # pixels of margin around the exact row and column ranges (float rounding)


@nb.njit(cache=True)
def _row_range(a, b, c, limit, my, y_lo, y_hi):
    """Rows [r0, r1) of a tile whose pixel centres can have an exponent <= limit.

    The ellipse 0.5 [dx dy] Q [dx dy]^T <= limit (Q = conic) reaches |dy| <= sqrt(2 limit a / det Q);
    a degenerate float32 conic falls back to the whole tile. Not inlined by numba: inside the backward (compiled
    with fused multiply-adds) it keeps its own rounding, so both passes visit the same rows, by which the cache
    of exp values and the row spans are laid out.
    """
    a64, b64, c64 = np.float64(a), np.float64(b), np.float64(c)
    det = a64 * c64 - b64 * b64
    if not (det > 0.0 and a64 > 0.0):
        return y_lo, y_hi
    ext = math.sqrt(2.0 * np.float64(limit) * a64 / det)
    lo = min(max(np.float64(my) - ext - 0.5 - _SPAN_EPS, y_lo - 1.0), y_hi + 1.0)
    hi = min(max(np.float64(my) + ext - 0.5 + _SPAN_EPS, y_lo - 1.0), y_hi + 1.0)
    return max(y_lo, int(math.ceil(lo))), min(y_hi, int(math.floor(hi)) + 1)


@nb.njit(cache=True)
def _row_span(a, inv_a, b, c, limit, dy, mx, x_lo, x_hi):
    """Columns [x0, x1) of one pixel row (dy = mean_y - centre_y) whose centres can have an exponent <= limit.

    Solves 0.5 a dx^2 + b dy dx + 0.5 c dy^2 <= limit for dx = mean_x - centre_x in float64
    (``inv_a`` = 1 / a in float64), widens by a thousandth of a pixel and clips to [x_lo, x_hi).
    The backward reads the forward's spans; it solves them again only for a tile whose pairs did not fit the
    cache. (Inlined into the forward it was slower: 19.3 -> 22.1 ns per pair at 256 px, 20k Gaussians.)
    """
    a64, b64, c64, dy64 = np.float64(a), np.float64(b), np.float64(c), np.float64(dy)
    if not a64 > 0.0:
        return x_lo, x_hi
    disc = (b64 * dy64) ** 2 - a64 * (c64 * dy64 * dy64 - 2.0 * np.float64(limit))
    if not disc >= 0.0:
        return x_lo, x_lo
    half = math.sqrt(disc) * inv_a
    centre = -b64 * dy64 * inv_a
    lo = min(max(np.float64(mx) - (centre + half) - 0.5 - _SPAN_EPS, x_lo - 1.0), x_hi + 1.0)
    hi = min(max(np.float64(mx) - (centre - half) - 0.5 + _SPAN_EPS, x_lo - 1.0), x_hi + 1.0)
    return max(x_lo, int(math.ceil(lo))), min(x_hi, int(math.floor(hi)) + 1)


@nb.njit(cache=True)
def _exponent(a, b, c, dx, dy):
    """Gaussian exponent at offset (dx, dy) = mean - pixel centre, with the conic (a, b, c): the forward's for a
    degenerate conic (no recurrence), the backward's for a tile whose pairs did not fit the cache.

    Deliberately not inlined: compiled without fused multiply-adds, it rounds the same way in
    the forward and in the (FMA-contracted) backward.
    """
    return _HALF * (a * dx * dx + c * dy * dy) + b * dx * dy


@nb.njit(parallel=True, cache=True)
def _tile_boxes(means2d, radii, tile_size, tiles_x, tiles_y, boxes, counts):
    """Tile box [x0, x1, y0, y1) and tile count of each (camera, Gaussian); 0 tiles when culled."""
    for g in nb.prange(means2d.shape[0]):
        rx, ry = radii[g, 0], radii[g, 1]
        if rx <= 0 or ry <= 0:
            counts[g] = 0
            boxes[g, 0] = boxes[g, 1] = boxes[g, 2] = boxes[g, 3] = 0
            continue
        mx, my = float(means2d[g, 0]), float(means2d[g, 1])
        x0 = min(max(math.floor((mx - rx) / tile_size), 0.0), float(tiles_x))
        x1 = min(max(math.ceil((mx + rx) / tile_size), 0.0), float(tiles_x))
        y0 = min(max(math.floor((my - ry) / tile_size), 0.0), float(tiles_y))
        y1 = min(max(math.ceil((my + ry) / tile_size), 0.0), float(tiles_y))
        boxes[g, 0], boxes[g, 1], boxes[g, 2], boxes[g, 3] = int(x0), int(x1), int(y0), int(y1)
        counts[g] = max(int(x1) - int(x0), 0) * max(int(y1) - int(y0), 0)


@nb.njit(cache=True)
def _depth_order(depth_bits, counts):
    """Indices of the Gaussians with tiles, nearest first and ties by index: an LSD radix sort (3 passes of 11
    bits) of ``depth_bits`` [M] int32, the bit patterns of the float32 depths, which for the positive depths of
    visible Gaussians sort like the floats. (numpy's sort of 64-bit (depth, index) keys, used before: 3.6 ms
    for 100k Gaussians against 0.6 ms.)"""
    n_visible = np.count_nonzero(counts > 0)
    order, key = np.empty(n_visible, np.int64), np.empty(n_visible, np.uint32)
    j = 0
    for g in range(depth_bits.shape[0]):
        if counts[g] > 0:
            order[j], key[j] = g, np.uint32(depth_bits[g])
            j += 1
    order_out, key_out = np.empty_like(order), np.empty_like(key)
    starts = np.empty(2048, np.int64)
    for shift in (0, 11, 22):
        starts[:] = 0
        for i in range(n_visible):
            starts[(key[i] >> shift) & 2047] += 1
        running = 0
        for b in range(2048):
            count = starts[b]
            starts[b] = running
            running += count
        for i in range(n_visible):  # stable scatter: equal digits keep their order, so ties stay by index
            b = (key[i] >> shift) & 2047
            order_out[starts[b]], key_out[starts[b]] = order[i], key[i]
            starts[b] += 1
        order, order_out = order_out, order
        key, key_out = key_out, key
    return order


@nb.njit(parallel=True, cache=True)
def _fill_tiles(order, boxes, gauss_offsets, n_per_cam, tiles_x, tiles_per_cam, tile_start, tile_gauss, gauss_isect):
    """Counting sort of the intersections into tiles, front to back within each tile.

    ``tile_start`` [n_tiles + 1] receives the tile offsets, ``tile_gauss`` [M] the
    Gaussian of each intersection, ``gauss_isect`` [M] (grouped per Gaussian by
    ``gauss_offsets``) the position of each of a Gaussian's intersections. The
    depth order is cut into chunks counted and scattered in parallel; a tile
    takes chunk 0's Gaussians first, then chunk 1's, ... so depth order holds.
    """
    n_tiles = tile_start.shape[0] - 1
    n_order = order.shape[0]
    n_chunks = min(max(n_order // _FILL_CHUNK, 1), 64)
    cursor = np.zeros((n_chunks, n_tiles), np.int64)
    for chunk in nb.prange(n_chunks):
        for i in range(chunk * n_order // n_chunks, (chunk + 1) * n_order // n_chunks):
            g = order[i]
            base = (g // n_per_cam) * tiles_per_cam
            for ty in range(boxes[g, 2], boxes[g, 3]):
                for tx in range(boxes[g, 0], boxes[g, 1]):
                    cursor[chunk, base + ty * tiles_x + tx] += 1
    running = 0
    for t in range(n_tiles):  # exclusive prefix sum, tile-major then chunk
        tile_start[t] = running
        for chunk in range(n_chunks):
            count = cursor[chunk, t]
            cursor[chunk, t] = running
            running += count
    tile_start[n_tiles] = running
    for chunk in nb.prange(n_chunks):
        for i in range(chunk * n_order // n_chunks, (chunk + 1) * n_order // n_chunks):
            g = order[i]
            base = (g // n_per_cam) * tiles_per_cam
            j = gauss_offsets[g]
            for ty in range(boxes[g, 2], boxes[g, 3]):
                for tx in range(boxes[g, 0], boxes[g, 1]):
                    t = base + ty * tiles_x + tx
                    pos = cursor[chunk, t]
                    cursor[chunk, t] = pos + 1
                    tile_gauss[pos] = g
                    gauss_isect[j] = pos
                    j += 1


@nb.njit(cache=True, inline="always")
def _tile_bounds(t, tiles_per_cam, tiles_x, tile_size, width, height):
    """Camera and pixels [x_lo, x_hi) x [y_lo, y_hi) of tile t (tiles camera-major, then row-major)."""
    cam = t // tiles_per_cam
    ty, tx = divmod(t - cam * tiles_per_cam, tiles_x)
    x_lo, y_lo = tx * tile_size, ty * tile_size
    return cam, x_lo, y_lo, min(x_lo + tile_size, width), min(y_lo + tile_size, height)


@nb.njit(parallel=True, cache=True)
def _pair_capacity(
    tile_start, tile_gauss, means2d, conics, limits, width, height, tile_size, tiles_x, tiles_per_cam, capacity
):
    """Upper bound of the pixel-Gaussian pairs each intersection can visit (its ellipse's box within the tile)."""
    for t in nb.prange(tile_start.shape[0] - 1):
        cam, x_lo, y_lo, x_hi, y_hi = _tile_bounds(t, tiles_per_cam, tiles_x, tile_size, width, height)
        for k in range(tile_start[t], tile_start[t + 1]):
            g = tile_gauss[k]
            a, b, c = conics[g, 0], conics[g, 1], conics[g, 2]
            r0, r1 = _row_range(a, b, c, limits[g], means2d[g, 1], y_lo, y_hi)
            a64, b64, c64 = np.float64(a), np.float64(b), np.float64(c)
            det = a64 * c64 - b64 * b64
            cols = x_hi - x_lo
            if det > 0.0 and a64 > 0.0:
                width_px = 2.0 * math.sqrt(2.0 * np.float64(limits[g]) * c64 / det) + 2.0 * _SPAN_EPS
                cols = min(cols, int(min(width_px, 1e9)) + 2)
            capacity[k] = max(r1 - r0, 0) * cols


@nb.njit(parallel=True, cache=True)
def _forward(
    tile_start,
    tile_gauss,
    means2d,
    conics,
    opacities,
    limits,
    colors,
    backgrounds,
    width,
    height,
    tile_size,
    tiles_x,
    tiles_per_cam,
    max_alpha,
    depths,
    out_color,
    out_trans,
    out_last,
    out_median,
    tile_pairs,
    cache_start,
    vis_cache,
    pair_start,
    tile_cached,
    spans,
    channels,
):
    """Front-to-back compositing, parallel over tiles; writes colour (+ T * background), T, n_contrib and the
    median depth (the depth of the Gaussian at which T first falls below 0.5, else 0).

    ``tile_pairs[t]`` receives the number of pixel-Gaussian pairs evaluated in tile t. For the
    backward, each visited pair's ``exp(-exponent)`` (0 where the pair does not count) goes to
    ``vis_cache`` from ``cache_start[tile_start[t]]`` on, intersection k's first one at
    ``pair_start[k]``; ``tile_cached[t]`` says whether the tile's pairs fitted; the columns [x0, x1) of each row
    it visits go to ``spans[k, row in tile]`` (relative to the tile). ``channels`` is ``tuple(range(D))`` for D
    colour channels: a tuple's length is part of its numba type, so each channel count gets its own compiled kernel
    whose per-pixel channel loop has a constant trip count (forward 14.6 -> 13.3 ns per pair, one thread, RGB).
    """
    n_ch = len(channels)
    for t in nb.prange(tile_start.shape[0] - 1):
        cam, x_lo, y_lo, x_hi, y_hi = _tile_bounds(t, tiles_per_cam, tiles_x, tile_size, width, height)
        tw = x_hi - x_lo
        n_pix = tw * (y_hi - y_lo)
        trans = np.ones(n_pix, np.float32)  # negated once the pixel has finished (T would fall below 1e-4)
        acc = np.zeros((n_pix, n_ch), np.float32)
        last = np.zeros(n_pix, np.int64)
        median = np.zeros(n_pix, np.float32)
        scratch = np.empty(tile_size, np.float32)
        alive = n_pix
        pairs = 0
        pos = cache_start[tile_start[t]]
        cache_end = cache_start[tile_start[t + 1]]
        cached = True
        for k in range(tile_start[t], tile_start[t + 1]):
            if alive == 0:
                break
            g = tile_gauss[k]
            mx, my = means2d[g, 0], means2d[g, 1]
            a, b, c = conics[g, 0], conics[g, 1], conics[g, 2]
            opac, limit, depth = opacities[g], limits[g], depths[g]
            r0, r1 = _row_range(a, b, c, limit, my, y_lo, y_hi)
            a64, b64, c64 = np.float64(a), np.float64(b), np.float64(c)  # (numba's float() keeps a float32)
            inv_a = 1.0 / a64 if a64 > 0.0 else 0.0
            recurrence = a64 > 0.0 and a64 * c64 - b64 * b64 > 0.0  # a positive-definite conic
            ratio_step = math.exp(-a64)
            pair_start[k] = pos
            for y in range(r0, r1):
                dy = my - (F32(y) + _HALF)
                x0, x1 = _row_span(a, inv_a, b, c, limit, dy, mx, x_lo, x_hi)
                x1 = max(x1, x0)
                spans[k, y - y_lo, 0] = x0 - x_lo
                spans[k, y - y_lo, 1] = x1 - x_lo
                pairs += x1 - x0
                if pos + (x1 - x0) > cache_end:
                    cached = False  # cannot happen with the capacity bound; the backward then recomputes
                row = vis_cache[pos : pos + (x1 - x0)] if cached else scratch[: x1 - x0]
                if cached:
                    pos += x1 - x0
                p0 = (y - y_lo) * tw - x_lo
                if recurrence:  # exp(-exponent) at (x0, y) and its ratio from x to x + 1 (both in float64); inside
                    # the span both stay within exp(+-limit), so the recurrence neither overflows nor underflows
                    dx0, dy64 = np.float64(mx) - (x0 + 0.5), np.float64(my) - (y + 0.5)
                    vis_next = math.exp(-(0.5 * (a64 * dx0 * dx0 + c64 * dy64 * dy64) + b64 * dx0 * dy64))
                    ratio = math.exp(a64 * dx0 + b64 * dy64 - 0.5 * a64)
                    for x in range(x0, x1):
                        vis = F32(vis_next)
                        vis_next *= ratio
                        ratio *= ratio_step
                        row[x - x0], alive = _composite(
                            trans, acc, last, median, p0 + x, vis, opac, max_alpha, colors, g, depth, k, alive, channels
                        )
                else:
                    for x in range(x0, x1):  # (a pair out of reach gets vis 0: alpha 0, nothing composited)
                        sigma = _exponent(a, b, c, mx - (F32(x) + _HALF), dy)
                        vis = F32(math.exp(-sigma)) if sigma >= _ZERO and sigma <= limit else _ZERO
                        row[x - x0], alive = _composite(
                            trans, acc, last, median, p0 + x, vis, opac, max_alpha, colors, g, depth, k, alive, channels
                        )
        tile_pairs[t] = pairs
        tile_cached[t] = cached
        for p in range(n_pix):
            py, px = divmod(p, tw)
            y, x = y_lo + py, x_lo + px
            t_p = abs(trans[p])
            for d in range(n_ch):
                out_color[cam, y, x, d] = acc[p, d] + t_p * backgrounds[cam, d]
            out_trans[cam, y, x] = t_p
            out_last[cam, y, x] = last[p]
            out_median[cam, y, x] = median[p] if t_p < _HALF else _ZERO


@nb.njit(cache=True, inline="always")
def _composite(trans, acc, last, median, p, vis, opac, max_alpha, colors, g, depth, k, alive, channels):
    """One pair of the forward: (the value the backward reads for it, alive pixels)."""
    t_p = trans[p]
    if t_p > _ZERO:
        alpha = min(max_alpha, opac * vis)
        if alpha >= _ALPHA_MIN:
            next_t = t_p * (_ONE - alpha)
            if next_t <= _T_MIN:
                trans[p] = -t_p
                return _ZERO, alive - 1
            weight = alpha * t_p
            for d in range(len(channels)):
                acc[p, d] += weight * colors[g, d]
            median[p] = depth if t_p >= _HALF else median[p]
            trans[p] = next_t
            last[p] = k + 1
            return vis, alive
    return _ZERO, alive


@nb.njit(parallel=True, cache=True, fastmath={"contract"})
def _backward(
    tile_start,
    tile_gauss,
    means2d,
    conics,
    opacities,
    limits,
    colors,
    backgrounds,
    width,
    height,
    tile_size,
    tiles_x,
    tiles_per_cam,
    max_alpha,
    final_trans,
    last_contrib,
    v_color,
    v_alpha,
    vis_cache,
    pair_start,
    tile_cached,
    spans,
    rows,
    channels,
):
    """Back-to-front gradients, parallel over tiles; one gradient row per intersection in ``rows``.

    Pairs read ``exp(-exponent)`` back from the forward's ``vis_cache`` and rows their columns from its
    ``spans`` (both recomputed where ``tile_cached`` is false). ``channels``: as in the forward, one compiled kernel
    per channel count.
    """
    n_ch = len(channels)
    for t in nb.prange(tile_start.shape[0] - 1):
        start, end = tile_start[t], tile_start[t + 1]
        if start == end:
            continue
        cam, x_lo, y_lo, x_hi, y_hi = _tile_bounds(t, tiles_per_cam, tiles_x, tile_size, width, height)
        tw = x_hi - x_lo
        n_pix = tw * (y_hi - y_lo)
        trans = np.empty(n_pix, np.float32)
        last = np.empty(n_pix, np.int64)
        v_c = np.empty((n_pix, n_ch), np.float32)
        tv_a = np.empty(n_pix, np.float32)  # T_final * (d loss / d alpha-image minus the background's share)
        behind = np.zeros(n_pix, np.float32)  # colour composited behind so far, dotted with the pixel's v_color
        v_col_g = np.empty(n_ch, np.float32)  # d loss / d colour of the current Gaussian
        scratch = np.empty(tile_size, np.float32)  # a row's exp values where the forward's did not fit its cache
        use_cache = tile_cached[t]
        max_last = start
        for p in range(n_pix):
            py, px = divmod(p, tw)
            y, x = y_lo + py, x_lo + px
            trans[p] = final_trans[cam, y, x]
            last[p] = last_contrib[cam, y, x]
            max_last = max(max_last, last[p])
            bg_dot = _ZERO
            for d in range(n_ch):
                v_c[p, d] = v_color[cam, y, x, d]
                bg_dot += backgrounds[cam, d] * v_c[p, d]
            tv_a[p] = trans[p] * (v_alpha[cam, y, x] - bg_dot)
        for k in range(max_last - 1, start - 1, -1):
            g = tile_gauss[k]
            mx, my = means2d[g, 0], means2d[g, 1]
            a, b, c = conics[g, 0], conics[g, 1], conics[g, 2]
            opac, limit = opacities[g], limits[g]
            g_o = s_xr = s_y = s_xy = s_yy = s_xx_tot = _ZERO  # sums over the tile of v_sigma times dx, dy, ...
            s_x = s_xx = row_s = _ZERO  # sums along the current row
            for d in range(n_ch):
                v_col_g[d] = _ZERO
            r0, r1 = _row_range(a, b, c, limit, my, y_lo, y_hi)
            inv_a = 1.0 / np.float64(a) if a > _ZERO else 0.0
            pos = pair_start[k]
            for y in range(r0, r1):
                dy = my - (F32(y) + _HALF)
                p0 = (y - y_lo) * tw - x_lo
                if use_cache:  # the forward's columns of this row (the same solve, not done twice)
                    x0, x1 = x_lo + np.int64(spans[k, y - y_lo, 0]), x_lo + np.int64(spans[k, y - y_lo, 1])
                    row = vis_cache[pos : pos + (x1 - x0)]
                    pos += x1 - x0
                else:  # solved again, exp(-exponent) where the pair counts (else 0) into a scratch row
                    x0, x1 = _row_span(a, inv_a, b, c, limit, dy, mx, x_lo, x_hi)
                    row = scratch[: x1 - x0]
                    for x in range(x0, x1):
                        sigma = _exponent(a, b, c, mx - (F32(x) + _HALF), dy)
                        row[x - x0] = math.exp(-sigma) if sigma >= _ZERO and sigma <= limit else _ZERO
                for x in range(x0, x1):  # back to front: the pixel's transmittance and colour behind, the sums
                    vis, p = row[x - x0], p0 + x
                    if vis == _ZERO or k >= last[p]:
                        continue
                    alpha = min(max_alpha, opac * vis)
                    if alpha < _ALPHA_MIN:
                        continue
                    ra = _ONE / (_ONE - alpha)
                    t_p = trans[p] * ra  # transmittance in front of this Gaussian
                    trans[p] = t_p
                    fac = alpha * t_p
                    v_alpha_p = ra * tv_a[p]
                    col_dot = _ZERO
                    for d in range(len(channels)):
                        vcol = v_c[p, d]
                        v_col_g[d] += fac * vcol
                        col_dot += colors[g, d] * vcol
                    v_alpha_p += col_dot * t_p - behind[p] * ra
                    behind[p] += col_dot * fac
                    if opac * vis <= max_alpha:
                        v_sigma = -opac * vis * v_alpha_p
                        dx = mx - (F32(x) + _HALF)
                        s_x += v_sigma * dx
                        s_xx += v_sigma * dx * dx
                        row_s += v_sigma
                        g_o += vis * v_alpha_p
                # fold the row's sums in, dy being constant along the row
                s_xr += s_x
                s_y += row_s * dy
                s_xy += s_x * dy
                s_yy += row_s * dy * dy
                s_xx_tot += s_xx
                s_x = s_xx = row_s = _ZERO
            for d in range(n_ch):
                rows[k, N_GRAD + d] = v_col_g[d]
            # d sigma / d (mean, conic) = (a dx + b dy, b dx + c dy, dx^2 / 2, dx dy, dy^2 / 2), summed
            rows[k, 0] = a * s_xr + b * s_y
            rows[k, 1] = b * s_xr + c * s_y
            rows[k, 2] = _HALF * s_xx_tot
            rows[k, 3] = s_xy
            rows[k, 4] = _HALF * s_yy
            rows[k, 5] = g_o
        for k in range(max_last, end):  # behind every pixel's last contributor: no gradient
            for j in range(rows.shape[1]):
                rows[k, j] = _ZERO


@nb.njit(parallel=True, cache=True)
def _sum_rows(gauss_offsets, gauss_isect, rows, out):
    """out[g] = sum of the gradient rows of Gaussian g's intersections (parallel over Gaussians)."""
    for g in nb.prange(out.shape[0]):
        for j in range(out.shape[1]):
            out[g, j] = _ZERO
        for i in range(gauss_offsets[g], gauss_offsets[g + 1]):
            k = gauss_isect[i]
            for j in range(out.shape[1]):
                out[g, j] += rows[k, j]


def bin_gaussians(
    means2d: np.ndarray,  # [C * N, 2] float32, camera-major
    radii: np.ndarray,  # [C * N, 2] float64, 0 = culled
    depths: np.ndarray,  # [C * N] float32
    n_cams: int,
    n_per_cam: int,
    width: int,
    height: int,
    tile_size: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Depth-sorted tile lists of every camera's visible Gaussians.

    Returns ``tile_start`` [C * tiles + 1] (tile t holds ``tile_gauss[tile_start[t]:tile_start[t + 1]]``,
    front to back; tiles camera-major then row-major), ``tile_gauss`` [M], and per Gaussian
    ``gauss_offsets`` [C * N + 1] into ``gauss_isect`` [M], the positions of its intersections.
    """
    tiles_x, tiles_y = math.ceil(width / tile_size), math.ceil(height / tile_size)
    n_total = means2d.shape[0]
    boxes = np.empty((n_total, 4), np.int64)
    counts = np.empty(n_total, np.int64)
    _tile_boxes(means2d, radii, tile_size, tiles_x, tiles_y, boxes, counts)
    gauss_offsets = np.zeros(n_total + 1, np.int64)
    np.cumsum(counts, out=gauss_offsets[1:])
    n_isect = int(gauss_offsets[-1])
    order = _depth_order(depths.view(np.int32), counts)
    tile_start = np.empty(n_cams * tiles_x * tiles_y + 1, np.int64)
    tile_start[0] = 0
    tile_gauss = np.empty(n_isect, np.int64)
    gauss_isect = np.empty(n_isect, np.int64)
    _fill_tiles(order, boxes, gauss_offsets, n_per_cam, tiles_x, tiles_x * tiles_y, tile_start, tile_gauss, gauss_isect)
    return tile_start, tile_gauss, gauss_offsets, gauss_isect


_FREE_CACHES: list[np.ndarray] = []  # exp caches of forwards whose autograd context has died, for reuse
_KEPT_CACHES = 2


def _exp_cache(ctx, size: int) -> np.ndarray:
    """A float32 buffer of ``size`` for a forward's exp cache, handed back for reuse when ``ctx`` dies: the
    smallest free one that fits, else a new one. (Tens of MB each call otherwise: mapped fresh, faulted in and
    zeroed by the kernel every call.)"""
    fits = [i for i, b in enumerate(_FREE_CACHES) if b.size >= size]
    if fits:
        buffer = _FREE_CACHES.pop(min(fits, key=lambda i: _FREE_CACHES[i].size))
    else:
        buffer = np.empty(max(size, 1), np.float32)
    weakref.finalize(ctx, _free_cache, buffer)
    return buffer[:size]


def _free_cache(buffer: np.ndarray) -> None:
    _FREE_CACHES.append(buffer)
    _FREE_CACHES.sort(key=lambda b: -b.size)
    del _FREE_CACHES[_KEPT_CACHES:]  # the largest: any smaller cache fits in them (a process keeps at most two)


def _numpy32(x: Tensor) -> np.ndarray:
    return np.ascontiguousarray(x.detach().to(torch.float32).cpu().numpy())


class _RasterizeCPU(torch.autograd.Function):
    """Composite projected Gaussians into images on the CPU (forward and backward: the numba kernels above):
    ``apply(means2d [C, N, 2], conics [C, N, 3], colors [C, N, D], opacities [C, N], radii [C, N, 2] (0 = culled),
    depths [C, N], width, height, tile_size, backgrounds [C, D] or None, max_alpha)``.

    Returns (colors [C, H, W, D], alphas [C, H, W, 1], stats [2] int64 = (tile-Gaussian
    intersections, pixel-Gaussian pairs evaluated by the forward pass), median depth [C, H, W, 1]
    (forward only: the ``depths`` value at which the transmittance first falls below 0.5, 0 where it never does)).
    """

    @staticmethod
    def forward(
        ctx, means2d, conics, colors, opacities, radii, depths, width, height, tile_size, backgrounds, max_alpha
    ):
        n_cams, n, n_ch = colors.shape
        tiles_x, tiles_y = math.ceil(width / tile_size), math.ceil(height / tile_size)
        tiles_per_cam = tiles_x * tiles_y
        m2d, con, col = (_numpy32(t).reshape(-1, t.shape[-1]) for t in (means2d, conics, colors))
        opa, dep = (_numpy32(t).reshape(-1) for t in (opacities, depths))
        rad = np.ascontiguousarray(radii.detach().cpu().numpy().astype(np.float64)).reshape(-1, 2)
        bgs = np.zeros((n_cams, n_ch), np.float32) if backgrounds is None else _numpy32(backgrounds)
        with np.errstate(divide="ignore"):  # alpha >= 1/255 <=> exponent <= ln(255 o); culled o <= 0 gives -inf
            limits = (np.log(np.float32(255.0) * np.maximum(opa, 0)) + _LOG_SLACK).astype(np.float32)

        tile_start, tile_gauss, gauss_offsets, gauss_isect = bin_gaussians(
            m2d, rad, dep, n_cams, n, width, height, tile_size
        )
        n_isect = tile_gauss.shape[0]

        out_color = torch.empty((n_cams, height, width, n_ch), dtype=torch.float32)
        out_trans = torch.empty((n_cams, height, width), dtype=torch.float32)
        out_median = torch.empty((n_cams, height, width, 1), dtype=torch.float32)
        last = np.empty((n_cams, height, width), np.int64)
        tile_pairs = np.empty(n_cams * tiles_per_cam, np.int64)
        capacity = np.empty(n_isect, np.int64)
        _pair_capacity(
            tile_start, tile_gauss, m2d, con, limits, width, height, tile_size, tiles_x, tiles_per_cam, capacity
        )
        cache_start = np.zeros(n_isect + 1, np.int64)
        np.cumsum(capacity, out=cache_start[1:])
        vis_cache = _exp_cache(ctx, int(cache_start[-1]))
        pair_start = np.zeros(n_isect, np.int64)
        tile_cached = np.empty(n_cams * tiles_per_cam, np.bool_)
        # each visited row's columns [x0, x1) within its tile, for the backward
        spans = np.empty((n_isect, tile_size, 2), np.uint8 if tile_size <= 255 else np.int64)
        image = (width, height, tile_size, tiles_x, tiles_per_cam)
        ctx.kernel_args = (tile_start, tile_gauss, m2d, con, opa, limits, col, bgs, *image, F32(max_alpha))
        outputs = (out_color.numpy(), out_trans.numpy(), last, out_median.numpy()[..., 0], tile_pairs)
        cache = (cache_start, vis_cache, pair_start, tile_cached, spans)
        with nb.parallel_chunksize(_TILE_CHUNK):
            _forward(*ctx.kernel_args, dep, *outputs, *cache, tuple(range(n_ch)))
        stats = torch.tensor([n_isect, int(tile_pairs.sum())], dtype=torch.int64)
        ctx.binning = (gauss_offsets, gauss_isect, last, cache)
        ctx.shapes = (n_cams, n, n_ch)
        ctx.has_background = backgrounds is not None
        ctx.save_for_backward(out_trans)
        ctx.mark_non_differentiable(stats, out_median)
        alphas = (1.0 - out_trans).unsqueeze(-1)
        return out_color, alphas, stats, out_median

    @staticmethod
    def backward(ctx, v_color, v_alphas, _v_stats, _v_median):
        (out_trans,) = ctx.saved_tensors
        gauss_offsets, gauss_isect, last, cache = ctx.binning
        n_cams, n, n_ch = ctx.shapes
        pixels = (out_trans.numpy(), last, _numpy32(v_color), _numpy32(v_alphas[..., 0]))
        rows = np.empty((gauss_isect.shape[0], N_GRAD + n_ch), np.float32)
        with nb.parallel_chunksize(_TILE_CHUNK):
            _backward(*ctx.kernel_args, *pixels, *cache[1:], rows, tuple(range(n_ch)))
        per_gauss = np.empty((n_cams * n, N_GRAD + n_ch), np.float32)
        _sum_rows(gauss_offsets, gauss_isect, rows, per_gauss)
        v = torch.from_numpy(per_gauss).reshape(n_cams, n, N_GRAD + n_ch)  # means2d, conics, opacities, colours
        v_backgrounds = None
        if ctx.has_background and ctx.needs_input_grad[9]:
            v_backgrounds = (v_color * out_trans.unsqueeze(-1)).sum(dim=(1, 2))
        return v[..., 0:2], v[..., 2:5], v[..., N_GRAD:], v[..., 5], None, None, None, None, None, v_backgrounds, None


rasterize_to_pixels_cpu = _RasterizeCPU.apply
