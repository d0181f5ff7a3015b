/* Fast path of physics_side.reference.PathSet.at: every agent's polyline at an arc length.
 *
 * The Python body spends ~40 us per call in ~20 small numpy calls whatever the agent
 * count; this loop does the same arithmetic per query, operation for operation, so its
 * results are bit-identical (tests/test_physics_pathkernel.py compares them):
 *
 * - the segment: numpy's searchsorted(key, clip(s, 0, total) + base, side="right") - 1,
 *   clamped to [first, last_seg], found by a binary search over the agent's own vertices
 *   only. The same since an agent's keys lie in [base, base + total] with total < _BIG,
 *   so the keys of every other agent fall entirely below or above the query. A NaN query
 *   sorts after every key in numpy, i.e. the agent's last segment.
 * - the expressions of PathSet.at with numpy's maximum / minimum (NaN propagates) and
 *   protocol.frames.wrap_pi with the same constants.
 *
 * Assumes finite paths (the wire decoder rejects anything else): with a NaN vertex the
 * Python search key is unsorted and numpy's result is undefined anyway.
 *
 * Plain CPython C API, no numpy headers: arrays come in through the buffer protocol and
 * the caller allocates the output.
 */

#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <float.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

#include "_numpy_arith.h" /* numpy's arithmetic: no FMA, its max / min, wrap_pi */

#define SEG_ROWS 15 /* reference._SEG_ROWS, the rows of PathSet._segment_table in its order */
enum { R_X0, R_Y0, R_DX, R_DY, R_C0, R_L, R_BS, R_BE, R_NEG_DS, R_DE, R_H, R_TWO_BS, R_TWO_BE, R_KS, R_KE };

/* ------------------------------------------------------------------ buffers */

#define MAX_NDIM 8
#define RELEASE_GIL_FROM 4096 /* queries per call */

typedef struct {
    Py_buffer v;
    int held;
} buf_t;

static void release(buf_t *b) {
    if (b->held) PyBuffer_Release(&b->v);
    b->held = 0;
}

/* A C-contiguous buffer of 8-byte items of `kind` ('f' float64, 'i' int64); strided
 * (any strides, e.g. np.broadcast_to) when `strided`. Raises and returns 0 otherwise. */
static int get(PyObject *obj, buf_t *b, const char *name, char kind, int writable, int strided) {
    const char *f;
    int flags = PyBUF_FORMAT | (strided ? PyBUF_STRIDES : PyBUF_C_CONTIGUOUS) | (writable ? PyBUF_WRITABLE : 0);
    b->held = 0;
    if (PyObject_GetBuffer(obj, &b->v, flags) < 0) {
        PyErr_Format(PyExc_TypeError, "%s: needs a%s%s array (got %.100s)", name, writable ? " writable" : "",
                     strided ? "" : " C-contiguous", Py_TYPE(obj)->tp_name);
        return 0;
    }
    b->held = 1;
    f = b->v.format ? b->v.format : "B";
    if (*f == '<' || *f == '=' || *f == '@') f++;
    if (b->v.itemsize != 8 || f[0] == '\0' || f[1] != '\0' ||
        (kind == 'f' ? f[0] != 'd' : (f[0] != 'q' && f[0] != 'l'))) {
        PyErr_Format(PyExc_TypeError, "%s: needs %s items (got format '%s', %zd bytes)", name,
                     kind == 'f' ? "float64" : "int64", b->v.format ? b->v.format : "B", b->v.itemsize);
        release(b);
        return 0;
    }
    if (b->v.ndim < 1 || b->v.ndim > MAX_NDIM) {
        PyErr_Format(PyExc_ValueError, "%s: needs 1 to %d dimensions (got %d)", name, MAX_NDIM, b->v.ndim);
        release(b);
        return 0;
    }
    return 1;
}

static int shape_is(buf_t *b, const char *name, int ndim, Py_ssize_t d0, Py_ssize_t d1) {
    if (b->v.ndim != ndim || b->v.shape[0] != d0 || (ndim > 1 && b->v.shape[1] != d1)) {
        if (ndim == 1)
            PyErr_Format(PyExc_ValueError, "%s: needs shape (%zd,)", name, d0);
        else
            PyErr_Format(PyExc_ValueError, "%s: needs shape (%zd, %zd)", name, d0, d1);
        return 0;
    }
    return 1;
}

/* ------------------------------------------------------------------ at */

typedef struct {
    const double *seg; /* (SEG_ROWS, m) */
    Py_ssize_t m;
    const double *key; /* (m + 1,): the vertices' arc lengths + their agent's base */
    const double *total, *base;
    const int64_t *first, *last_seg;
} paths_t;

/* One query of agent i: writes x, y, heading, curvature; 0 when the agent's segment range
 * is out of the table (no exception set: the caller raises, outside the GIL-free loop). */
static int at_one(const paths_t *p, Py_ssize_t i, double s, double *x, double *y, double *heading, double *kappa) {
    const int64_t first = p->first[i], last_seg = p->last_seg[i];
    int64_t j;
    const double *c;
    double t, tc, blend = 0.0, k = 0.0, L, bs, be, a;
    if (first < 0 || last_seg < first || last_seg >= p->m) return 0;
    if (s != s) {
        j = last_seg; /* numpy sorts NaN after every key */
    } else {
        /* the last of the vertices first .. last_seg with key <= q (first if none): a
         * branch-free binary search, as a query's segment is as good as random */
        const double q = np_min(np_max(s, 0.0), p->total[i]) + p->base[i];
        const double *keys = p->key + first;
        int64_t lo = 0, len = last_seg + 1 - first;
        while (len > 1) {
            const int64_t half = len / 2;
            lo += (keys[lo + half] <= q) ? half : 0;
            len -= half;
        }
        j = first + lo;
    }
    c = p->seg + j;
#define ROW(r) c[(Py_ssize_t)(r) * p->m]
    L = ROW(R_L);
    bs = ROW(R_BS);
    be = ROW(R_BE);
    t = s - ROW(R_C0); /* unclipped: extrapolates before 0 / past the end */
    tc = np_min(np_max(t, 0.0), L);
    if (tc < bs) {
        blend = ROW(R_NEG_DS) * (bs - tc) / ROW(R_TWO_BS);
        k = ROW(R_KS);
    } else if (tc > L - be) {
        blend = ROW(R_DE) * (tc - L + be) / ROW(R_TWO_BE);
        k = ROW(R_KE);
    }
    a = ROW(R_H) + blend;
    *x = ROW(R_X0) + ROW(R_DX) * t;
    *y = ROW(R_Y0) + ROW(R_DY) * t;
    *heading = wrap_pi(a);
    *kappa = k;
#undef ROW
    return 1;
}

static PyObject *py_at(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    buf_t seg, key, af, ai, s, out;
    paths_t p;
    Py_ssize_t n, m, rows = 1, count, idx[MAX_NDIM] = {0};
    int d, ok = 1, nd;
    PyObject *result = NULL;
    (void)self;
    seg.held = key.held = af.held = ai.held = s.held = out.held = 0;
    if (nargs != 6) {
        PyErr_SetString(PyExc_TypeError, "at(seg, key, agents_f, agents_i, s, out) takes 6 arguments");
        return NULL;
    }
    if (!get(args[0], &seg, "seg", 'f', 0, 0) || !get(args[1], &key, "key", 'f', 0, 0) ||
        !get(args[2], &af, "agents_f", 'f', 0, 0) || !get(args[3], &ai, "agents_i", 'i', 0, 0) ||
        !get(args[4], &s, "s", 'f', 0, 1) || !get(args[5], &out, "out", 'f', 1, 0))
        goto done;
    m = seg.v.shape[seg.v.ndim - 1];
    n = s.v.shape[s.v.ndim - 1];
    nd = s.v.ndim;
    if (!shape_is(&seg, "seg", 2, SEG_ROWS, m) || !shape_is(&key, "key", 1, m + 1, 0) ||
        !shape_is(&af, "agents_f (total, base)", 2, 2, n) || !shape_is(&ai, "agents_i (first, last_seg)", 2, 2, n))
        goto done;
    ok = out.v.ndim == nd + 1 && out.v.shape[0] == 4;
    for (d = 0; d < nd && ok; d++) ok = out.v.shape[d + 1] == s.v.shape[d];
    if (!ok) {
        PyErr_SetString(PyExc_ValueError, "out: needs shape (4, *s.shape)");
        goto done;
    }
    for (d = 0; d < nd - 1; d++) rows *= s.v.shape[d];
    count = rows * n;
    p.seg = (const double *)seg.v.buf;
    p.m = m;
    p.key = (const double *)key.v.buf;
    p.total = (const double *)af.v.buf;
    p.base = p.total + n;
    p.first = (const int64_t *)ai.v.buf;
    p.last_seg = p.first + n;
    {
        double *ox = (double *)out.v.buf, *oy = ox + count, *oh = oy + count, *oc = oh + count;
        const char *sb = (const char *)s.v.buf;
        const Py_ssize_t s_last = s.v.strides[nd - 1];
        Py_ssize_t r, i, q = 0;
        /* big batches let other threads run meanwhile; small ones would pay more than they save */
        PyThreadState *ts = count >= RELEASE_GIL_FROM ? PyEval_SaveThread() : NULL;
        for (r = 0; r < rows && ok; r++) {
            /* the leading dimensions' offset, from their index (an odometer over them) */
            Py_ssize_t off = 0;
            for (d = 0; d < nd - 1; d++) off += idx[d] * s.v.strides[d];
            for (i = 0; i < n; i++, q++) {
                double sv;
                memcpy(&sv, sb + off + i * s_last, sizeof sv);
                if (!at_one(&p, i, sv, ox + q, oy + q, oh + q, oc + q)) {
                    ok = 0;
                    break;
                }
            }
            for (d = nd - 2; d >= 0; d--) {
                if (++idx[d] < s.v.shape[d]) break;
                idx[d] = 0;
            }
        }
        if (ts) PyEval_RestoreThread(ts);
    }
    if (!ok) {
        PyErr_SetString(PyExc_ValueError, "agents_i: a segment range [first, last_seg] lies outside seg");
        goto done;
    }
    result = Py_None;
    Py_INCREF(result);
done:
    release(&seg);
    release(&key);
    release(&af);
    release(&ai);
    release(&s);
    release(&out);
    return result;
}

static PyMethodDef methods[] = {
    {"at", (PyCFunction)(void (*)(void))py_at, METH_FASTCALL,
     "at(seg, key, agents_f, agents_i, s, out) -> None: PathSet.at into out (4, *s.shape) = x, y, heading, "
     "curvature. seg: the (15, m) segment table; key: the (m + 1,) search key; agents_f: (2, n) total, base; "
     "agents_i: (2, n) int64 first, last_seg; s: float64 (..., n)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "physics_side._pathkernel",
    "C fast path of physics_side.reference.PathSet.at (bit-identical to its Python body).", -1, methods,
    NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__pathkernel(void) { return PyModule_Create(&module); }
