/* What every optional C fast path shares (protocol/, sumo_side/, physics_side/): arrays in
 * through the buffer protocol with their item type checked, their release, and the module
 * definition. Plain CPython C API, no numpy headers; include after <Python.h>.
 *
 * Its own folder because the extensions live in every layer, from the protocol up, and a
 * header in one of them would point the others' includes the wrong way.
 */
#ifndef SUMOCO_CAPI_H
#define SUMOCO_CAPI_H

#include <Python.h>

/* An array argument: a view and whether it is held (released once, on every path). */
typedef struct {
    Py_buffer v;
    int held;
} sc_buf;

static inline void sc_release(sc_buf *b) {
    if (b->held) PyBuffer_Release(&b->v);
    b->held = 0;
}

static inline void sc_release_all(sc_buf *b, int count) {
    for (int k = 0; k < count; k++) sc_release(&b[k]);
}

/* Release every buffer named: SC_RELEASE(&a, &b, ...) at a function's one exit. */
#define SC_RELEASE(...)                                                                   \
    do {                                                                                  \
        sc_buf *sc_bufs_[] = {__VA_ARGS__};                                               \
        for (size_t sc_k_ = 0; sc_k_ < sizeof sc_bufs_ / sizeof sc_bufs_[0]; sc_k_++)      \
            sc_release(sc_bufs_[sc_k_]);                                                  \
    } while (0)

/* item kinds of sc_get */
#define SC_F64 'f'  /* float64 */
#define SC_I64 'i'  /* int64 */
#define SC_BOOL 'b' /* bool or uint8 */

static inline const char *sc_kind_name(char kind) {
    return kind == SC_F64 ? "float64" : kind == SC_I64 ? "int64" : "bool";
}

/* ``o``'s buffer into ``b``: items of ``kind``, C-contiguous unless ``strided`` (any strides,
 * e.g. np.broadcast_to), writable when ``writable``. Raises (naming the argument ``name``)
 * and returns 0 otherwise, with nothing held. Dimensions are the caller's to check. */
static int sc_get(PyObject *o, sc_buf *b, const char *name, char kind, int writable, int strided) {
    const int flags = PyBUF_FORMAT | (strided ? PyBUF_STRIDES : PyBUF_C_CONTIGUOUS) | (writable ? PyBUF_WRITABLE : 0);
    const char *f;
    int ok;
    b->held = 0;
    if (PyObject_GetBuffer(o, &b->v, flags) < 0) {
        PyErr_Format(PyExc_TypeError, "%s: needs a%s%s array (got %.100s)", name, writable ? " writable" : "",
                     strided ? "" : " C-contiguous", Py_TYPE(o)->tp_name);
        return 0;
    }
    b->held = 1;
    f = b->v.format ? b->v.format : "B";
    if (*f == '<' || *f == '=' || *f == '@') f++;
    ok = f[0] != '\0' && f[1] == '\0';
    if (kind == SC_F64)
        ok = ok && b->v.itemsize == 8 && f[0] == 'd';
    else if (kind == SC_I64)
        ok = ok && b->v.itemsize == 8 && (f[0] == 'q' || f[0] == 'l');
    else
        ok = ok && b->v.itemsize == 1 && (f[0] == '?' || f[0] == 'B');
    if (!ok) {
        PyErr_Format(PyExc_TypeError, "%s: needs %s items (got format '%s', %zd bytes)", name, sc_kind_name(kind),
                     b->v.format ? b->v.format : "B", b->v.itemsize);
        sc_release(b);
        return 0;
    }
    return 1;
}

/* Has ``b`` ``ndim`` dimensions (1 or 2) of sizes d0 (, d1)? Raises ValueError otherwise. */
static int sc_shape(const sc_buf *b, const char *name, int ndim, Py_ssize_t d0, Py_ssize_t d1) {
    if (b->v.ndim != ndim || b->v.shape[0] != d0 || (ndim > 1 && b->v.shape[1] != d1)) {
        if (ndim == 1)
            PyErr_Format(PyExc_ValueError, "%s: needs shape (%zd,)", name, d0);
        else
            PyErr_Format(PyExc_ValueError, "%s: needs shape (%zd, %zd)", name, d0, d1);
        return 0;
    }
    return 1;
}

/* Has ``b`` ``ndim`` dimensions? Raises ValueError otherwise. */
static int sc_ndim(const sc_buf *b, const char *name, int ndim) {
    if (b->v.ndim != ndim) {
        PyErr_Format(PyExc_ValueError, "%s: needs %d dimension%s (got %d)", name, ndim, ndim == 1 ? "" : "s",
                     b->v.ndim);
        return 0;
    }
    return 1;
}

/* The module object of an extension: SC_MODULE(PyInit__name, "package._name", doc, methods). */
#define SC_MODULE(init, dotted, doc, methods)                                                             \
    static struct PyModuleDef sc_module_def = {PyModuleDef_HEAD_INIT, dotted, doc, -1, methods,            \
                                               NULL, NULL, NULL, NULL};                                    \
    PyMODINIT_FUNC init(void) { return PyModule_Create(&sc_module_def); }

#endif
