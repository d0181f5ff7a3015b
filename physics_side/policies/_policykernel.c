/* Fast paths of the physics side's per-step policies (physics_side.policies):
 *
 * - tightness: the (windows x agents) part of carry.path_tightness, every vehicle's
 *   tightest path ahead and the lateral acceleration its windows ask, from the path's
 *   headings on the grid (the numpy body runs ~30 calls over (11..13, n) arrays: ~0.6 ms per
 *   SUMO step at 1,000 cars).
 *
 * Each loop evaluates the numpy body's expressions operation for operation in numpy's order
 * (its reductions along the windows are row by row, as numpy's), with numpy's NaN-propagating
 * minimum / maximum and protocol.frames.wrap_pi's constants, so the results are bit-identical
 * (tests/test_physics_policykernel.py compares them).
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
#include "../_numpy_arith.h" /* numpy's arithmetic: no FMA, its max / min, wrap_pi */

/* a C-contiguous float64 (itemsize 8) or bool (itemsize 1) array of ``ndim`` dimensions */
static int get(PyObject *o, sc_buf *b, const char *name, int itemsize, int ndim, int writable) {
    return sc_get(o, b, name, itemsize == 8 ? SC_F64 : SC_BOOL, writable, 0) && sc_ndim(b, name, ndim);
}

static int get_n(PyObject *o, sc_buf *b, const char *name, int itemsize, Py_ssize_t n, int writable) {
    if (!get(o, b, name, itemsize, 1, writable)) return 0;
    if (b->v.shape[0] != n) {
        PyErr_Format(PyExc_ValueError, "tightness: %s has %zd items, expected %zd", name, b->v.shape[0], n);
        return 0;
    }
    return 1;
}

enum { A_H, A_GRID, A_V, A_AHEAD, A_REACH, A_ALAT, A_SHARE, A_BRAKE, A_ROLL, A_BIKE, A_TIGHT, A_SUST, A_CONST, N_ARGS };
enum { C_INTERP, C_GRIP, C_LEAN, C_K, C_KG, C_WINDOW, C_KAP_LEN, C_G, C_LEAN_MAX, C_CAR_SHARE, C_SHARE_FLOOR, N_CONST };

static PyObject *py_tightness(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    sc_buf b[A_CONST] = {{{0}}};
    PyObject *result = NULL;
    double c[N_CONST];
    (void)self;
    if (nargs != N_ARGS) {
        PyErr_SetString(PyExc_TypeError, "tightness(h, grid, v, ahead, reach, a_lat, share, brake, roll, bike, tight, "
                                         "sustained, constants) takes 13 arguments");
        return NULL;
    }
    if (!PyTuple_Check(args[A_CONST]) || PyTuple_GET_SIZE(args[A_CONST]) != N_CONST) {
        PyErr_Format(PyExc_TypeError, "tightness: constants must be a tuple of %d numbers", N_CONST);
        return NULL;
    }
    for (int j = 0; j < N_CONST; j++) {
        c[j] = PyFloat_AsDouble(PyTuple_GET_ITEM(args[A_CONST], j));
        if (c[j] == -1.0 && PyErr_Occurred()) return NULL;
    }
    if (!get(args[A_H], &b[A_H], "h", 8, 2, 0)) goto done;
    const Py_ssize_t G = b[A_H].v.shape[0], n = b[A_H].v.shape[1];
    const int interp = c[C_INTERP] != 0.0, grip_on = c[C_GRIP] != 0.0, lean_on = c[C_LEAN] != 0.0;
    const Py_ssize_t k = (Py_ssize_t)c[C_K], kg = (Py_ssize_t)c[C_KG];
    if (k < 1 || kg < 1 || k >= G || kg >= G) {
        PyErr_Format(PyExc_ValueError, "tightness: window offsets k=%zd, kg=%zd need 1 <= k, kg < %zd grid rows", k, kg, G);
        goto done;
    }
    if (!get_n(args[A_GRID], &b[A_GRID], "grid", 8, G, 0)) goto done;
    static const char *names[] = {"h", "grid", "v", "ahead", "reach", "a_lat", "share", "brake", "roll", "bike",
                                  "tight", "sustained"};
    for (int a = A_V; a < A_CONST; a++) {
        if (a == A_ROLL && !lean_on) continue; /* (None then) */
        if (!get_n(args[a], &b[a], names[a], a == A_BIKE ? 1 : 8, n, a == A_TIGHT || a == A_SUST)) goto done;
    }
    const double *h = b[A_H].v.buf, *grid = b[A_GRID].v.buf, *v = b[A_V].v.buf, *ahead = b[A_AHEAD].v.buf,
                 *reach = b[A_REACH].v.buf, *a_lat = b[A_ALAT].v.buf, *share = b[A_SHARE].v.buf,
                 *brake = b[A_BRAKE].v.buf, *roll = lean_on ? b[A_ROLL].v.buf : NULL;
    const uint8_t *bike = b[A_BIKE].v.buf;
    double *tight_out = b[A_TIGHT].v.buf, *sust_out = b[A_SUST].v.buf;
    const double window = c[C_WINDOW], kap_len = c[C_KAP_LEN];
    for (Py_ssize_t i = 0; i < n; i++) {
        const double vi = v[i], ai = ahead[i];
        double tight = 0.0, sust = 0.0;
        for (Py_ssize_t g = 0; g < G - k; g++) {
            const int in = grid[g] <= ai;
            const double kappa = fabs(wrap_pi(h[(g + k) * n + i] - h[g * n + i])) / window;
            const double v2 = interp ? vi * vi - 0.0 : vi * vi - 2.0 * brake[i] * grid[g];
            const double t_g = in ? kappa : 0.0, s_g = in ? kappa * np_max(v2, 0.0) : 0.0;
            tight = g ? np_max(tight, t_g) : t_g;
            sust = g ? np_max(sust, s_g) : s_g;
        }
        tight = tight / reach[i];
        sust_out[i] = sust;
        if (!grip_on) {
            tight_out[i] = tight;
            continue;
        }
        double dmax = 0.0, swing = 0.0, lean = 0.0;
        const int swings = lean_on && bike[i];
        if (swings) lean = -c[C_G] * tan(np_min(np_max(roll[i], -c[C_LEAN_MAX]), c[C_LEAN_MAX]));
        for (Py_ssize_t g = 0; g < G - kg; g++) {
            const double kap = wrap_pi(h[(g + kg) * n + i] - h[g * n + i]) / kap_len;
            const double demand = (grid[g] <= ai ? kap : 0.0) * vi * vi;
            const double d = fabs(demand);
            dmax = g ? np_max(dmax, d) : d;
            if (swings) {
                const double sw = fabs(demand - lean);
                swing = g ? np_max(swing, sw) : sw;
            }
        }
        double grip = dmax / a_lat[i];
        if (swings) grip = np_max(grip, swing / a_lat[i]);
        if (!interp) {
            grip = share[i] > 0 ? grip / np_max(share[i], c[C_SHARE_FLOOR]) : 0.0;
            grip = brake[i] > 0 ? sust / (a_lat[i] * c[C_CAR_SHARE]) : grip;
        }
        tight_out[i] = np_max(tight, grip);
    }
    result = Py_None;
    Py_INCREF(result);
done:
    sc_release_all(b, A_CONST);
    return result;
}

static PyMethodDef methods[] = {
    {"tightness", (PyCFunction)(void (*)(void))py_tightness, METH_FASTCALL,
     "tightness(h, grid, v, ahead, reach, a_lat, share, brake, roll, bike, tight, sustained, constants) -> None: "
     "carry.path_tightness from the path headings h (G, n) on the grid (G,) into tight and sustained (n,). "
     "roll: float64 (n,) or None (no lean swing); bike: bool (n,); constants: (interpolating, grip, lean, k, kg, "
     "window [m], kg window [m], g [m/s^2], lean read max [rad], car grip share, share floor)."},
    {NULL, NULL, 0, NULL},
};

SC_MODULE(PyInit__policykernel, "physics_side.policies._policykernel",
          "C fast paths of physics_side.policies (bit-identical to their numpy bodies).", methods)
