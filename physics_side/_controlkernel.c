/* Fast path of physics_side.control.control_default, the default preset's controller, per
 * agent once the reference and the bumper's projection are known:
 *
 * - prepare: what the Python wrapper needs before its calls into the reference (the speed
 *   the preview and the drift take, the preview's or the pursuit target's arc length) and
 *   Stanley's cross-track angle before numpy's tanh (numpy's own SIMD tanh is not libm's;
 *   the wrapper calls np.tanh between the two);
 * - control: the longitudinal loop (standing reference, Reference.mean_speed_lead's correction, stopping, integral,
 *   brake loop, torques, hold, roll back) and the lateral law (Stanley at the front bumper
 *   or front-axle pure pursuit) with their clips;
 * - limit: control.limit_commands' vehicle limits once the bend ahead's curvature and the
 *   reference speed are known (friction-circle steering, traction, curve speed, saturation
 *   and grip cuts, a leaning two-wheeler's friction circle); body: _limit_commands_numpy.
 *
 * The numpy body (control._control_default_numpy, ~55 numpy calls over every agent with the
 * mean-speed lead's: ~0.3 ms per control tick at 1,000 cars) stays the reference: each loop evaluates its expressions
 * operation for operation in numpy's order, with the libm functions numpy calls (cos, sin,
 * tan, atan, atan2) and numpy's NaN-propagating minimum / maximum, so the results are
 * bit-identical (tests/test_physics_controlkernel.py compares them). Where numpy evaluates
 * an expression for every agent and np.where keeps it for some, the loop evaluates it for
 * those only: the same bits.
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

static inline double clip(double x, double lo, double hi) { return np_min(np_max(x, lo), hi); }

/* ``n`` float64 (or bool) items in one dimension; None allowed where ``optional`` (nothing held). */
static int get_n(PyObject *o, sc_buf *b, const char *fn, const char *name, char kind, Py_ssize_t n, int optional,
                 int writable) {
    b->held = 0;
    if (optional && o == Py_None) return 1;
    if (!sc_get(o, b, name, kind, writable, 0)) return 0;
    if (b->v.ndim != 1 || b->v.shape[0] != n) {
        PyErr_Format(PyExc_ValueError, "%s: %s needs shape (%zd,)", fn, name, n);
        return 0;
    }
    return 1;
}

/* a tuple of ``count`` numbers into ``c`` */
static int get_consts(PyObject *o, const char *fn, double *c, Py_ssize_t count) {
    if (!PyTuple_Check(o) || PyTuple_GET_SIZE(o) != count) {
        PyErr_Format(PyExc_TypeError, "%s: constants must be a tuple of %zd numbers", fn, count);
        return 0;
    }
    for (Py_ssize_t j = 0; j < count; j++) {
        c[j] = PyFloat_AsDouble(PyTuple_GET_ITEM(o, j));
        if (c[j] == -1.0 && PyErr_Occurred()) return 0;
    }
    return 1;
}

/* ------------------------------------------------------------------ prepare */

enum { P_SPEED, P_S_ACT, P_E_LAT, P_OUT, P_CONST, P_ARGS };
enum { PC_STANLEY, PC_PREVIEW_S, PC_K_CROSS, PC_V_SOFT, PC_MC_ON, PC_MC, PC_LAD_MIN, PC_LAD_MAX, PC_K_LAD, PC_COUNT };
enum { PO_V_POS, PO_S, PO_CORR, PO_ROWS };

static PyObject *py_prepare(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    sc_buf b[P_CONST] = {{{0}}};
    PyObject *result = NULL;
    double c[PC_COUNT];
    (void)self;
    if (nargs != P_ARGS) {
        PyErr_SetString(PyExc_TypeError, "prepare(speed, s_act, e_lat, out, constants) takes 5 arguments");
        return NULL;
    }
    if (!get_consts(args[P_CONST], "prepare", c, PC_COUNT)) return NULL;
    if (!sc_get(args[P_SPEED], &b[P_SPEED], "speed", SC_F64, 0, 0)) goto done;
    if (b[P_SPEED].v.ndim != 1) {
        PyErr_SetString(PyExc_ValueError, "prepare: speed needs 1 dimension");
        goto done;
    }
    const Py_ssize_t n = b[P_SPEED].v.shape[0];
    if (!get_n(args[P_S_ACT], &b[P_S_ACT], "prepare", "s_act", SC_F64, n, 0, 0) ||
        !get_n(args[P_E_LAT], &b[P_E_LAT], "prepare", "e_lat", SC_F64, n, 0, 0) ||
        !sc_get(args[P_OUT], &b[P_OUT], "out", SC_F64, 1, 0) || !sc_shape(&b[P_OUT], "out", 2, PO_ROWS, n))
        goto done;
    const double *speed = b[P_SPEED].v.buf, *s_act = b[P_S_ACT].v.buf, *e_lat = b[P_E_LAT].v.buf;
    double *o = b[P_OUT].v.buf;
    const int stanley = c[PC_STANLEY] != 0.0, mc_on = c[PC_MC_ON] != 0.0;
    for (Py_ssize_t i = 0; i < n; i++) {
        const double v = speed[i], v_pos = np_max(v, 0.0);
        o[PO_V_POS * n + i] = v_pos;
        if (stanley) {
            /* _default_steer: s_act + np.maximum(speed, 0.0) * preview_s; stanley_bumper's
             * arctan2(k * e_lat, abs(v) + v_soft), divided by max_correction before its tanh */
            o[PO_S * n + i] = s_act[i] + v_pos * c[PC_PREVIEW_S];
            const double corr = atan2(c[PC_K_CROSS] * e_lat[i], fabs(v) + c[PC_V_SOFT]);
            o[PO_CORR * n + i] = mc_on ? corr / c[PC_MC] : corr;
        } else {
            /* lad(speed): where(v < lad_min, lad_min, minimum(v * k_lad, lad_max)) ahead */
            const double lad = v < c[PC_LAD_MIN] ? c[PC_LAD_MIN] : np_min(v * c[PC_K_LAD], c[PC_LAD_MAX]);
            o[PO_S * n + i] = s_act[i] + lad;
            o[PO_CORR * n + i] = 0.0;
        }
    }
    result = Py_None;
    Py_INCREF(result);
done:
    sc_release_all(b, P_CONST);
    return result;
}

/* ------------------------------------------------------------------ control */

/* reference.stopping_distance: distance and speed after ``tau`` from speed v at constant
 * acceleration a, never reversing */
static inline void stopping_distance(double v, double a, double tau, double *s, double *vt) {
    *vt = v + a * tau;
    *s = v * tau + 0.5 * a * tau * tau;
    if (*vt < 0.0) {
        *s = a < 0 ? v * v / (-2.0 * a) : 0.0;
        *vt = 0.0;
    }
}

/* arguments, in the order of control._control_default_c's call */
enum {
    A_FX, A_FY, A_CX, A_CY, A_YAW, A_SPEED, A_YAW_RATE, A_FVX, A_FVY, /* VehicleObs */
    A_RX, A_RY, A_RYAW, A_RS, A_RV, A_RA,                             /* ReferencePoint at tau */
    A_S_ACT, A_PP_H,                                                  /* projection of the bumper */
    A_V0, A_A0,                                                       /* the sample's speed, acceleration */
    A_STOP, A_STOP_SPEED,                                             /* stopping (bool) or None */
    A_INTEG,                                                          /* ControlState.integ */
    A_WB, A_DB, A_REAR, A_MEFF, A_RW, A_MAX_STEER, A_MAX_DRIVE, A_MAX_BRAKE, A_MAX_REAR, /* VehicleParams */
    A_ROLLS,                                                          /* rolls_back (bool) or None */
    A_LAT1, A_LAT2, A_DRIFT, A_CORR, /* Stanley: heading, curvature ahead, drift or None, corr; pursuit: target x, y */
    A_OUT, A_CONST, A_ARGS
};
enum {
    C_STANLEY, C_HOLD_SPEED, C_STOP_ACCEL, C_DT, C_INT_LO, C_INT_HI, C_W2, C_CZ, C_K_INT, C_BRAKE_ON, C_BW2, C_BZ,
    C_A_LO, C_A_HI, C_HOLD_ACCEL, C_HOLD_BRAKE, C_CREEP_ON, C_CREEP_LO, C_CREEP_FROM_REST, C_CREEP_DONE_LO,
    C_ROLLING_LO, C_CREEP_SPEED, C_CREEP_GAIN, C_CREEP_ACCEL, C_MC_ON, C_MC, C_BETA_MAX, C_K_YAW_ON, C_K_YAW,
    C_DEMAND_MAX, C_LEAD, C_TAU, C_LEAD_S, C_TAU_LEAD, C_COUNT
};
enum { LEAD_OFF, LEAD_ZERO, LEAD_ON }; /* C_LEAD: no lead, Reference.mean_speed_lead's zeros, its profile */
enum { O_STEER, O_DRIVE, O_BRAKE, O_ACCEL, O_INTEG, O_ROWS };

static const char *const arg_names[A_OUT] = {
    "fx", "fy", "cx", "cy", "yaw", "speed", "yaw_rate", "fvx", "fvy", "r_x", "r_y", "r_yaw", "r_s", "r_speed",
    "r_accel", "s_act", "pp_heading", "v0", "a0", "stopping", "stop_speed", "integ", "wheelbase",
    "d_bumper", "rear_axle", "m_eff", "r_wheel", "max_steer", "max_drive", "max_brake", "max_rear", "rolls_back",
    "lat1", "lat2", "drift", "corr"};

static PyObject *py_control(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    sc_buf b[A_CONST] = {{{0}}};
    PyObject *result = NULL;
    double c[C_COUNT];
    (void)self;
    if (nargs != A_ARGS) {
        PyErr_Format(PyExc_TypeError, "control takes %d arguments", A_ARGS);
        return NULL;
    }
    if (!get_consts(args[A_CONST], "control", c, C_COUNT)) return NULL;
    if (!sc_get(args[A_SPEED], &b[A_SPEED], "speed", SC_F64, 0, 0)) goto done;
    if (b[A_SPEED].v.ndim != 1) {
        PyErr_SetString(PyExc_ValueError, "control: speed needs 1 dimension");
        goto done;
    }
    const Py_ssize_t n = b[A_SPEED].v.shape[0];
    const int stanley = c[C_STANLEY] != 0.0;
    for (int a = 0; a < A_OUT; a++) {
        if (a == A_SPEED) continue;
        const int optional = a == A_STOP || a == A_STOP_SPEED || a == A_MAX_REAR ||
                             a == A_ROLLS || a == A_DRIFT || (a == A_CORR && !stanley);
        const char kind = a == A_STOP || a == A_ROLLS ? SC_BOOL : SC_F64;
        if (!get_n(args[a], &b[a], "control", arg_names[a], kind, n, optional, 0)) goto done;
    }
    if (b[A_STOP].held && !b[A_STOP_SPEED].held) {
        PyErr_SetString(PyExc_ValueError, "control: stopping needs stop_speed");
        goto done;
    }
    if (!sc_get(args[A_OUT], &b[A_OUT], "out", SC_F64, 1, 0) || !sc_shape(&b[A_OUT], "out", 2, O_ROWS, n)) goto done;

    const double *fx = b[A_FX].v.buf, *fy = b[A_FY].v.buf, *cx = b[A_CX].v.buf, *cy = b[A_CY].v.buf,
                 *yaw = b[A_YAW].v.buf, *speed = b[A_SPEED].v.buf, *yaw_rate = b[A_YAW_RATE].v.buf,
                 *fvx = b[A_FVX].v.buf, *fvy = b[A_FVY].v.buf;
    const double *rx = b[A_RX].v.buf, *ry = b[A_RY].v.buf, *ryaw = b[A_RYAW].v.buf, *rs = b[A_RS].v.buf,
                 *rv = b[A_RV].v.buf, *ra = b[A_RA].v.buf;
    const double *s_act = b[A_S_ACT].v.buf, *pp_h = b[A_PP_H].v.buf;
    const double *v0 = b[A_V0].v.buf, *a0 = b[A_A0].v.buf;
    const uint8_t *stop = b[A_STOP].held ? b[A_STOP].v.buf : NULL;
    const double *stop_speed = b[A_STOP_SPEED].held ? b[A_STOP_SPEED].v.buf : NULL;
    const double *integ = b[A_INTEG].v.buf;
    const double *wb = b[A_WB].v.buf, *db = b[A_DB].v.buf, *rear = b[A_REAR].v.buf, *m_eff = b[A_MEFF].v.buf,
                 *r_wheel = b[A_RW].v.buf, *max_steer = b[A_MAX_STEER].v.buf, *max_drive = b[A_MAX_DRIVE].v.buf,
                 *max_brake = b[A_MAX_BRAKE].v.buf, *max_rear = b[A_MAX_REAR].held ? b[A_MAX_REAR].v.buf : NULL;
    const uint8_t *rolls = b[A_ROLLS].held ? b[A_ROLLS].v.buf : NULL;
    const double *lat1 = b[A_LAT1].v.buf, *lat2 = b[A_LAT2].v.buf,
                 *drift = b[A_DRIFT].held ? b[A_DRIFT].v.buf : NULL, *corr_in = stanley ? b[A_CORR].v.buf : NULL;
    double *o = b[A_OUT].v.buf;
    const double hold_speed = c[C_HOLD_SPEED];
    const int brake_on = c[C_BRAKE_ON] != 0.0, creep_on = c[C_CREEP_ON] != 0.0, mc_on = c[C_MC_ON] != 0.0,
              k_yaw_on = c[C_K_YAW_ON] != 0.0, lead = (int)c[C_LEAD];

    for (Py_ssize_t i = 0; i < n; i++) {
        /* ---- control_default: the longitudinal loop */
        double e_s = rs[i] - s_act[i], v_ref = rv[i], a_ref = ra[i];
        if (v_ref <= hold_speed) /* a standing reference: the error along SUMO's own heading */
            e_s = (rx[i] - fx[i]) * cos(ryaw[i]) + (ry[i] - fy[i]) * sin(ryaw[i]);
        if (lead == LEAD_ZERO) {
            e_s = e_s + 0.0; /* (turns -0.0 into 0.0, as numpy's + zeros) */
            v_ref = v_ref + 0.0;
        } else if (lead == LEAD_ON) {
            /* Reference.mean_speed_lead: S(tau + lead) - S(lead) - S(tau), V(tau + lead) - V(tau) */
            double s0, w0, s1, w1, sl, wl;
            stopping_distance(v0[i], a0[i], c[C_TAU], &s0, &w0);
            stopping_distance(v0[i], a0[i], c[C_TAU_LEAD], &s1, &w1);
            stopping_distance(v0[i], a0[i], c[C_LEAD_S], &sl, &wl);
            e_s = e_s + (s1 - sl - s0);
            v_ref = v_ref + (w1 - w0);
        }
        const int stopping = stop && stop[i];
        if (stopping) {
            v_ref = stop_speed[i];
            a_ref = stop_speed[i] > 0 ? c[C_STOP_ACCEL] : 0.0;
            e_s = 0.0;
        }
        /* VehicleObs.bumper_speed_along(pp.heading) */
        const double e_v = v_ref - (fvx[i] * cos(pp_h[i]) + fvy[i] * sin(pp_h[i]));
        const int live = v_ref > hold_speed && !stopping;
        const double in = live ? clip(integ[i] + e_s * c[C_DT], c[C_INT_LO], c[C_INT_HI]) : 0.0;
        /* accel_command: a_ref + w^2 e_s + 2 zeta w e_v + k_i integral, left to right */
        double a_cmd = a_ref + c[C_W2] * e_s + c[C_CZ] * e_v + c[C_K_INT] * in;
        if (brake_on) a_cmd = np_min(a_cmd, a_ref + c[C_BW2] * e_s + c[C_BZ] * e_v + c[C_K_INT] * in);
        a_cmd = clip(a_cmd, c[C_A_LO], c[C_A_HI]);
        /* accel_to_torques */
        const double t = a_cmd * m_eff[i] * r_wheel[i];
        double drive = clip(t, 0.0, max_drive[i]), brake = clip(-t, 0.0, max_brake[i]);
        if (v_ref <= hold_speed && a_cmd <= c[C_HOLD_ACCEL]) {
            brake = np_max(brake, c[C_HOLD_BRAKE] * max_brake[i]);
            drive = 0.0;
        }
        /* _roll_back */
        int back = 0;
        if (creep_on) {
            back = v_ref <= hold_speed && ((e_s < c[C_CREEP_LO] && speed[i] < c[C_CREEP_FROM_REST]) ||
                                           (e_s < c[C_CREEP_DONE_LO] && speed[i] < c[C_ROLLING_LO]));
            if (rolls) back = back && rolls[i];
        }
        if (back) {
            const double v_back = -np_min(c[C_CREEP_SPEED], 0.5 * -e_s);
            const double t_back = clip(c[C_CREEP_GAIN] * (v_back - speed[i]), -c[C_CREEP_ACCEL], c[C_CREEP_ACCEL]) *
                                  m_eff[i] * r_wheel[i];
            drive = clip(t_back, -max_drive[i], max_drive[i]);
            brake = 0.0;
        }
        /* ---- _default_steer */
        double steer;
        if (stanley) {
            /* lat1, lat2: heading and curvature of the path ahead (the preview, or the projection) */
            double he = yaw[i] - lat1[i];
            if (drift) he = he - drift[i];
            he = wrap_pi(he);
            const double corr = mc_on ? c[C_MC] * corr_in[i] : corr_in[i];
            const double beta = clip(-he - corr, -c[C_BETA_MAX], c[C_BETA_MAX]);
            steer = atan(wb[i] * tan(beta) / db[i]);
            if (k_yaw_on) steer = steer - c[C_K_YAW] * (yaw_rate[i] - speed[i] * lat2[i]);
        } else {
            /* lat1, lat2: the pursuit target; pursuit_alpha from the front axle */
            const double cy_ = cos(yaw[i]), sy_ = sin(yaw[i]);
            const double ax_x = cx[i] + (rear[i] + wb[i]) * cy_, ax_y = cy[i] + (rear[i] + wb[i]) * sy_;
            steer = wrap_pi(atan2(lat2[i] - ax_y, lat1[i] - ax_x) - yaw[i]);
        }
        const double lim = max_rear && max_rear[i] > 0 ? c[C_DEMAND_MAX] : max_steer[i];
        steer = clip(steer, -lim, lim);
        if (back) steer = 0.0;
        o[O_STEER * n + i] = steer;
        o[O_DRIVE * n + i] = drive;
        o[O_BRAKE * n + i] = brake;
        o[O_ACCEL * n + i] = a_cmd;
        o[O_INTEG * n + i] = in;
    }
    result = Py_None;
    Py_INCREF(result);
done:
    sc_release_all(b, A_CONST);
    return result;
}

/* ------------------------------------------------------------------ limit */

/* arguments, in the order of control._limit_commands_c's call; each group is None together
 * where the numpy body skips it */
enum {
    L_STEER, L_DRIVE, L_BRAKE, L_SPEED, L_WB, L_A_LAT, L_MAX_STEER, L_MAX_REAR, /* always */
    L_YAW_RATE, L_GRIP,                                                        /* lim.any_grip */
    L_KAP, L_V_REF, L_MASK, L_ERR_LAT, L_MEFF, L_RW,                           /* catch_up */
    L_ROLL, L_BIKE, L_MAX_DRIVE, L_MAX_BRAKE,                                  /* lim.any_bike */
    L_OUT, L_CONST, L_ARGS
};
enum {
    LC_REAR_STEERED, LC_V_MIN, LC_G, LC_MAX_GRIP_USE, LC_GRIP_LATERAL, LC_CURV_FLOOR, LC_SAT_SHARE, LC_SAT_DECEL,
    LC_SAT_LAT, LC_A_LAT_FLOOR, LC_COUNT
};
enum { LO_STEER, LO_DRIVE, LO_BRAKE, LO_ROWS };

static const char *const limit_names[L_OUT] = {
    "steer", "drive", "brake", "speed", "wheelbase", "a_lat", "max_steer", "max_rear", "yaw_rate", "grip_torque",
    "kap", "v_ref", "mask", "err_lat", "m_eff", "r_wheel", "roll", "bike", "max_drive", "max_brake"};
static const int limit_groups[][2] = {{L_YAW_RATE, L_GRIP}, {L_KAP, L_RW}, {L_ROLL, L_MAX_BRAKE}};

static PyObject *py_limit(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    sc_buf b[L_CONST] = {{{0}}};
    PyObject *result = NULL;
    double c[LC_COUNT];
    (void)self;
    if (nargs != L_ARGS) {
        PyErr_Format(PyExc_TypeError, "limit takes %d arguments", L_ARGS);
        return NULL;
    }
    if (!get_consts(args[L_CONST], "limit", c, LC_COUNT)) return NULL;
    for (size_t g = 0; g < sizeof limit_groups / sizeof limit_groups[0]; g++) {
        const int none = args[limit_groups[g][0]] == Py_None;
        for (int a = limit_groups[g][0] + 1; a <= limit_groups[g][1]; a++)
            if ((args[a] == Py_None) != none) {
                PyErr_Format(PyExc_ValueError, "limit: %s and %s are None together", limit_names[limit_groups[g][0]],
                             limit_names[a]);
                return NULL;
            }
    }
    if (!sc_get(args[L_STEER], &b[L_STEER], "steer", SC_F64, 0, 0)) goto done;
    if (b[L_STEER].v.ndim != 1) {
        PyErr_SetString(PyExc_ValueError, "limit: steer needs 1 dimension");
        goto done;
    }
    const Py_ssize_t n = b[L_STEER].v.shape[0];
    for (int a = L_DRIVE; a < L_OUT; a++) {
        const char kind = a == L_MASK || a == L_BIKE ? SC_BOOL : SC_F64;
        if (!get_n(args[a], &b[a], "limit", limit_names[a], kind, n, a >= L_YAW_RATE, 0)) goto done;
    }
    if (!sc_get(args[L_OUT], &b[L_OUT], "out", SC_F64, 1, 0) || !sc_shape(&b[L_OUT], "out", 2, LO_ROWS, n)) goto done;

    const double *steer = b[L_STEER].v.buf, *drive = b[L_DRIVE].v.buf, *brake = b[L_BRAKE].v.buf,
                 *speed = b[L_SPEED].v.buf, *wb = b[L_WB].v.buf, *a_lat = b[L_A_LAT].v.buf,
                 *max_steer = b[L_MAX_STEER].v.buf, *max_rear = b[L_MAX_REAR].v.buf;
    const double *yaw_rate = b[L_YAW_RATE].held ? b[L_YAW_RATE].v.buf : NULL,
                 *grip = b[L_GRIP].held ? b[L_GRIP].v.buf : NULL;
    const double *kap = b[L_KAP].held ? b[L_KAP].v.buf : NULL, *v_ref = kap ? b[L_V_REF].v.buf : NULL,
                 *err_lat = kap ? b[L_ERR_LAT].v.buf : NULL, *m_eff = kap ? b[L_MEFF].v.buf : NULL,
                 *r_wheel = kap ? b[L_RW].v.buf : NULL;
    const uint8_t *mask = kap ? b[L_MASK].v.buf : NULL;
    const double *roll = b[L_ROLL].held ? b[L_ROLL].v.buf : NULL, *max_drive = roll ? b[L_MAX_DRIVE].v.buf : NULL,
                 *max_brake = roll ? b[L_MAX_BRAKE].v.buf : NULL;
    const uint8_t *bike = roll ? b[L_BIKE].v.buf : NULL;
    double *o = b[L_OUT].v.buf;
    const int rear_steered = c[LC_REAR_STEERED] != 0.0;
    const double g = c[LC_G], max_use = c[LC_MAX_GRIP_USE], share = c[LC_SAT_SHARE], decel = c[LC_SAT_DECEL];

    for (Py_ssize_t i = 0; i < n; i++) {
        const double v = speed[i];
        /* steer_limit: minimum(max_steer, arctan(L * a_lat / maximum(v, v_min) ** 2)) (** 2: x * x) */
        const double vm = np_max(v, c[LC_V_MIN]);
        const double lim_f = np_min(max_steer[i], atan(wb[i] * a_lat[i] / (vm * vm)));
        const int fixed = max_rear[i] <= 0;
        double st = steer[i], dr = drive[i], br = brake[i];
        if (!rear_steered || fixed) st = clip(st, -lim_f, lim_f); /* (np.clip with array bounds: clip()) */
        if (grip) { /* traction_limit */
            const double use = np_min(fabs(v * yaw_rate[i]) / g, max_use) * c[LC_GRIP_LATERAL];
            dr = np_min(dr, grip[i] * sqrt(1.0 - use * use));
        }
        if (kap) {
            /* curve_speed_cut */
            if (mask[i] && v > np_max(sqrt(a_lat[i] / np_max(kap[i], c[LC_CURV_FLOOR])), v_ref[i])) dr = 0.0;
            /* saturation_speed_cut against where(mask, v_ref, inf) */
            const double vr = mask[i] ? v_ref[i] : INFINITY;
            if (fabs(st) >= share * max_steer[i] && v > vr) {
                dr = 0.0;
                br = np_max(br, np_min((v - vr) * decel, decel) * m_eff[i] * r_wheel[i]);
            }
            /* at the tyres' limit (a fixed rear axle), faster than the reference and off the path */
            const int grip_sat = fabs(st) >= share * lim_f && (!rear_steered || fixed);
            if (grip_sat && v > vr && fabs(err_lat[i]) > c[LC_SAT_LAT]) dr = 0.0;
        }
        if (bike && bike[i]) { /* lean_traction_limit of drive and brake (the same use) */
            const double use = np_min(fabs(tan(roll[i])) * g / np_max(a_lat[i], c[LC_A_LAT_FLOOR]), max_use);
            const double rest = sqrt(1.0 - use * use);
            dr = np_min(dr, max_drive[i] * rest);
            br = np_min(br, max_brake[i] * rest);
        }
        o[LO_STEER * n + i] = st;
        o[LO_DRIVE * n + i] = dr;
        o[LO_BRAKE * n + i] = br;
    }
    result = Py_None;
    Py_INCREF(result);
done:
    sc_release_all(b, L_CONST);
    return result;
}

static PyMethodDef methods[] = {
    {"prepare", (PyCFunction)(void (*)(void))py_prepare, METH_FASTCALL,
     "prepare(speed, s_act, e_lat, out, constants) -> None: into out (3, n) the forward speed np.maximum(speed, 0), "
     "the arc length of the steering's preview (Stanley) or pursuit target, and Stanley's cross-track angle "
     "(divided by max_correction when it is on: numpy's tanh follows). constants: (stanley, preview_s [s], "
     "k_cross [1/s], v_soft [m/s], max_correction on, max_correction [rad], lad_min [m], lad_max [m], k_lad [s])."},
    {"control", (PyCFunction)(void (*)(void))py_control, METH_FASTCALL,
     "control(fx, fy, cx, cy, yaw, speed, yaw_rate, fvx, fvy, r_x, r_y, r_yaw, r_s, r_speed, r_accel, s_act, "
     "pp_heading, v0, a0, stopping, stop_speed, integ, wheelbase, d_bumper, rear_axle, m_eff, r_wheel, max_steer, "
     "max_drive, max_brake, max_rear, rolls_back, lat1, lat2, drift, corr, out, constants) -> None: "
     "control_default's commands into out (5, n): steer, drive, brake, commanded acceleration, integral. "
     "float64 (n,) arrays (stopping, rolls_back: bool; v0, a0: Reference.speed, .accel for the mean-speed lead); stopping / stop_speed, max_rear, rolls_back and "
     "drift may be None. constants: see control._default_constants."},
    {"limit", (PyCFunction)(void (*)(void))py_limit, METH_FASTCALL,
     "limit(steer, drive, brake, speed, wheelbase, a_lat, max_steer, max_rear, yaw_rate, grip_torque, kap, v_ref, "
     "mask, err_lat, m_eff, r_wheel, roll, bike, max_drive, max_brake, out, constants) -> None: "
     "control.limit_commands' (steer, drive, brake) into out (3, n). float64 (n,) arrays (mask, bike: bool); "
     "None together: yaw_rate, grip_torque (no grip limit); kap .. r_wheel (no catch-up; kap: largest |curvature| "
     "ahead, v_ref: the reference speed); roll .. max_brake (no two-wheelers). constants: (rear_steered, "
     "STEER_LIMIT_V_MIN, G, MAX_GRIP_USE, GRIP_LATERAL, CURVATURE_FLOOR, STEER_SAT_SHARE, STEER_SAT_DECEL, "
     "GRIP_SAT_LAT_M, A_LAT_FLOOR)."},
    {NULL, NULL, 0, NULL},
};

SC_MODULE(PyInit__controlkernel, "physics_side._controlkernel",
          "C fast paths of physics_side.control.control_default and limit_commands (bit-identical to their numpy "
          "bodies).", methods)
