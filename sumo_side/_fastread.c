/* Fast path of sumo_side.simulation's vehicle read: subscription results -> columns.
 *
 * read_vehicles calls libsumo's getSubscriptionResults once per vehicle and takes the
 * variables out of each result dict while it is fresh in the cache, then drops it: the
 * dicts are never all alive at once (the Python path holds 10,000 of them, then walks them
 * again per column). Floats go straight into buffers the caller passes in (numpy arrays),
 * lane and type ids become indexes through the caller's dicts, route ids come back as a list.
 *
 * On anything it does not expect -- a result that is not a dict, a missing variable (a
 * vehicle without a subscription), a value of another type than libsumo's, an index that
 * is not a small int -- it returns None before any side effect, and the caller runs its
 * Python path, which handles (or raises on) such input. So it never has to match a Python
 * error message: declining too much only costs time, accepting too much would be a bug.
 * Exceptions raised by the callables it is given (libsumo's, the type table's) propagate.
 *
 * Plain CPython C API (no numpy headers): the columns are writable C-contiguous buffers.
 */

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "sumoco_capi.h" /* buffers in, module definition */

/* The subscribed variables, in the order of simulation._VEHICLE_ROW (configure sets them). */
enum { K_POS, K_ANGLE, K_SPEED, K_SIGNALS, K_LANEPOS, K_LANE, K_TYPE, K_ROUTE, NKEYS };
static PyObject *g_keys[NKEYS];
static int g_ready = 0;

/* Signals travel as float64 in the Python path (then cast to int64): exact only up to 2^53. */
#define EXACT_INT_MAX (1LL << 53)

/* float64 columns, n values each (xy interleaved, two per vehicle) */
enum { F_XY = 0, F_ANGLE = 2, F_SPEED = 3, F_LANEPOS = 4, NF = 5 };
/* int64 columns */
enum { I_SIGNALS = 0, I_LANE = 1, I_VTYPE = 2, NI = 3 };

typedef struct {
    Py_ssize_t *row;   /* vehicles whose type is not in the table yet, in their order */
    PyObject **type;   /* their type ids (new references) */
    Py_ssize_t n, cap;
} pending_t;

static void pending_free(pending_t *p) {
    for (Py_ssize_t k = 0; k < p->n; k++) Py_DECREF(p->type[k]);
    free(p->row);
    free(p->type);
    memset(p, 0, sizeof(*p));
}

static int pending_push(pending_t *p, Py_ssize_t row, PyObject *type) {
    if (p->n == p->cap) {
        Py_ssize_t cap = p->cap ? 2 * p->cap : 16;
        Py_ssize_t *r = realloc(p->row, (size_t)cap * sizeof(*r));
        if (r == NULL) return -1;
        p->row = r;
        PyObject **t = realloc(p->type, (size_t)cap * sizeof(*t));
        if (t == NULL) return -1;
        p->type = t;
        p->cap = cap;
    }
    Py_INCREF(type);
    p->row[p->n] = row;
    p->type[p->n] = type;
    p->n++;
    return 0;
}

/* A small int of an index dict. 1 ok, 0 decline. */
static int small_int(PyObject *v, int64_t *out) {
    int overflow = 0;
    long long x;
    if (!PyLong_CheckExact(v)) return 0;
    x = PyLong_AsLongLongAndOverflow(v, &overflow);
    if (overflow || (x == -1 && PyErr_Occurred())) {
        PyErr_Clear();
        return 0;
    }
    *out = (int64_t)x;
    return 1;
}

/* table[key] for an exact str key: 1 found, 2 missing, 0 decline, -1 error. */
static int lookup(PyObject *table, PyObject *key, int64_t *out) {
    PyObject *v;
    if (!PyUnicode_CheckExact(key)) return 0;
    v = PyDict_GetItemWithError(table, key);  /* borrowed */
    if (v == NULL) return PyErr_Occurred() ? -1 : 2;
    return small_int(v, out);
}

/* Row i of the columns from the variables v of one result. 1 ok, 0 decline, -1 error. */
static int take_values(PyObject **v, Py_ssize_t i, Py_ssize_t n, double *f, int64_t *c, PyObject *lanes,
                       PyObject *types, pending_t *pending, PyObject *routes) {
    PyObject *x, *y;
    int overflow = 0, rc;
    long long sig;
    int64_t idx;
    /* position: exactly two floats (the Python path flattens whatever it gets) */
    if (!PyTuple_CheckExact(v[K_POS]) || PyTuple_GET_SIZE(v[K_POS]) != 2) return 0;
    x = PyTuple_GET_ITEM(v[K_POS], 0);
    y = PyTuple_GET_ITEM(v[K_POS], 1);
    if (!PyFloat_CheckExact(x) || !PyFloat_CheckExact(y) || !PyFloat_CheckExact(v[K_ANGLE]) ||
        !PyFloat_CheckExact(v[K_SPEED]) || !PyFloat_CheckExact(v[K_LANEPOS]) || !PyLong_CheckExact(v[K_SIGNALS]) ||
        !PyUnicode_CheckExact(v[K_ROUTE]))
        return 0;
    sig = PyLong_AsLongLongAndOverflow(v[K_SIGNALS], &overflow);
    if (overflow || (sig == -1 && PyErr_Occurred()) || sig > EXACT_INT_MAX || sig < -EXACT_INT_MAX) {
        PyErr_Clear();
        return 0;
    }
    /* lane: -1 when the table does not know it (as simulation._lookup) */
    rc = lookup(lanes, v[K_LANE], &idx);
    if (rc <= 0) return rc;
    c[I_LANE * n + i] = rc == 1 ? idx : -1;
    /* type: a new one is added after the pass (in the vehicles' order), see read_vehicles */
    rc = lookup(types, v[K_TYPE], &idx);
    if (rc <= 0) return rc;
    if (rc == 2) {
        if (pending_push(pending, i, v[K_TYPE]) < 0) {
            PyErr_NoMemory();
            return -1;
        }
        idx = -1;
    }
    c[I_VTYPE * n + i] = idx;
    c[I_SIGNALS * n + i] = (int64_t)sig;
    f[F_XY * n + 2 * i] = PyFloat_AS_DOUBLE(x);
    f[F_XY * n + 2 * i + 1] = PyFloat_AS_DOUBLE(y);
    f[F_ANGLE * n + i] = PyFloat_AS_DOUBLE(v[K_ANGLE]);
    f[F_SPEED * n + i] = PyFloat_AS_DOUBLE(v[K_SPEED]);
    f[F_LANEPOS * n + i] = PyFloat_AS_DOUBLE(v[K_LANEPOS]);
    Py_INCREF(v[K_ROUTE]);
    PyList_SET_ITEM(routes, i, v[K_ROUTE]);
    return 1;
}

/* One result dict into row i of the columns. 1 ok, 0 decline, -1 error. The values are held
 * while they are read (a lookup in the caller's dicts may run Python code). */
static int take_row(PyObject *r, Py_ssize_t i, Py_ssize_t n, double *f, int64_t *c, PyObject *lanes,
                    PyObject *types, pending_t *pending, PyObject *routes) {
    PyObject *v[NKEYS];
    int k, rc;
    if (!PyDict_CheckExact(r)) return 0;
    for (k = 0; k < NKEYS; k++) {
        v[k] = PyDict_GetItemWithError(r, g_keys[k]);  /* borrowed */
        if (v[k] == NULL) break;
        Py_INCREF(v[k]);
    }
    rc = k < NKEYS ? (PyErr_Occurred() ? -1 : 0) : take_values(v, i, n, f, c, lanes, types, pending, routes);
    while (k-- > 0) Py_DECREF(v[k]);
    return rc;
}

/* A writable C-contiguous float64 / int64 column block of exactly `bytes` bytes. */
static int get_columns(PyObject *obj, sc_buf *b, char kind, Py_ssize_t bytes, const char *name) {
    if (!sc_get(obj, b, name, kind, 1, 0)) return -1;
    if (b->v.len != bytes) {
        PyErr_Format(PyExc_ValueError, "%s: expected a writable buffer of %zd bytes, 8-byte items", name, bytes);
        sc_release(b);
        return -1;
    }
    return 0;
}

static PyObject *py_read_vehicles(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    PyObject *get, *vids, *lanes, *types, *add, *routes = NULL, *out = NULL;
    sc_buf fb = {0}, ib = {0};
    pending_t pending = {0};
    Py_ssize_t n;
    double *f;
    int64_t *c;
    (void)self;
    if (nargs != 7) {
        PyErr_SetString(PyExc_TypeError,
                        "read_vehicles(get, vids, lane_index, type_index, add_type, floats, ints)");
        return NULL;
    }
    get = args[0], vids = args[1], lanes = args[2], types = args[3], add = args[4];
    if (!g_ready) {
        PyErr_SetString(PyExc_RuntimeError, "configure() first");
        return NULL;
    }
    if (!PyList_CheckExact(vids) || !PyDict_CheckExact(lanes) || !PyDict_CheckExact(types)) {
        PyErr_SetString(PyExc_TypeError, "vids: list, lane_index and type_index: dict");
        return NULL;
    }
    n = PyList_GET_SIZE(vids);
    if (n > PY_SSIZE_T_MAX / (8 * NF)) return PyErr_NoMemory();
    if (get_columns(args[5], &fb, SC_F64, 8 * NF * n, "floats") < 0 ||
        get_columns(args[6], &ib, SC_I64, 8 * NI * n, "ints") < 0)
        goto done;
    f = (double *)fb.v.buf;
    c = (int64_t *)ib.v.buf;
    routes = PyList_New(n);
    if (routes == NULL) goto done;
    for (Py_ssize_t i = 0; i < n; i++) {
        PyObject *vid, *r;
        int rc;
        if (i >= PyList_GET_SIZE(vids)) goto decline;  /* the list changed under us */
        vid = PyList_GET_ITEM(vids, i);
        Py_INCREF(vid);
        r = PyObject_CallOneArg(get, vid);
        Py_DECREF(vid);
        if (r == NULL) goto done;
        rc = take_row(r, i, n, f, c, lanes, types, &pending, routes);
        Py_DECREF(r);  /* freed now: the next result reuses its memory */
        if (rc < 0) goto done;
        if (rc == 0) goto decline;
    }
    /* New types, only now that every row was taken (declining leaves no trace): add_type
     * per vehicle in the vehicles' order, as VTypeTable.indices does once a type is new
     * (it returns the index of a type known already, also one added here before). */
    for (Py_ssize_t k = 0; k < pending.n; k++) {
        PyObject *res = PyObject_CallOneArg(add, pending.type[k]);
        long long idx;
        if (res == NULL) goto done;
        idx = PyLong_AsLongLong(res);
        Py_DECREF(res);
        if (idx == -1 && PyErr_Occurred()) goto done;
        c[I_VTYPE * n + pending.row[k]] = (int64_t)idx;
    }
    out = routes;
    routes = NULL;
    goto done;
decline:
    out = Py_None;
    Py_INCREF(out);
done:
    Py_XDECREF(routes);  /* unfilled slots are NULL, which list dealloc skips */
    pending_free(&pending);
    SC_RELEASE(&fb, &ib);
    return out;
}

static PyObject *py_configure(PyObject *self, PyObject *keys) {
    (void)self;
    if (!PyTuple_CheckExact(keys) || PyTuple_GET_SIZE(keys) != NKEYS) {
        PyErr_Format(PyExc_ValueError, "configure: expected a tuple of %d variable ids", NKEYS);
        return NULL;
    }
    for (int k = 0; k < NKEYS; k++) {
        PyObject *key = PyTuple_GET_ITEM(keys, k);
        PyObject *old = g_keys[k];
        Py_INCREF(key);
        g_keys[k] = key;
        Py_XDECREF(old);
    }
    g_ready = 1;
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"configure", py_configure, METH_O,
     "configure(keys): the variable ids of position, angle, speed, signals, lane position, lane, "
     "type and route, in this order."},
    {"read_vehicles", (PyCFunction)(void (*)(void))py_read_vehicles, METH_FASTCALL,
     "read_vehicles(get, vids, lane_index, type_index, add_type, floats, ints) -> list | None: "
     "get(vid) per vehicle into the columns (floats: xy pairs, angle, speed, lane position; ints: "
     "signals, lane index (-1 unknown), type index (add_type(t) for a type not in type_index)); "
     "the route ids, or None: use the Python path."},
    {NULL, NULL, 0, NULL},
};

SC_MODULE(PyInit__fastread, "sumo_side._fastread",
          "C fast path of sumo_side.simulation's vehicle read (None: use the Python path).", methods)
