/* Fast paths of physics_side.reference: PathSet.at (every agent's polyline at an arc
 * length), Reference.at / at_and_project (`reference`: the speed profile, the path there,
 * the sample's offset and drift, and the projection of the measured bumper, per agent),
 * Reference.point_at (`point_at`: the path shifted by that offset and drift), and
 * per SUMO step PathSet's tables (`build`) and PathSet.dedup.
 *
 * The Python bodies spend ~40 us (PathSet.at) and ~80 us (at_and_project) per call in small
 * numpy calls whatever the agent count; these loops do the same arithmetic per agent,
 * operation for operation, so their results are bit-identical
 * (tests/test_physics_pathkernel.py, tests/test_physics_referencekernel.py compare them):
 *
 * - the segment: numpy's searchsorted(key, clip(s, 0, total) + base, side="right") - 1,
 *   clamped to [first, last_seg], found by a binary search over the agent's own vertices
 *   only. The same since an agent's keys lie in [base, base + total] with total < _BIG,
 *   so the keys of every other agent fall entirely below or above the query. A NaN query
 *   sorts after every key in numpy, i.e. the agent's last segment.
 * - the expressions of PathSet.at with numpy's maximum / minimum (NaN propagates) and
 *   protocol.frames.wrap_pi with the same constants.
 *
 * - Reference: the expressions of Reference._profile, _shift and _project and of
 *   stopping_distance, with np.clip's comparisons; its scalars (u = tau / L, (1 - u) ** 2)
 *   come from the Python wrapper. cos / sin are libm's (gcc merges them into sincos, which
 *   glibc computes with the same code): the wrapper runs it only where numpy's are the same
 *   bits (runtime.native.numpy_math_is_libm).
 *
 * - build / dedup: the numpy bodies' expressions per segment (hypot, atan2 from libm, under
 *   the same condition), numpy's cumsum as the sequential sum it is.
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

#include "sumoco_capi.h"  /* buffers in, module definition */
#include "_numpy_arith.h" /* numpy's arithmetic: no FMA, its max / min, wrap_pi */

#define SEG_ROWS 15 /* reference._SEG_ROWS, the rows of PathSet._segment_table in its order */
enum { R_X0, R_Y0, R_DX, R_DY, R_C0, R_L, R_BS, R_BE, R_NEG_DS, R_DE, R_H, R_TWO_BS, R_TWO_BE, R_KS, R_KE };

/* ------------------------------------------------------------------ buffers */

#define MAX_NDIM 8
#define RELEASE_GIL_FROM 4096 /* queries per call */

/* A buffer of float64 ('f') / int64 ('i') items, C-contiguous unless `strided`, of 1 to
 * MAX_NDIM dimensions. Raises and returns 0 otherwise. */
static int get(PyObject *obj, sc_buf *b, const char *name, char kind, int writable, int strided) {
    if (!sc_get(obj, b, name, kind, writable, strided)) return 0;
    if (b->v.ndim < 1 || b->v.ndim > MAX_NDIM) {
        PyErr_Format(PyExc_ValueError, "%s: needs 1 to %d dimensions (got %d)", name, MAX_NDIM, b->v.ndim);
        sc_release(b);
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

/* PathSet's tables, the first four arguments of at / reference / point_at (seg, key,
 * agents_f, agents_i), into b[0..4). */
static int get_paths(PyObject *const *args, sc_buf *b) {
    return get(args[0], &b[0], "seg", 'f', 0, 0) && get(args[1], &b[1], "key", 'f', 0, 0) &&
           get(args[2], &b[2], "agents_f", 'f', 0, 0) && get(args[3], &b[3], "agents_i", 'i', 0, 0);
}

/* get_paths' tables as paths_t, their shapes checked for n agents */
static int paths_of(const sc_buf *b, Py_ssize_t n, paths_t *p) {
    const Py_ssize_t m = b[0].v.shape[b[0].v.ndim - 1];
    if (!sc_shape(&b[0], "seg", 2, SEG_ROWS, m) || !sc_shape(&b[1], "key", 1, m + 1, 0) ||
        !sc_shape(&b[2], "agents_f (total, base)", 2, 2, n) || !sc_shape(&b[3], "agents_i (first, last_seg)", 2, 2, n))
        return 0;
    p->seg = (const double *)b[0].v.buf;
    p->m = m;
    p->key = (const double *)b[1].v.buf;
    p->total = (const double *)b[2].v.buf;
    p->base = p->total + n;
    p->first = (const int64_t *)b[3].v.buf;
    p->last_seg = p->first + n;
    return 1;
}

/* The result of a loop over the agents' paths: None, or the error of a segment range
 * outside seg (at_one failed) */
static PyObject *paths_result(int ok) {
    if (ok) Py_RETURN_NONE;
    PyErr_SetString(PyExc_ValueError, "agents_i: a segment range [first, last_seg] lies outside seg");
    return NULL;
}

static PyObject *py_at(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    sc_buf pb[4] = {{{0}}}, s = {0}, out = {0};
    paths_t p;
    Py_ssize_t n, rows = 1, count, idx[MAX_NDIM] = {0};
    int d, ok = 1, nd;
    PyObject *result = NULL;
    (void)self;
    if (nargs != 6) {
        PyErr_SetString(PyExc_TypeError, "at(seg, key, agents_f, agents_i, s, out) takes 6 arguments");
        return NULL;
    }
    if (!get_paths(args, pb) || !get(args[4], &s, "s", 'f', 0, 1) || !get(args[5], &out, "out", 'f', 1, 0))
        goto done;
    n = s.v.shape[s.v.ndim - 1];
    nd = s.v.ndim;
    if (!paths_of(pb, n, &p)) goto done;
    ok = out.v.ndim == nd + 1 && out.v.shape[0] == 4;
    for (d = 0; d < nd && ok; d++) ok = out.v.shape[d + 1] == s.v.shape[d];
    if (!ok) {
        PyErr_SetString(PyExc_ValueError, "out: needs shape (4, *s.shape)");
        goto done;
    }
    for (d = 0; d < nd - 1; d++) rows *= s.v.shape[d];
    count = rows * n;
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
    result = paths_result(ok);
done:
    sc_release_all(pb, 4);
    SC_RELEASE(&s, &out);
    return result;
}

/* ------------------------------------------------------------------ reference */

/* Rows of Reference._c_state (per agent), in its order */
enum { S_SPEED, S_ACCEL, S_OFF_LON, S_OFF_LAT, S_DYAW, S_SIDE_RATE, S_SIDE_CAP, S_INTERP, S_S_END, S_V0, S_V1,
       S_A_END, STATE_ROWS };
/* Rows of the output: Reference.at's ReferencePoint, then project's s, lateral offset and PathPoint */
enum { O_X, O_Y, O_YAW, O_V, O_A, O_KAPPA, O_S, O_TANGENT, AT_ROWS, O_PS = AT_ROWS, O_LAT, O_PX, O_PY, O_PH, O_PK,
       PROJECT_ROWS };
/* Reference._profile's cases: extrapolated from the sample; interpolated with tau <= L (the
 * cubic); interpolated with tau > L (extrapolated from the next sample) */
enum { MODE_EXTRAPOLATE, MODE_CUBIC, MODE_PAST_END };

/* np.clip(x, lo, hi) on float64 (numpy's clip loop): min(max(x, lo), hi) where a NaN first
 * argument is the result, a NaN bound passes through and of two equal values the second wins */
static inline double clip_max(double a, double b) { return (a != a) ? a : (a > b ? a : b); }
static inline double clip_min(double a, double b) { return (a != a) ? a : (a < b ? a : b); }

/* reference.stopping_distance for one agent: the same expressions in the same order */
static inline void stopping(double v, double a, double tau, double *s, double *vt) {
    double w = v + a * tau;
    double d = v * tau + 0.5 * a * tau * tau;
    if (w < 0.0) {
        d = (a < 0) ? v * v / (-2.0 * a) : 0.0;
        w = 0.0;
    }
    *s = d;
    *vt = w;
}

typedef struct {
    int mode, drift;
    double tau, tau_l, L, u, c2;
    /* the cubic's factors in u, each computed as the Python body computes it (scalars first) */
    double c1, c3, d1, d2, d3, e1, e2, e3;
} profile_t;

/* Reference._profile for agent i: arc length, speed, acceleration */
static inline void profile_one(const profile_t *f, const double *st, Py_ssize_t n, Py_ssize_t i, double *s, double *v,
                               double *a) {
#define ST(r) st[(Py_ssize_t)(r) * n + i]
    const double spd = ST(S_SPEED), acc = ST(S_ACCEL);
    double sx, vx, ax, si, vi, ai;
    if (f->mode == MODE_EXTRAPOLATE) {
        stopping(spd, acc, f->tau, s, v);
        *a = *v > 0.0 ? acc : 0.0;
        return;
    }
    stopping(spd, acc, f->tau_l, &sx, &vx); /* its own sample is L later */
    ax = vx > 0.0 ? acc : 0.0;
    {
        const double S = ST(S_S_END), v0 = ST(S_V0), v1 = ST(S_V1), u = f->u, L = f->L;
        if (f->mode == MODE_CUBIC) {
            si = S * f->c1 * u * u + L * (v0 * f->c2 * u + v1 * f->c3 * u * u);
            vi = S * 6.0 * u * f->d1 / L + v0 * f->d1 * f->d2 + v1 * u * f->d3;
            ai = (S * f->e1 / L + v0 * f->e2 + v1 * f->e3) / L;
            vi = np_max(vi, 0.0);
        } else {
            const double a_end = ST(S_A_END);
            double s2;
            stopping(v1, a_end, f->tau_l, &s2, &vi);
            si = S + s2;
            ai = vi > 0.0 ? a_end : 0.0;
        }
    }
    if (ST(S_INTERP) != 0.0) {
        *s = si;
        *v = vi;
        *a = ai;
    } else {
        *s = sx;
        *v = vx;
        *a = ax;
    }
#undef ST
}

/* Reference._shift's sideways offset of agent i (state S, n agents) tau [s] past its
 * sample: the sample's offset from its path plus, with `drift`, the capped drift since */
static inline double shift_lat(const double *S, Py_ssize_t n, Py_ssize_t i, int drift, double tau) {
    const double lat = S[S_OFF_LAT * n + i];
    if (!drift) return lat;
    return lat + clip_min(clip_max(S[S_SIDE_RATE * n + i] * tau, -S[S_SIDE_CAP * n + i]), S[S_SIDE_CAP * n + i]);
}

/* the path point (x, y) moved by the offsets lon, lat [m] in the path's frame there (cos c, sin sn) */
static inline void shift_xy(double x, double y, double c, double sn, double lon, double lat, double *ox, double *oy) {
    *ox = x + (lon * c - lat * sn);
    *oy = y + (lon * sn + lat * c);
}

static int as_double(PyObject *o, const char *name, double *v) {
    *v = PyFloat_AsDouble(o);
    if (*v == -1.0 && PyErr_Occurred()) {
        PyErr_Clear();
        PyErr_Format(PyExc_TypeError, "%s: needs a float (got %.100s)", name, Py_TYPE(o)->tp_name);
        return 0;
    }
    return 1;
}

static PyObject *py_reference(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    sc_buf pb[4] = {{{0}}}, st = {0}, sg = {0}, bx = {0}, by = {0}, out = {0};
    paths_t p;
    profile_t f;
    Py_ssize_t n, i;
    long mode;
    int project, ok = 1;
    PyObject *result = NULL;
    (void)self;
    if (nargs != 16) {
        PyErr_SetString(PyExc_TypeError, "reference(seg, key, agents_f, agents_i, state, mode, drift, tau, tau_l, L, "
                                         "u, c2, s_guess, px, py, out) takes 16 arguments");
        return NULL;
    }
    if (!get_paths(args, pb) || !get(args[4], &st, "state", 'f', 0, 0) || !get(args[15], &out, "out", 'f', 1, 0))
        goto done;
    mode = PyLong_AsLong(args[5]);
    if (mode == -1 && PyErr_Occurred()) goto done;
    if (mode < MODE_EXTRAPOLATE || mode > MODE_PAST_END) {
        PyErr_SetString(PyExc_ValueError, "mode: needs 0 (extrapolate), 1 (cubic) or 2 (past the end)");
        goto done;
    }
    f.mode = (int)mode;
    f.drift = PyObject_IsTrue(args[6]);
    if (f.drift < 0 || !as_double(args[7], "tau", &f.tau) || !as_double(args[8], "tau_l", &f.tau_l) ||
        !as_double(args[9], "L", &f.L) || !as_double(args[10], "u", &f.u) || !as_double(args[11], "c2", &f.c2))
        goto done;
    /* Reference._profile's scalar factors (3.0 - 2.0 * u, u - 1.0, ...), as Python rounds them */
    f.c1 = 3.0 - 2.0 * f.u;
    f.c3 = f.u - 1.0;
    f.d1 = 1.0 - f.u;
    f.d2 = 1.0 - 3.0 * f.u;
    f.d3 = 3.0 * f.u - 2.0;
    f.e1 = 6.0 - 12.0 * f.u;
    f.e2 = 6.0 * f.u - 4.0;
    f.e3 = 6.0 * f.u - 2.0;
    n = st.v.shape[st.v.ndim - 1];
    project = args[12] != Py_None;
    if (!paths_of(pb, n, &p) || !sc_shape(&st, "state", 2, STATE_ROWS, n) ||
        !sc_shape(&out, "out", 2, project ? PROJECT_ROWS : AT_ROWS, n))
        goto done;
    if (project && (!get(args[12], &sg, "s_guess", 'f', 0, 0) || !get(args[13], &bx, "px", 'f', 0, 0) ||
                    !get(args[14], &by, "py", 'f', 0, 0) || !sc_shape(&sg, "s_guess", 1, n, 0) ||
                    !sc_shape(&bx, "px", 1, n, 0) || !sc_shape(&by, "py", 1, n, 0)))
        goto done;
    {
        const double *S = (const double *)st.v.buf;
        const double *gs = project ? (const double *)sg.v.buf : NULL;
        const double *qx = project ? (const double *)bx.v.buf : NULL, *qy = project ? (const double *)by.v.buf : NULL;
        double *o = (double *)out.v.buf;
#define OUT(r) o[(Py_ssize_t)(r) * n + i]
#define ST(r) S[(Py_ssize_t)(r) * n + i]
        for (i = 0; i < n; i++) {
            double s, v, a, x, y, h, k, lat, c, sn;
            profile_one(&f, S, n, i, &s, &v, &a);
            if (!at_one(&p, i, s, &x, &y, &h, &k)) {
                ok = 0;
                break;
            }
            /* Reference._shift: the sample's offset from its path plus the drift since, in the
             * path's frame at the point */
            lat = shift_lat(S, n, i, f.drift, f.tau);
            c = cos(h);
            sn = sin(h);
            shift_xy(x, y, c, sn, ST(S_OFF_LON), lat, &OUT(O_X), &OUT(O_Y));
            OUT(O_YAW) = wrap_pi(h + ST(S_DYAW));
            OUT(O_V) = v;
            OUT(O_A) = a;
            OUT(O_KAPPA) = k;
            OUT(O_S) = s;
            OUT(O_TANGENT) = h;
            if (project) {
                /* Reference._project at the shifted path point of s_guess */
                const double g = gs[i];
                double gx, gy, dx, dy, ds;
                if (!at_one(&p, i, g, &x, &y, &h, &k)) {
                    ok = 0;
                    break;
                }
                c = cos(h);
                sn = sin(h);
                shift_xy(x, y, c, sn, ST(S_OFF_LON), lat, &gx, &gy);
                dx = qx[i] - gx;
                dy = qy[i] - gy;
                ds = dx * c + dy * sn;
                OUT(O_PS) = g + ds;
                OUT(O_LAT) = -dx * sn + dy * c;
                OUT(O_PX) = gx + ds * c;
                OUT(O_PY) = gy + ds * sn;
                OUT(O_PH) = wrap_pi(h + k * ds);
                OUT(O_PK) = k;
            }
        }
#undef OUT
#undef ST
    }
    result = paths_result(ok);
done:
    sc_release_all(pb, 4);
    SC_RELEASE(&st, &sg, &bx, &by, &out);
    return result;
}

/* Reference.point_at(s, tau) for s of shape (n,): the path at s shifted by the sample's
 * offset and drift (Reference._shift) into out (4, n) = x, y, heading, curvature. */
static PyObject *py_point_at(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    sc_buf pb[4] = {{{0}}}, st = {0}, sb = {0}, out = {0};
    paths_t p;
    Py_ssize_t n, i;
    int drift, ok = 1;
    double tau;
    PyObject *result = NULL;
    (void)self;
    if (nargs != 9) {
        PyErr_SetString(PyExc_TypeError, "point_at(seg, key, agents_f, agents_i, state, drift, tau, s, out) takes 9 "
                                         "arguments");
        return NULL;
    }
    if (!get_paths(args, pb) || !get(args[4], &st, "state", 'f', 0, 0) || !get(args[7], &sb, "s", 'f', 0, 0) ||
        !get(args[8], &out, "out", 'f', 1, 0))
        goto done;
    drift = PyObject_IsTrue(args[5]);
    if (drift < 0 || !as_double(args[6], "tau", &tau)) goto done;
    n = st.v.shape[st.v.ndim - 1];
    if (!paths_of(pb, n, &p) || !sc_shape(&st, "state", 2, STATE_ROWS, n) || !sc_shape(&sb, "s", 1, n, 0) ||
        !sc_shape(&out, "out", 2, 4, n))
        goto done;
    {
        const double *S = (const double *)st.v.buf, *q = (const double *)sb.v.buf;
        double *o = (double *)out.v.buf;
#define ST(r) S[(Py_ssize_t)(r) * n + i]
        for (i = 0; i < n; i++) {
            double x, y, h, k, lat, c, sn;
            if (!at_one(&p, i, q[i], &x, &y, &h, &k)) {
                ok = 0;
                break;
            }
            lat = shift_lat(S, n, i, drift, tau);
            c = cos(h);
            sn = sin(h);
            shift_xy(x, y, c, sn, ST(S_OFF_LON), lat, &o[i], &o[n + i]);
            o[2 * n + i] = h;
            o[3 * n + i] = k;
        }
#undef ST
    }
    result = paths_result(ok);
done:
    sc_release_all(pb, 4);
    SC_RELEASE(&st, &sb, &out);
    return result;
}

/* ------------------------------------------------------------------ PathSet construction */

/* reference's constants, as exact doubles */
static const double MIN_SEG_M = 1e-9;     /* [m] segment lengths divide as at least this */
static const double AGENT_GAP_M = 1.0e6;  /* [m] reference._BIG, the search key's gap between agents */
static const double BLEND_M = 3.5;        /* [m] */
static const double FINE_SEG_M = 4.0;     /* [m] */
static const double SAMPLING_RATIO = 1.5; /* [1] */

/* Are the offsets what PathSet reads: from 0 to the vertex count, >= 2 vertices each? */
static int offsets_ok(const int64_t *off, Py_ssize_t n, Py_ssize_t count, int min_each) {
    Py_ssize_t a;
    if (off[0] != 0 || off[n] != count) return 0;
    for (a = 0; a < n; a++)
        if (off[a + 1] - off[a] < min_each) return 0;
    return 1;
}

/* PathSet.__init__ (_measure, _vertex_turns, _continue_sampled_ends, _segment_table) into
 * seg (SEG_ROWS, m), cum and key (m + 1,), turn (m,) and agents_f (2, n) = total, base; the
 * same expressions in numpy's order. Returns False (nothing written) when the offsets are
 * not 0 .. len(xy) with >= 2 vertices each: the Python body then runs (and raises). */
static PyObject *py_build(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    sc_buf ob, xb, sb, cb, kb, tb, ab;
    Py_ssize_t n, M, m, j, a;
    PyObject *result = NULL;
    double *raw = NULL;
    (void)self;
    ob.held = xb.held = sb.held = cb.held = kb.held = tb.held = ab.held = 0;
    if (nargs != 7) {
        PyErr_SetString(PyExc_TypeError, "build(offsets, xy, seg, cum, key, turn, agents_f) takes 7 arguments");
        return NULL;
    }
    if (!get(args[0], &ob, "offsets", 'i', 0, 0) || !get(args[1], &xb, "xy", 'f', 0, 0) ||
        !get(args[2], &sb, "seg", 'f', 1, 0) || !get(args[3], &cb, "cum", 'f', 1, 0) ||
        !get(args[4], &kb, "key", 'f', 1, 0) || !get(args[5], &tb, "turn", 'f', 1, 0) ||
        !get(args[6], &ab, "agents_f", 'f', 1, 0))
        goto done;
    n = ob.v.shape[0] - 1;
    M = xb.v.shape[0];
    m = M - 1;
    if (n < 1 || m < 1) {
        PyErr_SetString(PyExc_ValueError, "build: needs at least one path and one segment");
        goto done;
    }
    if (!sc_shape(&ob, "offsets", 1, n + 1, 0) || !sc_shape(&xb, "xy", 2, M, 2) ||
        !sc_shape(&sb, "seg", 2, SEG_ROWS, m) || !sc_shape(&cb, "cum", 1, M, 0) || !sc_shape(&kb, "key", 1, M, 0) ||
        !sc_shape(&tb, "turn", 1, m, 0) || !sc_shape(&ab, "agents_f", 2, 2, n))
        goto done;
    {
        const int64_t *off = (const int64_t *)ob.v.buf;
        const double *xy = (const double *)xb.v.buf;
        double *seg = (double *)sb.v.buf, *cum = (double *)cb.v.buf, *key = (double *)kb.v.buf;
        double *turn = (double *)tb.v.buf, *total = (double *)ab.v.buf, *base = total + n;
        double *X0 = seg + R_X0 * m, *Y0 = seg + R_Y0 * m, *DX = seg + R_DX * m, *DY = seg + R_DY * m;
        double *C0 = seg + R_C0 * m, *SL = seg + R_L * m, *BS = seg + R_BS * m, *BE = seg + R_BE * m;
        double *NDS = seg + R_NEG_DS * m, *DE = seg + R_DE * m, *H = seg + R_H * m, *TBS = seg + R_TWO_BS * m;
        double *TBE = seg + R_TWO_BE * m, *KS = seg + R_KS * m, *KE = seg + R_KE * m;
        double c;
        if (!offsets_ok(off, n, M, 2)) {
            result = Py_False;
            Py_INCREF(result);
            goto done;
        }
        raw = PyMem_Malloc((size_t)m * sizeof(double)); /* the segment lengths before the floor */
        if (!raw) {
            PyErr_NoMemory();
            goto done;
        }
        /* _measure: segments, lengths (0 across two paths), headings, directions */
        for (j = 0; j < m; j++) {
            const double dx = xy[2 * j + 2] - xy[2 * j], dy = xy[2 * j + 3] - xy[2 * j + 1];
            raw[j] = hypot(dx, dy);
            H[j] = atan2(dy, dx);
            X0[j] = xy[2 * j];
            Y0[j] = xy[2 * j + 1];
            DX[j] = dx; /* divided below, once the gaps' lengths are 0 */
            DY[j] = dy;
        }
        for (a = 0; a + 1 < n; a++) raw[off[a + 1] - 1] = 0.0;
        for (j = 0; j < m; j++) {
            SL[j] = np_max(raw[j], MIN_SEG_M);
            DX[j] = DX[j] / SL[j];
            DY[j] = DY[j] / SL[j];
        }
        /* the arc lengths: numpy's cumsum (sequential) minus each path's start */
        c = 0.0;
        cum[0] = 0.0;
        for (j = 0; j < m; j++) cum[j + 1] = c = c + raw[j];
        for (a = 0; a < n; a++) {
            const double start = cum[off[a]], b = (double)a * AGENT_GAP_M;
            Py_ssize_t v;
            for (v = off[a]; v < off[a + 1]; v++) {
                cum[v] = cum[v] - start;
                key[v] = cum[v] + b;
            }
            total[a] = cum[off[a + 1] - 1];
            base[a] = b;
        }
        for (j = 0; j < m; j++) C0[j] = cum[j];
        /* _vertex_turns */
        turn[0] = 0.0;
        BS[0] = 0.0;
        for (j = 1; j < m; j++) {
            turn[j] = wrap_pi(H[j] - H[j - 1]);
            BS[j] = np_min(np_min(raw[j], raw[j - 1]) * 0.5, BLEND_M);
        }
        for (a = 0; a < n; a++) turn[off[a]] = BS[off[a]] = 0.0;
        for (j = 0; j + 1 < m; j++) {
            DE[j] = turn[j + 1];
            BE[j] = BS[j + 1];
        }
        DE[m - 1] = BE[m - 1] = 0.0;
        for (a = 0; a < n; a++) DE[off[a + 1] - 2] = BE[off[a + 1] - 2] = 0.0;
        /* _continue_sampled_ends: a path's first / last segment continues its neighbour's turn */
        if (m > 1) {
            for (a = 0; a < n; a++) {
                const Py_ssize_t f = off[a], ls = off[a + 1] - 2;
                if (f == ls) continue;
                if (raw[f] <= FINE_SEG_M && raw[f + 1] <= FINE_SEG_M && raw[f] <= SAMPLING_RATIO * raw[f + 1]) {
                    turn[f] = DE[f] * raw[f] / np_max(raw[f + 1], MIN_SEG_M);
                    BS[f] = 0.5 * raw[f];
                }
                if (raw[ls] <= FINE_SEG_M && raw[ls - 1] <= FINE_SEG_M && raw[ls] <= SAMPLING_RATIO * raw[ls - 1]) {
                    DE[ls] = turn[ls] * raw[ls] / np_max(raw[ls - 1], MIN_SEG_M);
                    BE[ls] = 0.5 * raw[ls];
                }
            }
        }
        /* _segment_table's derived rows */
        for (j = 0; j < m; j++) {
            NDS[j] = -turn[j];
            TBS[j] = BS[j] > 0 ? 2 * BS[j] : 1.0;
            TBE[j] = BE[j] > 0 ? 2 * BE[j] : 1.0;
            KS[j] = turn[j] / TBS[j];
            KE[j] = DE[j] / TBE[j];
        }
    }
    result = Py_True;
    Py_INCREF(result);
done:
    PyMem_Free(raw);
    SC_RELEASE(&ob, &xb, &sb, &cb, &kb, &tb, &ab);
    return result;
}

/* Squared tolerances within which dedup asks hypot: outside them the squared distance
 * (2 roundings, relative error < 1e-15) decides hypot(dx, dy) >= tol (< 1 ulp off) alike;
 * a NaN or overflowing square falls to hypot or to the right side. Only for tolerances whose
 * square is a normal double. */
#define DEDUP_SQ_MARGIN 1e-6 /* [1] */
#define DEDUP_QUICK_TOL_MIN 1e-100 /* [m] */
#define DEDUP_QUICK_TOL_MAX 1e100  /* [m] */

static inline int far_enough(double dx, double dy, double tol, double lo2, double hi2) {
    const double q = dx * dx + dy * dy;
    if (q > hi2) return 1;
    if (q < lo2) return 0;
    return hypot(dx, dy) >= tol;
}

/* PathSet.dedup: keeps a path's first vertex and every vertex at least tol from the one
 * before it (hypot >= tol, so a NaN distance drops it), into new_offsets (n + 1,) and the
 * first rows of new_xy (len(xy), 2). Returns the number of vertices kept (len(xy): nothing
 * dropped, the inputs stay), or -1 when the offsets are not 0 .. len(xy) (the Python body
 * then runs). */
static PyObject *py_dedup(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    sc_buf ob, xb, nob, nxb;
    Py_ssize_t n, M, v, a, kept = 0;
    double tol;
    PyObject *result = NULL;
    (void)self;
    ob.held = xb.held = nob.held = nxb.held = 0;
    if (nargs != 5) {
        PyErr_SetString(PyExc_TypeError, "dedup(offsets, xy, tol, new_offsets, new_xy) takes 5 arguments");
        return NULL;
    }
    if (!get(args[0], &ob, "offsets", 'i', 0, 0) || !get(args[1], &xb, "xy", 'f', 0, 0) ||
        !as_double(args[2], "tol", &tol) || !get(args[3], &nob, "new_offsets", 'i', 1, 0) ||
        !get(args[4], &nxb, "new_xy", 'f', 1, 0))
        goto done;
    n = ob.v.shape[0] - 1;
    M = xb.v.shape[0];
    if (n < 1) { /* no paths: the Python body's case */
        result = PyLong_FromSsize_t(-1);
        goto done;
    }
    if (!sc_shape(&ob, "offsets", 1, n + 1, 0) || !sc_shape(&xb, "xy", 2, M, 2) ||
        !sc_shape(&nob, "new_offsets", 1, n + 1, 0) || !sc_shape(&nxb, "new_xy", 2, M, 2))
        goto done;
    {
        const int64_t *off = (const int64_t *)ob.v.buf;
        const double *xy = (const double *)xb.v.buf;
        int64_t *no = (int64_t *)nob.v.buf;
        double *nxy = (double *)nxb.v.buf;
        int dropped = 0;
        const int quick = tol >= DEDUP_QUICK_TOL_MIN && tol <= DEDUP_QUICK_TOL_MAX;
        /* without the quick test every distance goes to hypot (the bounds never decide) */
        const double lo2 = quick ? tol * tol * (1.0 - DEDUP_SQ_MARGIN) : -HUGE_VAL;
        const double hi2 = quick ? tol * tol * (1.0 + DEDUP_SQ_MARGIN) : HUGE_VAL;
        if (!offsets_ok(off, n, M, 0)) {
            result = PyLong_FromSsize_t(-1);
            goto done;
        }
        for (v = 1; v < M && !dropped; v++)
            dropped = !far_enough(xy[2 * v] - xy[2 * v - 2], xy[2 * v + 1] - xy[2 * v - 1], tol, lo2, hi2);
        if (dropped) {
            /* some vertex goes (maybe a path's first, which stays): compact */
            no[0] = 0;
            for (a = 0; a < n; a++) {
                for (v = off[a]; v < off[a + 1]; v++) {
                    /* (a path's first vertex stays, without reading the one before it) */
                    if (v == off[a] ||
                        far_enough(xy[2 * v] - xy[2 * v - 2], xy[2 * v + 1] - xy[2 * v - 1], tol, lo2, hi2)) {
                        nxy[2 * kept] = xy[2 * v];
                        nxy[2 * kept + 1] = xy[2 * v + 1];
                        kept++;
                    }
                }
                no[a + 1] = kept;
            }
        } else {
            kept = M;
        }
    }
    result = PyLong_FromSsize_t(kept);
done:
    SC_RELEASE(&ob, &xb, &nob, &nxb);
    return result;
}

static PyMethodDef methods[] = {
    {"at", (PyCFunction)(void (*)(void))py_at, METH_FASTCALL,
     "at(seg, key, agents_f, agents_i, s, out) -> None: PathSet.at into out (4, *s.shape) = x, y, heading, "
     "curvature. seg: the (15, m) segment table; key: the (m + 1,) search key; agents_f: (2, n) total, base; "
     "agents_i: (2, n) int64 first, last_seg; s: float64 (..., n)."},
    {"reference", (PyCFunction)(void (*)(void))py_reference, METH_FASTCALL,
     "reference(seg, key, agents_f, agents_i, state, mode, drift, tau, tau_l, L, u, c2, s_guess, px, py, out) -> "
     "None: Reference.at(tau) into out[:8] (x, y, yaw, speed, accel, curvature, s, tangent) and, unless s_guess "
     "is None, project(px, py, s_guess, tau) into out[8:14] (s, lateral offset, x, y, heading, curvature). "
     "state: Reference._c_state (12, n); mode, drift, tau, tau_l, L, u, c2: the scalars of Reference._profile "
     "and _shift (Reference._run_c); the rest as in at, s_guess, px, py float64 (n,)."},
    {"point_at", (PyCFunction)(void (*)(void))py_point_at, METH_FASTCALL,
     "point_at(seg, key, agents_f, agents_i, state, drift, tau, s, out) -> None: Reference.point_at(s, tau) into "
     "out (4, n) = x, y, heading, curvature; s float64 (n,), the rest as in reference."},
    {"build", (PyCFunction)(void (*)(void))py_build, METH_FASTCALL,
     "build(offsets, xy, seg, cum, key, turn, agents_f) -> bool: PathSet.__init__'s tables into seg (15, m), "
     "cum, key (m + 1,), turn (m,), agents_f (2, n) = total, base; False (nothing written) unless offsets run "
     "from 0 to len(xy) with >= 2 vertices each. offsets int64 (n + 1,), xy float64 (m + 1, 2)."},
    {"dedup", (PyCFunction)(void (*)(void))py_dedup, METH_FASTCALL,
     "dedup(offsets, xy, tol, new_offsets, new_xy) -> int: PathSet.dedup into new_offsets (n + 1,) and "
     "new_xy[:kept]; returns kept (len(xy): nothing dropped), or -1 unless offsets run from 0 to len(xy)."},
    {NULL, NULL, 0, NULL},
};

SC_MODULE(PyInit__pathkernel, "physics_side._pathkernel",
          "C fast paths of physics_side.reference: PathSet.at, Reference.at / at_and_project, PathSet's tables "
    "and dedup (bit-identical to their Python bodies).", methods)
