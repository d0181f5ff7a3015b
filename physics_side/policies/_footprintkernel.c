/* Fast paths of physics_side.policies.footprints: near_pairs, footprint_gap and gap_floor.
 *
 * The contact guard calls them once per SUMO step on ~1,000 discs and a few thousand
 * candidate pairs; their numpy bodies spend most of that time in ~100 small array
 * operations. These loops do the same arithmetic per element, operation for operation and
 * in numpy's order, so the results are bit-identical (tests/test_physics_footprintkernel.py
 * compares them):
 *
 * - footprint_gap: libm's cos / sin (numpy's on every build where FAST_FOOTPRINTS is set:
 *   footprints.py checks them against numpy's at import), numpy's maximum (NaN propagates).
 * - gap_floor: libm's hypot (numpy's np.hypot), the same constant 1 / sqrt(2).
 * - near_pairs: the same grid keys, a stable sort of them (numpy's argsort kind="stable" has
 *   one answer), each neighbour cell's range of the sorted keys (numpy's searchsorted, found
 *   by pointers that only move forward: the wanted key grows with the position) and the pairs
 *   emitted in the Python body's order: neighbour by neighbour, disc by disc in key order,
 *   then filtered by the same strict disc test. Inputs outside what the integer grid holds
 *   exactly (non-finite values, cells beyond 2^52, keys that would overflow int64) return
 *   None: the caller runs the Python body on them.
 *
 * Plain CPython C API, no numpy headers: arrays come in through the buffer protocol; the
 * caller allocates fixed-size outputs, near_pairs returns its pairs in a bytearray.
 */

#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <float.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

#include "sumoco_capi.h"  /* buffers in, module definition */
#include "../_numpy_arith.h" /* numpy's arithmetic: no FMA, its max / min, wrap_pi */

/* footprints.INV_SQRT2 = 1.0 / np.sqrt(2.0), as exact bits (the quotient rounds down: one ulp
 * below the nearest double to 1 / sqrt(2)) */
static const double INV_SQRT2 = 0x1.6a09e667f3bccp-1;
/* footprints.CELL_MIN_M [m] */
static const double CELL_MIN_M = 1e-3;
/* grid cells beyond this (in cells from 0) go to the Python body: below it a cell index is
 * an exact double and an int64 difference of two cannot overflow */
static const double MAX_CELL = 4503599627370496.0; /* 2^52 */
#define RELEASE_GIL_FROM 4096 /* pairs per call */

/* ------------------------------------------------------------------ buffers */

/* A 1-D C-contiguous float64 ('f') / int64 ('i') array of length `n` (any when n < 0). */
static int get(PyObject *obj, sc_buf *b, const char *name, char kind, int writable, Py_ssize_t n) {
    if (!sc_get(obj, b, name, kind, writable, 0)) return 0;
    if (!sc_ndim(b, name, 1)) goto fail;
    if (n >= 0 && b->v.shape[0] != n) {
        PyErr_Format(PyExc_ValueError, "%s: needs length %zd (got %zd)", name, n, b->v.shape[0]);
        goto fail;
    }
    return 1;
fail:
    sc_release(b);
    return 0;
}

#define F(b) ((const double *)(b).v.buf)
#define I(b) ((const int64_t *)(b).v.buf)

/* ------------------------------------------------------------------ footprint_gap */

static const char *GAP_NAMES[10] = {"ax", "ay", "ah", "al", "aw", "bx", "by", "bh", "bl", "bw"};

/* footprints._footprint_gap_python for one pair, expression by expression */
static inline double gap_one(double ax, double ay, double ah, double al, double aw, double bx, double by, double bh,
                             double bl, double bw) {
    const double ca = cos(ah), sa = sin(ah), cb = cos(bh), sb = sin(bh);
    const double dx = bx - ax, dy = by - ay;
    const double hal = 0.5 * al, haw = 0.5 * aw, hbl = 0.5 * bl, hbw = 0.5 * bw;
    const double axes[4][2] = {{ca, sa}, {-sa, ca}, {cb, sb}, {-sb, cb}};
    double gap = -INFINITY;
    int k;
    for (k = 0; k < 4; k++) {
        const double ux = axes[k][0], uy = axes[k][1];
        const double ra = hal * fabs(ca * ux + sa * uy) + haw * fabs(-sa * ux + ca * uy);
        const double rb = hbl * fabs(cb * ux + sb * uy) + hbw * fabs(-sb * ux + cb * uy);
        gap = np_max(gap, fabs(dx * ux + dy * uy) - ra - rb);
    }
    return gap;
}

static PyObject *py_footprint_gap(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    sc_buf in[10], out;
    Py_ssize_t m = -1, q;
    int k, ok = 1;
    PyObject *result = NULL;
    (void)self;
    for (k = 0; k < 10; k++) in[k].held = 0;
    out.held = 0;
    if (nargs != 11) {
        PyErr_SetString(PyExc_TypeError,
                        "footprint_gap(ax, ay, ah, al, aw, bx, by, bh, bl, bw, out) takes 11 arguments");
        return NULL;
    }
    for (k = 0; k < 10 && ok; k++) {
        ok = get(args[k], &in[k], GAP_NAMES[k], 'f', 0, m);
        if (ok) m = in[k].v.shape[0];
    }
    if (!ok || !get(args[10], &out, "out", 'f', 1, m)) goto done;
    {
        const double *ax = F(in[0]), *ay = F(in[1]), *ah = F(in[2]), *al = F(in[3]), *aw = F(in[4]);
        const double *bx = F(in[5]), *by = F(in[6]), *bh = F(in[7]), *bl = F(in[8]), *bw = F(in[9]);
        double *o = (double *)out.v.buf;
        /* big batches let other threads run meanwhile; small ones would pay more than they save */
        PyThreadState *ts = m >= RELEASE_GIL_FROM ? PyEval_SaveThread() : NULL;
        for (q = 0; q < m; q++)
            o[q] = gap_one(ax[q], ay[q], ah[q], al[q], aw[q], bx[q], by[q], bh[q], bl[q], bw[q]);
        if (ts) PyEval_RestoreThread(ts);
    }
    result = Py_None;
    Py_INCREF(result);
done:
    sc_release_all(in, 10);
    sc_release(&out);
    return result;
}

/* ------------------------------------------------------------------ gap_floor */

static PyObject *py_gap_floor(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    sc_buf x, y, i, j, hl, hd, out;
    Py_ssize_t n, m, q;
    PyObject *result = NULL;
    (void)self;
    x.held = y.held = i.held = j.held = hl.held = hd.held = out.held = 0;
    if (nargs != 7) {
        PyErr_SetString(PyExc_TypeError, "gap_floor(x, y, i, j, half_long, half_diag, out) takes 7 arguments");
        return NULL;
    }
    if (!get(args[0], &x, "x", 'f', 0, -1)) goto done;
    n = x.v.shape[0];
    if (!get(args[1], &y, "y", 'f', 0, n) || !get(args[2], &i, "i", 'i', 0, -1)) goto done;
    m = i.v.shape[0];
    if (!get(args[3], &j, "j", 'i', 0, m) || !get(args[4], &hl, "half_long", 'f', 0, n) ||
        !get(args[5], &hd, "half_diag", 'f', 0, n) || !get(args[6], &out, "out", 'f', 1, m))
        goto done;
    {
        const double *px = F(x), *py = F(y), *l = F(hl), *dg = F(hd);
        const int64_t *pi = I(i), *pj = I(j);
        double *o = (double *)out.v.buf;
        /* numpy's fancy indexing raises (or wraps a negative index): the caller's Python body does */
        for (q = 0; q < m; q++)
            if (pi[q] < 0 || pi[q] >= n || pj[q] < 0 || pj[q] >= n) break;
        if (q < m) {
            result = Py_False;
            Py_INCREF(result);
            goto done;
        }
        for (q = 0; q < m; q++) {
            const int64_t a = pi[q], b = pj[q];
            const double d = hypot(px[a] - px[b], py[a] - py[b]) * INV_SQRT2;
            o[q] = np_max(d - l[a] - dg[b], d - l[b] - dg[a]);
        }
    }
    result = Py_True;
    Py_INCREF(result);
done:
    SC_RELEASE(&x, &y, &i, &j, &hl, &hd, &out);
    return result;
}

/* ------------------------------------------------------------------ near_pairs */

/* footprints._NEIGHBOURS, in its order */
static const int NEIGHBOURS[5][2] = {{0, 0}, {0, 1}, {1, -1}, {1, 0}, {1, 1}};

/* Stable sort of idx[0..n) by key (ties keep their order): bottom-up merge sort. */
static void stable_argsort(const int64_t *key, int64_t *idx, int64_t *tmp, Py_ssize_t n) {
    Py_ssize_t w, lo, a, b, k, mid, hi;
    int64_t *src = idx, *dst = tmp;
    for (k = 0; k < n; k++) idx[k] = k;
    for (w = 1; w < n; w *= 2) {
        for (lo = 0; lo < n; lo += 2 * w) {
            mid = lo + w < n ? lo + w : n;
            hi = lo + 2 * w < n ? lo + 2 * w : n;
            a = lo;
            b = mid;
            k = lo;
            while (a < mid && b < hi) dst[k++] = key[src[b]] < key[src[a]] ? src[b++] : src[a++];
            while (a < mid) dst[k++] = src[a++];
            while (b < hi) dst[k++] = src[b++];
        }
        {
            int64_t *t = src;
            src = dst;
            dst = t;
        }
    }
    if (src != idx) memcpy(idx, src, (size_t)n * sizeof *idx);
}

typedef struct {
    int64_t *i, *j;
    Py_ssize_t len, cap;
} pairs_t;

static int push(pairs_t *p, int64_t a, int64_t b) {
    if (p->len == p->cap) {
        Py_ssize_t cap = p->cap ? 2 * p->cap : 1024;
        int64_t *i = PyMem_Realloc(p->i, (size_t)cap * sizeof *i), *j;
        if (!i) return 0;
        p->i = i;
        j = PyMem_Realloc(p->j, (size_t)cap * sizeof *j);
        if (!j) return 0;
        p->j = j;
        p->cap = cap;
    }
    /* np.minimum(i, j), np.maximum(i, j) */
    p->i[p->len] = a < b ? a : b;
    p->j[p->len] = a < b ? b : a;
    p->len++;
    return 1;
}

/* The grid of cell width `cell` over the n discs: key per disc and the row count; 0 when a
 * cell index or a key would leave what int64 / double hold exactly (the Python body runs). */
static int grid_keys(const double *x, const double *y, Py_ssize_t n, double cell, int64_t *key, int64_t *rows_out) {
    double gxmin = INFINITY, gymin = INFINITY, gxmax = -INFINITY, gymax = -INFINITY;
    int64_t gx0, gy0, rows, span;
    Py_ssize_t k;
    for (k = 0; k < n; k++) {
        const double gx = floor(x[k] / cell), gy = floor(y[k] / cell);
        if (!(fabs(gx) <= MAX_CELL && fabs(gy) <= MAX_CELL)) return 0; /* NaN too */
        if (gx < gxmin) gxmin = gx;
        if (gx > gxmax) gxmax = gx;
        if (gy < gymin) gymin = gy;
        if (gy > gymax) gymax = gy;
    }
    gx0 = (int64_t)gxmin;
    gy0 = (int64_t)gymin;
    rows = (int64_t)gymax - gy0 + 3; /* gy -= gy.min() - 1; rows = gy.max() + 2 */
    span = (int64_t)gxmax - gx0;      /* gx -= gx.min(): the largest gx */
    /* the largest key, span * rows + rows - 1 (+ a neighbour's rows + 1), stays below 2^62 */
    if (span >= ((int64_t)1 << 62) / rows - 2) return 0;
    for (k = 0; k < n; k++)
        key[k] = ((int64_t)floor(x[k] / cell) - gx0) * rows + ((int64_t)floor(y[k] / cell) - (gy0 - 1));
    *rows_out = rows;
    return 1;
}

static PyObject *py_near_pairs(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    sc_buf bx, by, br;
    Py_ssize_t n, k;
    int64_t *key = NULL, *order = NULL, *ks = NULL, rows = 0;
    pairs_t p = {NULL, NULL, 0, 0};
    PyObject *result = NULL;
    (void)self;
    bx.held = by.held = br.held = 0;
    if (nargs != 3) {
        PyErr_SetString(PyExc_TypeError, "near_pairs(x, y, r) takes 3 arguments");
        return NULL;
    }
    if (!get(args[0], &bx, "x", 'f', 0, -1)) goto done;
    n = bx.v.shape[0];
    if (!get(args[1], &by, "y", 'f', 0, n) || !get(args[2], &br, "r", 'f', 0, n)) goto done;
    if (n >= 2) {
        const double *x = F(bx), *y = F(by), *r = F(br);
        double rmax = -INFINITY, cell;
        for (k = 0; k < n; k++) {
            if (!isfinite(r[k])) break;
            if (r[k] > rmax) rmax = r[k];
        }
        if (k < n) goto fallback; /* r.max() with a NaN or an infinite cell */
        /* max(2.0 * float(r.max()), CELL_MIN_M): Python's max keeps the first unless the second is larger */
        cell = 2.0 * rmax;
        if (CELL_MIN_M > cell) cell = CELL_MIN_M;
        key = PyMem_Malloc((size_t)n * sizeof *key);
        order = PyMem_Malloc((size_t)n * sizeof *order);
        ks = PyMem_Malloc((size_t)n * sizeof *ks);
        if (!key || !order || !ks) {
            PyErr_NoMemory();
            goto done;
        }
        if (!grid_keys(x, y, n, cell, key, &rows)) goto fallback;
        stable_argsort(key, order, ks, n); /* ks: scratch of the sort, then the sorted keys */
        for (k = 0; k < n; k++) ks[k] = key[order[k]];
        for (int d = 0; d < 5; d++) {
            const int64_t shift = NEIGHBOURS[d][0] * rows + NEIGHBOURS[d][1];
            Py_ssize_t lo = 0, hi = 0, pos;
            for (pos = 0; pos < n; pos++) {
                const int64_t want = ks[pos] + shift;
                Py_ssize_t b, first;
                /* searchsorted(ks, want, "left") and "right": want grows with pos */
                while (lo < n && ks[lo] < want) lo++;
                if (hi < lo) hi = lo;
                while (hi < n && ks[hi] <= want) hi++;
                first = (d == 0 && lo < pos + 1) ? pos + 1 : lo; /* its own cell: the discs after it */
                for (b = first; b < hi; b++) {
                    const int64_t i = order[pos], j = order[b];
                    if (hypot(x[i] - x[j], y[i] - y[j]) < r[i] + r[j] && !push(&p, i, j)) {
                        PyErr_NoMemory();
                        goto done;
                    }
                }
            }
        }
    }
    /* the pairs as int64 i[0..m) then j[0..m) */
    result = PyByteArray_FromStringAndSize(NULL, (Py_ssize_t)(2 * p.len * sizeof(int64_t)));
    if (result && p.len) {
        char *o = PyByteArray_AS_STRING(result);
        memcpy(o, p.i, (size_t)p.len * sizeof(int64_t));
        memcpy(o + p.len * sizeof(int64_t), p.j, (size_t)p.len * sizeof(int64_t));
    }
    goto done;
fallback:
    result = Py_None;
    Py_INCREF(result);
done:
    PyMem_Free(key);
    PyMem_Free(order);
    PyMem_Free(ks);
    PyMem_Free(p.i);
    PyMem_Free(p.j);
    SC_RELEASE(&bx, &by, &br);
    return result;
}

/* ------------------------------------------------------------------ libm probes */

/* libm's cos and sin of x into out (2, n): footprints.py compares them with numpy's at import. */
static PyObject *py_cos_sin(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    sc_buf x, out;
    Py_ssize_t n, k;
    PyObject *result = NULL;
    (void)self;
    x.held = out.held = 0;
    if (nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "cos_sin(x, out) takes 2 arguments");
        return NULL;
    }
    if (!get(args[0], &x, "x", 'f', 0, -1)) goto done;
    n = x.v.shape[0];
    if (!get(args[1], &out, "out", 'f', 1, 2 * n)) goto done;
    for (k = 0; k < n; k++) {
        ((double *)out.v.buf)[k] = cos(F(x)[k]);
        ((double *)out.v.buf)[n + k] = sin(F(x)[k]);
    }
    result = Py_None;
    Py_INCREF(result);
done:
    SC_RELEASE(&x, &out);
    return result;
}

static PyMethodDef methods[] = {
    {"near_pairs", (PyCFunction)(void (*)(void))py_near_pairs, METH_FASTCALL,
     "near_pairs(x, y, r) -> bytearray | None: footprints.near_pairs' pairs as int64 i[0..m) then j[0..m), "
     "or None where the Python body must run (non-finite input, a grid beyond int64). x, y, r: float64 (n,)."},
    {"footprint_gap", (PyCFunction)(void (*)(void))py_footprint_gap, METH_FASTCALL,
     "footprint_gap(ax, ay, ah, al, aw, bx, by, bh, bl, bw, out) -> None: footprints.footprint_gap into out. "
     "Every argument float64 (m,)."},
    {"gap_floor", (PyCFunction)(void (*)(void))py_gap_floor, METH_FASTCALL,
     "gap_floor(x, y, i, j, half_long, half_diag, out) -> bool: footprints.gap_floor into out; False (out "
     "unwritten) when an index lies outside [0, n). x, y, half_long, half_diag: float64 (n,); i, j: int64 "
     "(m,); out: float64 (m,)."},
    {"cos_sin", (PyCFunction)(void (*)(void))py_cos_sin, METH_FASTCALL,
     "cos_sin(x, out) -> None: libm's cos(x), sin(x) into out (2 n,). x: float64 (n,)."},
    {NULL, NULL, 0, NULL},
};

SC_MODULE(PyInit__footprintkernel, "physics_side.policies._footprintkernel",
          "C fast paths of physics_side.policies.footprints (bit-identical to its Python bodies).", methods)
