/* Fast paths of physics_side.world.PhysicsWorld's per-tick reads and writes of vehicles:
 *
 * - observe: the gather of their freejoint and steering coordinates out of the batch state
 *   and the observation derived from them, in one pass (the numpy body runs ~40 calls over
 *   (15, n) gathered rows: ~200 us per control tick at 1,000 cars);
 * - command: the Ackermann split of the steering and the scatter of steering, drive and
 *   brake columns into the batch state and the brakes' frictionloss.
 *
 * Each loop evaluates the numpy body's expressions operation for operation in numpy's order,
 * with the libm functions numpy calls (atan2, asin, tan, cos, sin) and numpy's
 * NaN-propagating minimum / maximum, so the results are bit-identical
 * (tests/test_physics_worldkernel.py compares them).
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

#define STATE_ROWS 15 /* world._SlotPlan.veh_state: freejoint qpos (7), qvel (6), two steer qpos */
#define OBS_ROWS 16   /* world.OBSERVATION_ROWS, in that order */
enum { O_CX, O_CY, O_Z, O_FX, O_FY, O_YAW, O_ROLL, O_PITCH, O_SPEED, O_VX, O_VY, O_WZ, O_WX, O_STEER, O_FVX, O_FVY };

/* a C-contiguous float64 ('f') / int64 ('i') array of ``ndim`` dimensions */
static int get(PyObject *o, sc_buf *b, const char *name, char kind, int ndim, int writable) {
    return sc_get(o, b, name, kind, writable, 0) && sc_ndim(b, name, ndim);
}

static PyObject *py_observe(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    sc_buf st = {0}, idx = {0}, fr = {0}, out = {0};
    PyObject *result = NULL;
    (void)self;
    if (nargs != 4) {
        PyErr_SetString(PyExc_TypeError, "observe(state, idx, front, out) takes 4 arguments");
        return NULL;
    }
    if (!get(args[0], &st, "state", 'f', 1, 0) || !get(args[1], &idx, "idx", 'i', 2, 0) ||
        !get(args[2], &fr, "front", 'f', 1, 0) || !get(args[3], &out, "out", 'f', 2, 1))
        goto done;
    const Py_ssize_t n = idx.v.shape[1], m = st.v.shape[0];
    if (idx.v.shape[0] != STATE_ROWS || fr.v.shape[0] != n || out.v.shape[0] != OBS_ROWS || out.v.shape[1] != n) {
        PyErr_Format(PyExc_ValueError, "observe: expected idx (%d, n), front (n,), out (%d, n); got idx (%zd, %zd), "
                     "front (%zd,), out (%zd, %zd)", STATE_ROWS, OBS_ROWS, idx.v.shape[0], n, fr.v.shape[0],
                     out.v.shape[0], out.v.shape[1]);
        goto done;
    }
    const double *s = (const double *)st.v.buf, *front = (const double *)fr.v.buf;
    const int64_t *ix = (const int64_t *)idx.v.buf;
    double *o = (double *)out.v.buf;
    for (Py_ssize_t k = 0; k < STATE_ROWS * n; k++) {
        if (ix[k] < 0 || ix[k] >= m) {
            PyErr_Format(PyExc_IndexError, "observe: state index %lld out of range [0, %zd)", (long long)ix[k], m);
            goto done;
        }
    }
    for (Py_ssize_t i = 0; i < n; i++) {
        double g[STATE_ROWS];
        for (int r = 0; r < STATE_ROWS; r++) g[r] = s[ix[r * n + i]];
        const double qw = g[3], qx = g[4], qy = g[5], qz = g[6];
        /* world._vehicle_state, expression by expression */
        const double xx_yy = qx * qx + qy * qy;
        const double yaw = atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz));
        const double roll = atan2(2.0 * (qw * qx + qy * qz), 1.0 - 2.0 * xx_yy);
        const double pitch = -asin(np_min(np_max(2.0 * (qw * qy - qz * qx), -1.0), 1.0));
        const double wz = 2.0 * (qx * qz - qw * qy) * g[10] + 2.0 * (qy * qz + qw * qx) * g[11] + (1.0 - 2.0 * xx_yy) * g[12];
        const double steer = 0.5 * (g[13] + g[14]);
        /* PhysicsWorld.observe */
        const double c = cos(yaw), sn = sin(yaw), f = front[i], vx = g[7], vy = g[8];
        const double wf = wz * f;
        o[O_CX * n + i] = g[0];
        o[O_CY * n + i] = g[1];
        o[O_Z * n + i] = g[2];
        o[O_FX * n + i] = g[0] + f * c;
        o[O_FY * n + i] = g[1] + f * sn;
        o[O_YAW * n + i] = yaw;
        o[O_ROLL * n + i] = roll;
        o[O_PITCH * n + i] = pitch;
        o[O_SPEED * n + i] = vx * c + vy * sn;
        o[O_VX * n + i] = vx;
        o[O_VY * n + i] = vy;
        o[O_WZ * n + i] = wz;
        o[O_WX * n + i] = g[10];
        o[O_STEER * n + i] = steer;
        o[O_FVX * n + i] = vx - wf * sn;
        o[O_FVY * n + i] = vy + wf * c;
    }
    result = Py_None;
    Py_INCREF(result);
done:
    SC_RELEASE(&st, &idx, &fr, &out);
    return result;
}

/* a float64 / int64 argument of ``n`` rows, ``cols`` columns (0: 1-d) */
static int get_n(PyObject *o, sc_buf *b, const char *name, char kind, Py_ssize_t n, Py_ssize_t cols) {
    if (!get(o, b, name, kind, cols ? 2 : 1, 0)) return 0;
    if (b->v.shape[0] != n || (cols && b->v.shape[1] != cols)) {
        PyErr_Format(PyExc_ValueError, "command: %s has %zd rows, expected %zd", name, b->v.shape[0], n);
        return 0;
    }
    return 1;
}

static int in_range(const int64_t *ix, Py_ssize_t count, Py_ssize_t m, const char *name) {
    for (Py_ssize_t k = 0; k < count; k++) {
        if (ix[k] < 0 || ix[k] >= m) {
            PyErr_Format(PyExc_IndexError, "command: %s index %lld out of range [0, %zd)", name, (long long)ix[k], m);
            return 0;
        }
    }
    return 1;
}

#define N_BRAKE 4 /* layout: a vehicle's brake columns (a two-wheeler's wheel in two each) */

static PyObject *py_command(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    sc_buf st = {0}, fl = {0}, sl = {0}, sr = {0}, du = {0}, sf = {0}, wb = {0}, tr = {0}, bs = {0}, str = {0}, dr = {0},
        br = {0};
    PyObject *result = NULL;
    (void)self;
    if (nargs != 12) {
        PyErr_SetString(PyExc_TypeError, "command(state, frictionloss, steer_l, steer_r, drive_u, spin_fl, wheelbase, "
                                         "track, brake_share, steer, drive, brake) takes 12 arguments");
        return NULL;
    }
    if (!get(args[0], &st, "state", 'f', 1, 1) || !get(args[1], &fl, "frictionloss", 'f', 1, 1) ||
        !get(args[2], &sl, "steer_l", 'i', 1, 0))
        goto done;
    const Py_ssize_t n = sl.v.shape[0], m = st.v.shape[0], mf = fl.v.shape[0];
    if (!get_n(args[3], &sr, "steer_r", 'i', n, 0) || !get_n(args[4], &du, "drive_u", 'i', n, 0) ||
        !get_n(args[5], &sf, "spin_fl", 'i', n, N_BRAKE) || !get_n(args[6], &wb, "wheelbase", 'f', n, 0) ||
        !get_n(args[7], &tr, "track", 'f', n, 0) || !get_n(args[8], &bs, "brake_share", 'f', n, N_BRAKE) ||
        !get_n(args[9], &str, "steer", 'f', n, 0) || !get_n(args[10], &dr, "drive", 'f', n, 0) ||
        !get_n(args[11], &br, "brake", 'f', n, 0))
        goto done;
    const int64_t *il = (const int64_t *)sl.v.buf, *ir = (const int64_t *)sr.v.buf, *id = (const int64_t *)du.v.buf,
                  *ib = (const int64_t *)sf.v.buf;
    if (!in_range(il, n, m, "steer_l") || !in_range(ir, n, m, "steer_r") || !in_range(id, n, m, "drive_u") ||
        !in_range(ib, N_BRAKE * n, mf, "spin_fl"))
        goto done;
    double *s = (double *)st.v.buf, *f = (double *)fl.v.buf;
    const double *w = (const double *)wb.v.buf, *t = (const double *)tr.v.buf, *share = (const double *)bs.v.buf,
                 *d = (const double *)str.v.buf, *drive = (const double *)dr.v.buf, *brake = (const double *)br.v.buf;
    /* numpy writes every left angle, then every right one, drive, brakes: where two columns
     * share an index (none do) the later array would win; the same order of arrays here */
    double *right = PyMem_Malloc((n ? n : 1) * sizeof(double));
    if (!right) {
        PyErr_NoMemory();
        goto done;
    }
    for (Py_ssize_t i = 0; i < n; i++) {
        /* kinematics.ackermann */
        const double tt = tan(d[i]);
        const double half = 0.5 * t[i] * tt, lt = w[i] * tt;
        s[il[i]] = atan2(lt, w[i] - half);
        right[i] = atan2(lt, w[i] + half);
    }
    for (Py_ssize_t i = 0; i < n; i++) s[ir[i]] = right[i];
    PyMem_Free(right);
    for (Py_ssize_t i = 0; i < n; i++) s[id[i]] = drive[i];
    for (Py_ssize_t k = 0; k < N_BRAKE * n; k++) f[ib[k]] = brake[k / N_BRAKE] * share[k];
    result = Py_None;
    Py_INCREF(result);
done:
    SC_RELEASE(&st, &fl, &sl, &sr, &du, &sf, &wb, &tr, &bs, &str, &dr, &br);
    return result;
}

static PyMethodDef methods[] = {
    {"command", (PyCFunction)(void (*)(void))py_command, METH_FASTCALL,
     "command(state, frictionloss, steer_l, steer_r, drive_u, spin_fl, wheelbase, track, brake_share, steer, drive, "
     "brake) -> None: every vehicle's Ackermann-split steering, drive and brake torques written into the batch "
     "state and the brakes' frictionloss (world.PhysicsWorld.command_vehicles without rear steering, traction "
     "control and stabiliser)."},
    {"observe", (PyCFunction)(void (*)(void))py_observe, METH_FASTCALL,
     "observe(state, idx, front, out) -> None: the vehicles' Observation into out (16, n), rows in "
     "world.OBSERVATION_ROWS order. state: the flat float64 batch state; idx: (15, n) int64 flat indices "
     "(world._SlotPlan.veh_state); front: (n,) float64 body origin to front bumper [m]."},
    {NULL, NULL, 0, NULL},
};

SC_MODULE(PyInit__worldkernel, "physics_side._worldkernel",
          "C fast paths of physics_side.world.PhysicsWorld.observe and command_vehicles (bit-identical to their numpy "
          "bodies).", methods)
