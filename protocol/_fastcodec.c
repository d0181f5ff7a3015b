/* Fast path of protocol.codec for the two hot messages, step and physics.
 *
 * decode: one pass over the msgpack bytes that applies every check of the Python decoder
 *   and returns the raw material of the message (scalars, id lists, one bytearray holding
 *   every column). On anything unexpected -- a failed check, an unknown key, another
 *   layout, a value this code does not handle -- it returns None and protocol.codec runs
 *   the Python decoder, which raises the canonical ProtocolError. So nothing here builds
 *   error messages: rejecting too much only costs time, accepting too much would be a bug.
 * encode: the bytes msgpack.packb(protocol.codec._encode_*(msg), use_bin_type=True)
 *   produces, written into one buffer of exactly the right size (a counting pass first).
 *   None when an input is not what this code expects (the caller then casts the arrays
 *   or runs the Python encoder).
 *
 * Plain CPython C API. Every read of the input is checked against its length (the bytes
 * come from the network). Little-endian hosts only: both the wire columns and numpy's
 * arrays are then the same bytes (elsewhere every function returns None).
 */

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <float.h>
#include <stdint.h>
#include <string.h>

#include "sumoco_capi.h" /* module definition */

/* ------------------------------------------------------------------ configuration */

/* The wire's major version and the column bounds, handed over by protocol.codec at import
 * (configure), so that FLOAT_BOUNDS and INT_BOUNDS stay the one source of truth. */
static int g_ready = 0;
static int64_t g_major = -1;

typedef struct {
    const char *name;
    char kind;      /* 'f' float, 'i' signed, 'u' unsigned */
    int size;       /* bytes per value */
    int bounded;    /* float: always (FLOAT_BOUNDS or any finite); int: only when in INT_BOUNDS */
    double lo, hi;  /* inclusive */
} column_t;

#define FINITE_MAX DBL_MAX  /* the bounds of "any finite value" */

/* bits of the largest float32 within la_dx's bound (the path offsets', set by configure) */
static uint32_t g_path_lim_bits = 0;

#define STEP_NCOL 14
static column_t STEP_COLS[STEP_NCOL] = {  /* STEP_AGENT_COLUMNS, in its order */
    {"cls", 'u', 1, 0, 0, 0}, {"vtype", 'u', 2, 0, 0, 0}, {"x", 'f', 8, 0, 0, 0}, {"y", 'f', 8, 0, 0, 0},
    {"angle", 'f', 4, 0, 0, 0}, {"speed", 'f', 4, 0, 0, 0}, {"accel", 'f', 4, 0, 0, 0},
    {"signals", 'u', 2, 0, 0, 0}, {"la_dx", 'f', 4, 0, 0, 0}, {"la_dy", 'f', 4, 0, 0, 0},
    {"length", 'f', 4, 0, 0, 0}, {"width", 'f', 4, 0, 0, 0}, {"lane", 'i', 4, 0, 0, 0}, {"flags", 'u', 1, 0, 0, 0},
};
enum { S_CLS, S_VTYPE, S_X, S_Y, S_ANGLE, S_SPEED, S_ACCEL, S_SIGNALS, S_LADX, S_LADY, S_LENGTH, S_WIDTH,
       S_LANE, S_FLAGS };

#define PHYS_NCOL 14
static column_t PHYS_COLS[PHYS_NCOL] = {  /* PHYSICS_AGENT_COLUMNS, in its order */
    {"cls", 'u', 1, 0, 0, 0}, {"mode", 'u', 1, 0, 0, 0}, {"x", 'f', 8, 0, 0, 0}, {"y", 'f', 8, 0, 0, 0},
    {"z", 'f', 4, 0, 0, 0}, {"heading", 'f', 4, 0, 0, 0}, {"roll", 'f', 4, 0, 0, 0}, {"pitch", 'f', 4, 0, 0, 0},
    {"speed", 'f', 4, 0, 0, 0}, {"steer", 'f', 4, 0, 0, 0}, {"drive", 'f', 4, 0, 0, 0}, {"brake", 'f', 4, 0, 0, 0},
    {"err_lon", 'f', 4, 0, 0, 0}, {"err_lat", 'f', 4, 0, 0, 0},
};

/* Bounds of values outside the column tables (protocol.codec: STEP_FIELDS, _decode_tls,
 * Reader.path); the equality and fallback tests pin them to the Python decoder. */
#define DT_LO 1e-6          /* [s] step length */
#define DT_HI 3600.0        /* [s] */
#define TLS_NEXT_LIM 1e9    /* [s] time to the next switch */
#define TLS_PHASE_HI 2147483647.0
#define MAX_VTYPES 65535    /* u16 index */
#define MAX_MAP 4096        /* msgpack max_map_len of DecodeLimits */
#define MAX_DEPTH 32        /* nesting skipped while looking for keys; the messages use 4 */

/* Loops the compiler vectorises stay out of line: inlined into the large decode function,
 * GCC leaves them scalar. */
#if defined(__GNUC__)
#define NOINLINE __attribute__((noinline))
#else
#define NOINLINE
#endif

static int host_is_little(void) {
    const uint16_t one = 1;
    uint8_t b;
    memcpy(&b, &one, 1);
    return b == 1;
}

/* ------------------------------------------------------------------ reading */

typedef struct {
    const uint8_t *p;
    size_t len, pos;        /* invariant: pos <= len */
    size_t max_str_bytes;   /* the msgpack limits of DecodeLimits._limits_kw */
    size_t max_bin;
    size_t max_array;
} rd_t;

static int rd_byte(rd_t *r, uint8_t *b) {
    if (r->pos >= r->len) return 0;
    *b = r->p[r->pos++];
    return 1;
}

static int rd_peek(const rd_t *r, uint8_t *b) {
    if (r->pos >= r->len) return 0;
    *b = r->p[r->pos];
    return 1;
}

static int rd_be(rd_t *r, size_t k, uint64_t *v) {  /* k <= 8 big-endian bytes */
    if (r->len - r->pos < k) return 0;
    uint64_t x = 0;
    for (size_t i = 0; i < k; i++) x = (x << 8) | r->p[r->pos + i];
    r->pos += k;
    *v = x;
    return 1;
}

static int rd_take(rd_t *r, uint64_t n, const uint8_t **s) {  /* n bytes of payload */
    if (n > r->len - r->pos) return 0;
    *s = r->p + r->pos;
    r->pos += (size_t)n;
    return 1;
}

static int rd_str(rd_t *r, const char **s, size_t *n) {
    uint8_t t;
    uint64_t L;
    const uint8_t *q;
    if (!rd_byte(r, &t)) return 0;
    if ((t & 0xe0) == 0xa0) L = t & 0x1f;
    else if (t == 0xd9) { if (!rd_be(r, 1, &L)) return 0; }
    else if (t == 0xda) { if (!rd_be(r, 2, &L)) return 0; }
    else if (t == 0xdb) { if (!rd_be(r, 4, &L)) return 0; }
    else return 0;
    if (L > r->max_str_bytes || !rd_take(r, L, &q)) return 0;
    *s = (const char *)q;
    *n = (size_t)L;
    return 1;
}

static int rd_bin(rd_t *r, const uint8_t **s, size_t *n) {
    uint8_t t;
    uint64_t L;
    if (!rd_byte(r, &t)) return 0;
    if (t == 0xc4) { if (!rd_be(r, 1, &L)) return 0; }
    else if (t == 0xc5) { if (!rd_be(r, 2, &L)) return 0; }
    else if (t == 0xc6) { if (!rd_be(r, 4, &L)) return 0; }
    else return 0;
    if (L > r->max_bin || !rd_take(r, L, s)) return 0;
    *n = (size_t)L;
    return 1;
}

static int rd_array(rd_t *r, size_t *n) {
    uint8_t t;
    uint64_t L;
    if (!rd_byte(r, &t)) return 0;
    if ((t & 0xf0) == 0x90) L = t & 0x0f;
    else if (t == 0xdc) { if (!rd_be(r, 2, &L)) return 0; }
    else if (t == 0xdd) { if (!rd_be(r, 4, &L)) return 0; }
    else return 0;
    if (L > r->max_array || L > r->len - r->pos) return 0;  /* every item takes a byte at least */
    *n = (size_t)L;
    return 1;
}

static int rd_map(rd_t *r, size_t *n) {
    uint8_t t;
    uint64_t L;
    if (!rd_byte(r, &t)) return 0;
    if ((t & 0xf0) == 0x80) L = t & 0x0f;
    else if (t == 0xde) { if (!rd_be(r, 2, &L)) return 0; }
    else if (t == 0xdf) { if (!rd_be(r, 4, &L)) return 0; }
    else return 0;
    if (L > MAX_MAP || L > (r->len - r->pos) / 2) return 0;
    *n = (size_t)L;
    return 1;
}

static int64_t sign_extend(uint64_t x, int bits) {
    uint64_t sign = (uint64_t)1 << (bits - 1);
    if (x & sign) {
        /* -(2^bits - x), written without overflowing int64 */
        uint64_t mag = (bits == 64) ? (~x + 1) : (((uint64_t)1 << bits) - x);
        if (mag == ((uint64_t)1 << 63)) return INT64_MIN;
        return -(int64_t)mag;
    }
    return (int64_t)x;
}

/* A msgpack integer. *big: an unsigned value above INT64_MAX (then *v is INT64_MAX). */
static int rd_int(rd_t *r, int64_t *v, int *big) {
    uint8_t t;
    uint64_t x;
    *big = 0;
    if (!rd_byte(r, &t)) return 0;
    if (t <= 0x7f) { *v = t; return 1; }
    if (t >= 0xe0) { *v = (int64_t)t - 256; return 1; }
    switch (t) {
    case 0xcc: if (!rd_be(r, 1, &x)) return 0; *v = (int64_t)x; return 1;
    case 0xcd: if (!rd_be(r, 2, &x)) return 0; *v = (int64_t)x; return 1;
    case 0xce: if (!rd_be(r, 4, &x)) return 0; *v = (int64_t)x; return 1;
    case 0xcf:
        if (!rd_be(r, 8, &x)) return 0;
        if (x > (uint64_t)INT64_MAX) { *big = 1; *v = INT64_MAX; }
        else *v = (int64_t)x;
        return 1;
    case 0xd0: if (!rd_be(r, 1, &x)) return 0; *v = sign_extend(x, 8); return 1;
    case 0xd1: if (!rd_be(r, 2, &x)) return 0; *v = sign_extend(x, 16); return 1;
    case 0xd2: if (!rd_be(r, 4, &x)) return 0; *v = sign_extend(x, 32); return 1;
    case 0xd3: if (!rd_be(r, 8, &x)) return 0; *v = sign_extend(x, 64); return 1;
    default: return 0;
    }
}

/* An integer in lo..hi (a big unsigned value is above every hi used here). */
static int rd_int_in(rd_t *r, int64_t lo, int64_t hi, int64_t *v) {
    int big;
    return rd_int(r, v, &big) && !big && *v >= lo && *v <= hi;
}

static int is_float_tag(uint8_t t) { return t == 0xca || t == 0xcb; }

static int rd_float(rd_t *r, double *d) {
    uint8_t t;
    uint64_t x;
    if (!rd_byte(r, &t)) return 0;
    if (t == 0xca) {
        float f;
        uint32_t u;
        if (!rd_be(r, 4, &x)) return 0;
        u = (uint32_t)x;
        memcpy(&f, &u, 4);
        *d = (double)f;
        return 1;
    }
    if (t == 0xcb) {
        if (!rd_be(r, 8, &x)) return 0;
        memcpy(d, &x, 8);
        return 1;
    }
    return 0;
}

static int rd_bool(rd_t *r, int *b) {
    uint8_t t;
    if (!rd_byte(r, &t)) return 0;
    if (t == 0xc2 || t == 0xc3) { *b = (t == 0xc3); return 1; }
    return 0;
}

/* Skip one value (every length checked against the limits, as msgpack would). */
static int rd_skip(rd_t *r, int depth) {
    uint8_t t;
    size_t n;
    const char *s;
    const uint8_t *b;
    double d;
    int64_t v;
    int big;
    if (depth > MAX_DEPTH || !rd_peek(r, &t)) return 0;
    if (t <= 0x7f || t >= 0xe0 || (t >= 0xcc && t <= 0xd3)) return rd_int(r, &v, &big);
    if (t == 0xc0 || t == 0xc2 || t == 0xc3) { r->pos++; return 1; }
    if (is_float_tag(t)) return rd_float(r, &d);
    if ((t & 0xe0) == 0xa0 || (t >= 0xd9 && t <= 0xdb)) return rd_str(r, &s, &n);
    if (t >= 0xc4 && t <= 0xc6) return rd_bin(r, &b, &n);
    if ((t & 0xf0) == 0x90 || t == 0xdc || t == 0xdd) {
        if (!rd_array(r, &n)) return 0;
        for (size_t i = 0; i < n; i++) {
            uint8_t e;
            if (!rd_peek(r, &e)) return 0;
            if ((e & 0xe0) == 0xa0 && (size_t)(e & 0x1f) <= r->max_str_bytes) {  /* fixstr: ids */
                if ((size_t)(e & 0x1f) >= r->len - r->pos) return 0;
                r->pos += 1 + (size_t)(e & 0x1f);
            } else if (!rd_skip(r, depth + 1)) {
                return 0;
            }
        }
        return 1;
    }
    if ((t & 0xf0) == 0x80 || t == 0xde || t == 0xdf) {
        if (!rd_map(r, &n)) return 0;
        for (size_t i = 0; i < n; i++) {
            uint8_t k;
            size_t klen;
            if (!rd_peek(r, &k)) return 0;
            /* strict_map_key: str or bytes keys only */
            if ((k & 0xe0) == 0xa0 || (k >= 0xd9 && k <= 0xdb)) { if (!rd_str(r, &s, &klen)) return 0; }
            else if (k >= 0xc4 && k <= 0xc6) { if (!rd_bin(r, &b, &klen)) return 0; }
            else return 0;
            if (!rd_skip(r, depth + 1)) return 0;
        }
        return 1;
    }
    return 0;  /* ext types (none on this wire) and the unused 0xc1 */
}

#define ABSENT SIZE_MAX

typedef struct {
    const char *s;
    size_t n;
} name_t;
#define NAME(s) {s, sizeof(s) - 1}

/* Reads the value of key `j` in place when it is a map scanned with its own keys: 1 read,
 * 0 failed, -1 not such a key (the caller skips the value). */
typedef int (*nest_fn)(rd_t *r, int j, void *ctx);

/* A map whose keys are all among `names` (each at most once): the position of each value
 * (ABSENT when missing). An unknown or repeated key fails (the Python decoder ignores
 * unknown keys and msgpack keeps the last of repeated ones: that is its business). */
static int rd_keys(rd_t *r, const name_t *names, int count, size_t *pos, nest_fn nest, void *ctx) {
    size_t n;
    if (!rd_map(r, &n)) return 0;
    for (int j = 0; j < count; j++) pos[j] = ABSENT;
    for (size_t i = 0; i < n; i++) {
        const char *s;
        size_t len;
        int j, k;
        if (!rd_str(r, &s, &len)) return 0;
        for (j = 0; j < count; j++)
            if (names[j].n == len && memcmp(names[j].s, s, len) == 0) break;
        if (j == count || pos[j] != ABSENT) return 0;
        pos[j] = r->pos;
        k = nest != NULL ? nest(r, j, ctx) : -1;
        if (k == 0 || (k < 0 && !rd_skip(r, 1))) return 0;
    }
    return 1;
}

static int rd_at(rd_t *r, size_t pos) {  /* move to a value found by rd_keys */
    if (pos == ABSENT || pos > r->len) return 0;
    r->pos = pos;
    return 1;
}

/* ------------------------------------------------------------------ strings */

/* A str of at most max_chars characters (strict UTF-8, as msgpack with raw=False), or NULL
 * with no exception set. */
static PyObject *mk_str(const char *s, size_t n, Py_ssize_t max_chars) {
    PyObject *u = PyUnicode_DecodeUTF8(s, (Py_ssize_t)n, NULL);
    if (u == NULL) {
        PyErr_Clear();
        return NULL;
    }
    /* UTF-8 takes a byte per character at least: short byte strings need no count */
    if ((Py_ssize_t)n > max_chars && PyUnicode_GET_LENGTH(u) > max_chars) {
        Py_DECREF(u);
        return NULL;
    }
    return u;
}

/* Uniqueness of a list of str: open addressing over their hashes. PyObject_Hash caches the
 * hash in each str, as the Python decoder's set() does, so the ids are as cheap to use as
 * dict keys later. Slots hold list index + 1 (0: empty). */
static int unique_strs(PyObject *list) {
    Py_ssize_t n = PyList_GET_SIZE(list);
    size_t cap = 8, mask;
    uint32_t *slots;
    int ok = 1;
    if (n < 2) return 1;
    if ((size_t)n > 0x7fffffffu) return 0;
    while (cap < 2 * (size_t)n) cap <<= 1;
    slots = (uint32_t *)PyMem_Calloc(cap, sizeof(uint32_t));
    if (slots == NULL) return 0;
    mask = cap - 1;
    for (Py_ssize_t i = 0; i < n && ok; i++) {
        PyObject *u = PyList_GET_ITEM(list, i);
        Py_hash_t h = PyObject_Hash(u);
        size_t k = (size_t)h & mask;
        Py_ssize_t len = PyUnicode_GET_LENGTH(u);
        int kind = PyUnicode_KIND(u);
        if (h == -1) {
            ok = 0;
            break;
        }
        while (slots[k] != 0) {
            PyObject *v = PyList_GET_ITEM(list, (Py_ssize_t)slots[k] - 1);
            /* equal strings have the same canonical (compact) form: kind, length, bytes */
            if (PyObject_Hash(v) == h && PyUnicode_GET_LENGTH(v) == len && PyUnicode_KIND(v) == kind &&
                memcmp(PyUnicode_DATA(v), PyUnicode_DATA(u), (size_t)len * (size_t)kind) == 0) {
                ok = 0;
                break;
            }
            k = (k + 1) & mask;
        }
        slots[k] = (uint32_t)i + 1;
    }
    PyMem_Free(slots);
    return ok;
}

/* mk_str for the common case of an ASCII string: no decoder call. */
static PyObject *mk_str_fast(const char *s, size_t n, Py_ssize_t max_chars) {
    PyObject *u;
    size_t i;
    for (i = 0; i < n; i++)
        if ((uint8_t)s[i] & 0x80) return mk_str(s, n, max_chars);
    if ((Py_ssize_t)n > max_chars) return NULL;
    u = PyUnicode_New((Py_ssize_t)n, 127);
    if (u == NULL) {
        PyErr_Clear();
        return NULL;
    }
    if (n) memcpy(PyUnicode_DATA(u), s, n);
    return u;
}

/* The id cache: the str objects of recent ids, by their bytes. Vehicle ids repeat from step
 * to step: a hit costs a hash of a few bytes instead of an allocation, a copy and a siphash
 * (the cached str keeps its hash). ASCII ids of at most 31 bytes only (msgpack fixstr).
 * Bounded: when a list would fill it over half, it is emptied first. Each cached str is
 * the one object of its text, so ids from the cache are unique when their pointers are. */
typedef struct {
    uint64_t h;
    PyObject *str;  /* owned; NULL: empty slot */
    uint32_t len;
} idslot_t;

/* Bounds: 2^18 slots of 24 bytes (6 MiB) holding at most 2^17 strings (~7 MiB), whatever a
 * peer sends; a list of more than 2^16 ids goes without the cache. */
#define ID_CACHE_MIN 4096               /* slots */
#define ID_CACHE_MAX ((size_t)1 << 18)  /* slots */
#define ID_MAX_BYTES 31

static idslot_t *g_ids = NULL;
static size_t g_ids_cap = 0, g_ids_used = 0;

/* The previous id list of a step and of a physics state, in order: the next one is mostly the
 * same ids in the same order, compared byte for byte here (sequential memory) instead of
 * looked up. Pointers borrowed from the cache (dropped with it). */
typedef struct {
    PyObject **str;  /* NULL: that id was not cached */
    uint8_t *len;
    char *bytes;     /* ID_MAX_BYTES per id */
    size_t n, cap;
} prev_t;

#define PREV_STEP 0
#define PREV_PHYSICS 1
#define PREV_NONE (-1)
#define PREV_WINDOW 4  /* previous ids tried per id */
static prev_t g_prev[2];

static void id_cache_clear(void) {
    for (size_t i = 0; i < g_ids_cap; i++) Py_CLEAR(g_ids[i].str);
    PyMem_Free(g_ids);
    g_ids = NULL;
    g_ids_cap = g_ids_used = 0;
    for (int k = 0; k < 2; k++) g_prev[k].n = 0;  /* their pointers were the cache's */
}

/* Room for `n` new ids at under half load; 0: no cache for this list. */
static int id_cache_ready(size_t n) {
    size_t cap = ID_CACHE_MIN;
    if (n > ID_CACHE_MAX / 4) return 0;
    while (cap < 4 * n) cap <<= 1;
    if (g_ids == NULL || cap > g_ids_cap || 2 * (g_ids_used + n) > g_ids_cap) {
        if (g_ids != NULL && cap <= g_ids_cap) cap = g_ids_cap;  /* keep the size, drop the entries */
        id_cache_clear();
        g_ids = (idslot_t *)PyMem_Calloc(cap, sizeof(idslot_t));
        if (g_ids == NULL) return 0;
        g_ids_cap = cap;
    }
    return 1;
}

static uint64_t id_hash(const char *s, size_t n) {  /* a multiply-xor mix of 8-byte words */
    uint64_t h = 0x9e3779b97f4a7c15ULL ^ (uint64_t)n, w;
    for (; n >= 8; s += 8, n -= 8) {
        memcpy(&w, s, 8);
        h = (h ^ w) * 0xff51afd7ed558ccdULL;
        h ^= h >> 32;
    }
    if (n > 0) {
        w = 0;
        for (size_t i = 0; i < n; i++) w |= (uint64_t)(uint8_t)s[i] << (8 * i);
        h = (h ^ w) * 0xff51afd7ed558ccdULL;
        h ^= h >> 32;
    }
    return h;
}

static int same_bytes(const char *a, const char *b, size_t n) {  /* short: no library call */
    for (size_t i = 0; i < n; i++)
        if (a[i] != b[i]) return 0;
    return 1;
}

static int is_ascii(const char *s, size_t n) {
    for (size_t i = 0; i < n; i++)
        if ((uint8_t)s[i] & 0x80) return 0;
    return 1;
}

/* The cached str of ASCII bytes s[0:n] (n <= ID_MAX_BYTES; a borrowed reference), made and
 * cached when new; NULL when it cannot be made. */
static PyObject *id_cached(const char *s, size_t n) {
    uint64_t h = id_hash(s, n);
    size_t k = (size_t)h & (g_ids_cap - 1);
    for (;;) {
        idslot_t *e = &g_ids[k];
        if (e->str == NULL) {
            PyObject *u = PyUnicode_New((Py_ssize_t)n, 127);
            if (u == NULL) {
                PyErr_Clear();
                return NULL;
            }
            if (n) memcpy(PyUnicode_DATA(u), s, n);
            if (PyObject_Hash(u) == -1) {  /* computed once, kept in the str */
                PyErr_Clear();
                Py_DECREF(u);
                return NULL;
            }
            e->h = h;
            e->str = u;
            e->len = (uint32_t)n;
            g_ids_used++;
            return u;
        }
        if (e->h == h && e->len == n && same_bytes((const char *)PyUnicode_DATA(e->str), s, n)) return e->str;
        k = (k + 1) & (g_ids_cap - 1);
    }
}

static int prev_reserve(prev_t *p, size_t n) {
    if (n <= p->cap) return 1;
    PyMem_Free(p->str);
    PyMem_Free(p->len);
    PyMem_Free(p->bytes);
    p->cap = p->n = 0;
    p->str = (PyObject **)PyMem_Calloc(n, sizeof(PyObject *));
    p->len = (uint8_t *)PyMem_Calloc(n, 1);
    p->bytes = (char *)PyMem_Calloc(n, ID_MAX_BYTES);
    if (p->str == NULL || p->len == NULL || p->bytes == NULL) return 0;
    p->cap = n;
    return 1;
}

/* Set of pointers (open addressing, 0 = empty): distinct cached strs are distinct ids. */
static int ptrset_add(uintptr_t *t, size_t mask, uintptr_t v) {
    size_t k = (size_t)(((uint64_t)v * 0x9e3779b97f4a7c15ULL) >> 32) & mask;
    while (t[k] != 0) {
        if (t[k] == v) return 0;
        k = (k + 1) & mask;
    }
    t[k] = v;
    return 1;
}

/* An array of `want` strings (any count when want < 0) of at most max_chars characters,
 * unique when asked: a new list, or NULL with no exception set. Unique lists (ids) go
 * through the id cache; `prev` names the previous list of the same kind (PREV_NONE). */
static PyObject *rd_strs(rd_t *r, Py_ssize_t want, int unique, Py_ssize_t max_chars, int prev) {
    size_t n, j = 0;
    PyObject *list;
    prev_t *p = NULL, *rec = NULL;
    int cache, all_cached = 1, cache_failed = 0, looked_up = 0;
    if (!rd_array(r, &n) || (want >= 0 && n != (size_t)want)) return NULL;
    list = PyList_New((Py_ssize_t)n);
    if (list == NULL) {
        PyErr_Clear();
        return NULL;
    }
    cache = unique && n > 0 && max_chars >= ID_MAX_BYTES && id_cache_ready(n);
    if (cache && prev != PREV_NONE) {
        p = &g_prev[prev];
        /* the new list is recorded as it goes, in arrays of its own when the old are read */
        rec = p;
    }
    for (size_t i = 0; i < n; i++) {
        const char *s;
        size_t len;
        PyObject *u = NULL;
        if (!rd_str(r, &s, &len)) goto fail;
        if (cache && len <= ID_MAX_BYTES) {
            /* the same id as the previous list's next one, or one of the few after it (vehicles
             * left); else (a vehicle arrived, or another order) the cache */
            if (p != NULL)
                for (size_t k = j; k < p->n && k < j + PREV_WINDOW; k++)
                    if (p->len[k] == len && same_bytes(p->bytes + k * ID_MAX_BYTES, s, len)) {
                        u = p->str[k];
                        j = k + 1;
                        break;
                    }
            if (u == NULL && is_ascii(s, len)) {
                u = id_cached(s, len);
                cache_failed |= u == NULL;
                looked_up = 1;
            }
#if defined(__GNUC__)
            if (p != NULL && j + 8 < p->n && p->str[j + 8] != NULL) __builtin_prefetch(p->str[j + 8], 1);
#endif
            if (u != NULL) Py_INCREF(u);
        }
        if (u == NULL) {
            all_cached = 0;
            u = mk_str_fast(s, len, max_chars);
            if (u == NULL) goto fail;
        }
        PyList_SET_ITEM(list, (Py_ssize_t)i, u);
    }
    /* Uniqueness. Ids taken from the previous list only are unique already: that list was,
     * and its entries were taken at rising positions. Cached ids are unique when their
     * pointers are (one str per text); any other id needs the full check. */
    if (unique && cache && all_cached && looked_up) {
        size_t cap = 8, mask;
        uintptr_t *seen;
        int dup = 0;
        while (cap < 2 * n) cap <<= 1;
        seen = (uintptr_t *)PyMem_Calloc(cap, sizeof(uintptr_t));
        if (seen == NULL) goto fail;
        mask = cap - 1;
        for (size_t i = 0; i < n && !dup; i++) dup = !ptrset_add(seen, mask, (uintptr_t)PyList_GET_ITEM(list, (Py_ssize_t)i));
        PyMem_Free(seen);
        if (dup) goto fail;
    }
    if (unique && !(cache && all_cached) && !unique_strs(list)) goto fail;
    if (rec != NULL) {  /* this list is the next one's previous (its short ASCII ids all cached) */
        if (cache_failed || !prev_reserve(rec, n)) {
            rec->n = 0;
        } else {
            for (size_t i = 0; i < n; i++) {
                PyObject *u = PyList_GET_ITEM(list, (Py_ssize_t)i);
                Py_ssize_t len;
                int cached;
                if (i < rec->n && rec->str[i] == u) continue;  /* recorded there already: no store */
                len = PyUnicode_GET_LENGTH(u);
                cached = PyUnicode_IS_COMPACT_ASCII(u) && len <= ID_MAX_BYTES;
                rec->str[i] = cached ? u : NULL;
                rec->len[i] = cached ? (uint8_t)len : UINT8_MAX;  /* never equal to an id's length */
                if (cached && len) memcpy(rec->bytes + i * ID_MAX_BYTES, PyUnicode_DATA(u), (size_t)len);
            }
            rec->n = n;
        }
    }
    return list;
fail:
    PyErr_Clear();
    Py_DECREF(list);
    return NULL;
}

/* ------------------------------------------------------------------ columns */

typedef struct {
    const uint8_t *p;  /* the column's bytes inside the message */
} bin_t;

/* The bin of `n` values of `size` bytes at `pos`. */
static int rd_column(rd_t *r, size_t pos, size_t n, int size, bin_t *out) {
    size_t len;
    if (!rd_at(r, pos) || !rd_bin(r, &out->p, &len)) return 0;
    return n <= SIZE_MAX / (size_t)size && len == n * (size_t)size;
}

/* Copy float64 values and check each within lo..hi (NaN fails every comparison). */
static int put_f8(double *dst, const uint8_t *src, size_t n, double lo, double hi) {
    if (n == 0) return 1;
    memcpy(dst, src, n * 8);
    for (size_t i = 0; i < n; i++)
        if (!(dst[i] >= lo && dst[i] <= hi)) return 0;
    return 1;
}

static int put_f4(float *dst, const uint8_t *src, size_t n, double lo, double hi) {
    if (n == 0) return 1;
    memcpy(dst, src, n * 4);
    for (size_t i = 0; i < n; i++) {
        double v = (double)dst[i];
        if (!(v >= lo && v <= hi)) return 0;
    }
    return 1;
}

/* Copy an integer column; when bounded, every value within lo..hi. */
#define INT_LOOP(T)                                                  \
    do {                                                             \
        const T *v = (const T *)dst;                                 \
        for (size_t i = 0; i < n; i++)                               \
            if (!((double)v[i] >= lo && (double)v[i] <= hi)) return 0; \
    } while (0)

static int put_int(void *dst, const uint8_t *src, size_t n, const column_t *c, double lo, double hi, int bounded) {
    if (n == 0) return 1;
    memcpy(dst, src, n * (size_t)c->size);
    if (!bounded) return 1;
    switch (c->size * (c->kind == 'u' ? 1 : -1)) {
    case 1: INT_LOOP(uint8_t); break;
    case -1: INT_LOOP(int8_t); break;
    case 2: INT_LOOP(uint16_t); break;
    case -2: INT_LOOP(int16_t); break;
    case 4: INT_LOOP(uint32_t); break;
    case -4: INT_LOOP(int32_t); break;
    default: return 0;
    }
    return 1;
}

static float load_f4(const uint8_t *p) {
    float f;
    memcpy(&f, p, 4);
    return f;
}

/* Every one of `count` float32 values at `p` (any alignment) within +-the float whose bits
 * are `lim_bits`: |v| <= lim <=> (bits & 0x7fffffff) <= bits(lim) for a non-negative lim,
 * and NaN (whose patterns are all above infinity's) fails it too. Integer compares without
 * a branch, in a function of their own: the compiler makes vector code of it. */
static NOINLINE int bits_within(const uint8_t *p, size_t count, uint32_t lim_bits) {
    uint32_t bad = 0;
    for (size_t j = 0; j < count; j++) {
        uint32_t u;
        memcpy(&u, p + 4 * j, 4);
        bad |= (u & 0x7fffffffu) > lim_bits;
    }
    return !bad;
}

/* `count` (x, y) points: float32 offsets at `src` plus the anchor (ax, ay), as float64. */
static NOINLINE void add_anchor(double *restrict dst, const uint8_t *restrict src, size_t count, double ax, double ay) {
    for (size_t j = 0; j < count; j++) {
        dst[2 * j] = ax + (double)load_f4(src + 8 * j);
        dst[2 * j + 1] = ay + (double)load_f4(src + 8 * j + 4);
    }
}

/* Checked size arithmetic for the output layout. */
static int add_sz(size_t *acc, size_t a, size_t b) {  /* acc += a * b */
    if (b != 0 && a > SIZE_MAX / b) return 0;
    if (a * b > SIZE_MAX - *acc) return 0;
    *acc += a * b;
    return 1;
}

typedef struct {
    Py_ssize_t max_agents, max_points, max_str;
} limits_t;

/* ------------------------------------------------------------------ decode: common */

static const name_t TOP_KEYS[] = {NAME("v"), NAME("kind"), NAME("run"), NAME("step"), NAME("t"), NAME("dt"),
                                  NAME("sv"), NAME("final"), NAME("epoch"), NAME("agents"), NAME("tls"),
                                  NAME("vtypes"), NAME("tick"), NAME("sumo_step"), NAME("counters")};
enum { T_V, T_KIND, T_RUN, T_STEP, T_T, T_DT, T_SV, T_FINAL, T_EPOCH, T_AGENTS, T_TLS, T_VTYPES, T_TICK,
       T_SUMO_STEP, T_COUNTERS, N_TOP };

/* The agents map of either kind: n, id, the step's columns in STEP_COLS order, path, then
 * the physics-only columns. */
static const name_t AGENT_KEYS[] = {
    NAME("n"), NAME("id"), NAME("cls"), NAME("vtype"), NAME("x"), NAME("y"), NAME("angle"), NAME("speed"),
    NAME("accel"), NAME("signals"), NAME("la_dx"), NAME("la_dy"), NAME("length"), NAME("width"), NAME("lane"),
    NAME("flags"), NAME("path"), NAME("mode"), NAME("z"), NAME("heading"), NAME("roll"), NAME("pitch"),
    NAME("steer"), NAME("drive"), NAME("brake"), NAME("err_lon"), NAME("err_lat")};
#define A_N 0
#define A_ID 1
#define A_COL0 2
#define A_PATH (A_COL0 + STEP_NCOL)
#define N_AGENT_KEYS ((int)(sizeof AGENT_KEYS / sizeof AGENT_KEYS[0]))

static const name_t PATH_KEYS[] = {NAME("off"), NAME("dxy")};
static const name_t TLS_KEYS[] = {NAME("id"), NAME("state"), NAME("phase"), NAME("next"), NAME("program")};
enum { L_ID, L_STATE, L_PHASE, L_NEXT, L_PROGRAM, N_TLS_KEYS };

/* Where every value is: one pass over the message (the nested maps scanned in place). */
typedef struct {
    size_t top[N_TOP], ag[N_AGENT_KEYS], path[2], tls[N_TLS_KEYS];
} scan_t;

static int nest_agents(rd_t *r, int j, void *ctx) {
    scan_t *sc = (scan_t *)ctx;
    return j == A_PATH ? rd_keys(r, PATH_KEYS, 2, sc->path, NULL, NULL) : -1;
}

static int nest_top(rd_t *r, int j, void *ctx) {
    scan_t *sc = (scan_t *)ctx;
    if (j == T_AGENTS) return rd_keys(r, AGENT_KEYS, N_AGENT_KEYS, sc->ag, nest_agents, sc);
    if (j == T_TLS) return rd_keys(r, TLS_KEYS, N_TLS_KEYS, sc->tls, NULL, NULL);
    return -1;
}

static int scan(rd_t *r, scan_t *sc) {
    size_t i;
    for (i = 0; i < N_AGENT_KEYS; i++) sc->ag[i] = ABSENT;
    for (i = 0; i < 2; i++) sc->path[i] = ABSENT;
    for (i = 0; i < N_TLS_KEYS; i++) sc->tls[i] = ABSENT;
    return rd_keys(r, TOP_KEYS, N_TOP, sc->top, nest_top, sc);
}

enum { KIND_STEP = 1, KIND_PHYSICS = 2 };

/* ``v``: [major, minor] integers, the major this build speaks. */
static int check_version(rd_t *r, size_t pos) {
    size_t n;
    int64_t major, minor;
    int big;
    if (!rd_at(r, pos) || !rd_array(r, &n) || n != 2) return 0;
    if (!rd_int(r, &major, &big) || big || major != g_major) return 0;
    return rd_int(r, &minor, &big);  /* any minor */
}

static int rd_run(rd_t *r, size_t pos, Py_ssize_t max_str, PyObject **out) {
    const char *s;
    size_t n;
    if (!rd_at(r, pos) || !rd_str(r, &s, &n)) return 0;
    *out = mk_str(s, n, max_str);
    return *out != NULL;
}

/* A number field as ``_fields`` reads it (ints become floats): within lo..hi, finite. */
static int rd_number(rd_t *r, size_t pos, double lo, double hi, double *d) {
    uint8_t t;
    if (!rd_at(r, pos) || !rd_peek(r, &t)) return 0;
    if (is_float_tag(t)) {
        if (!rd_float(r, d)) return 0;
    } else {
        int64_t v;
        int big;
        /* an int beyond int64 would need Python's rounding rules: leave it to Python */
        if (!rd_int(r, &v, &big) || big) return 0;
        *d = (double)v;
        /* the Python check compares the int itself; |v| < 2^53 keeps the double exact */
        if (v > ((int64_t)1 << 53) || v < -((int64_t)1 << 53)) return 0;
    }
    return *d >= lo && *d <= hi;
}

/* An optional integer field (absent: the default). */
static int rd_opt_int(rd_t *r, size_t pos, int64_t lo, int64_t hi, int64_t dflt, int64_t *v) {
    if (pos == ABSENT) { *v = dflt; return 1; }
    return rd_at(r, pos) && rd_int_in(r, lo, hi, v);
}

/* Python objects of a decoded message, released on every exit. */
typedef struct {
    PyObject *run, *vtypes, *ids, *buf, *tls_ids, *tls_state, *tls_program, *counters;
} objs_t;

static void objs_clear(objs_t *o) {
    Py_CLEAR(o->run);
    Py_CLEAR(o->vtypes);
    Py_CLEAR(o->ids);
    Py_CLEAR(o->buf);
    Py_CLEAR(o->tls_ids);
    Py_CLEAR(o->tls_state);
    Py_CLEAR(o->tls_program);
    Py_CLEAR(o->counters);
}

/* ------------------------------------------------------------------ decode: step */


/* ``vtypes``: [[id, vclass], ...] string pairs; a list of 2-tuples (NULL: failed). */
static PyObject *rd_vtypes(rd_t *r, size_t pos, Py_ssize_t max_str, size_t *count) {
    size_t n;
    PyObject *list;
    if (!rd_at(r, pos) || !rd_array(r, &n) || n > MAX_VTYPES) return NULL;
    list = PyList_New((Py_ssize_t)n);
    if (list == NULL) {
        PyErr_Clear();
        return NULL;
    }
    for (size_t i = 0; i < n; i++) {
        size_t two, la, lb;
        const char *a, *b;
        PyObject *ua, *ub, *pair;
        if (!rd_array(r, &two) || two != 2 || !rd_str(r, &a, &la) || !rd_str(r, &b, &lb)) goto fail;
        ua = mk_str(a, la, max_str);
        if (ua == NULL) goto fail;
        ub = mk_str(b, lb, max_str);
        if (ub == NULL) {
            Py_DECREF(ua);
            goto fail;
        }
        pair = PyTuple_Pack(2, ua, ub);
        Py_DECREF(ua);
        Py_DECREF(ub);
        if (pair == NULL) goto fail;
        PyList_SET_ITEM(list, (Py_ssize_t)i, pair);
    }
    *count = n;
    return list;
fail:
    PyErr_Clear();
    Py_DECREF(list);
    return NULL;
}

/* The output layout of a step (protocol.codec._fast_step reads it the same way): float64
 * x, y, la_x, la_y [n each], path xy [2m]; float32 angle, speed, accel, length, width [n
 * each], tls next [k]; int32 lane [n], tls phase [k]; uint32 path offsets [n + 1 or 0];
 * uint16 vtype, signals [n each]; uint8 cls, flags [n each]. Each block starts aligned for
 * its type: the blocks before it are made of wider or equal items. */
static PyObject *decode_step(rd_t *r, const scan_t *sc, const limits_t *lim) {
    objs_t o = {0};
    const size_t *top = sc->top, *ap = sc->ag, *pp = sc->path, *tp = sc->tls;
    bin_t col[STEP_NCOL], off_bin = {0}, dxy_bin = {0};
    int64_t n64, step, sv, epoch;
    double t, dt;
    int final = 0, has_path;
    size_t n, m = 0, k, nvt = 0, total = 0, dxy_len;
    PyObject *res = NULL;

    if (top[T_TICK] != ABSENT || top[T_SUMO_STEP] != ABSENT || top[T_COUNTERS] != ABSENT) return NULL;
    for (int j = A_PATH + 1; j < N_AGENT_KEYS; j++)  /* physics columns */
        if (ap[j] != ABSENT) return NULL;
    /* scalars (STEP_FIELDS) */
    if (!rd_run(r, top[T_RUN], lim->max_str, &o.run)) goto fail;
    if (!rd_at(r, top[T_STEP]) || !rd_int_in(r, 0, INT64_MAX, &step)) goto fail;
    if (!rd_number(r, top[T_T], -FINITE_MAX, FINITE_MAX, &t)) goto fail;
    if (!rd_number(r, top[T_DT], DT_LO, DT_HI, &dt)) goto fail;
    if (!rd_opt_int(r, top[T_SV], 0, INT64_MAX, 0, &sv)) goto fail;
    if (!rd_opt_int(r, top[T_EPOCH], 0, INT64_MAX, 0, &epoch)) goto fail;
    if (top[T_FINAL] != ABSENT && !(rd_at(r, top[T_FINAL]) && rd_bool(r, &final))) goto fail;
    if (top[T_VTYPES] != ABSENT && (o.vtypes = rd_vtypes(r, top[T_VTYPES], lim->max_str, &nvt)) == NULL) goto fail;

    /* agents: the count, the columns and the path's sizes */
    if (!rd_at(r, ap[A_N]) || !rd_int_in(r, 0, lim->max_agents, &n64)) goto fail;
    n = (size_t)n64;
    for (int c = 0; c < STEP_NCOL; c++)
        if (!rd_column(r, ap[A_COL0 + c], n, STEP_COLS[c].size, &col[c])) goto fail;
    has_path = ap[A_PATH] != ABSENT;
    if (has_path) {
        if (n == SIZE_MAX || !rd_column(r, pp[0], n + 1, 4, &off_bin)) goto fail;
        if (!rd_at(r, pp[1]) || !rd_bin(r, &dxy_bin.p, &dxy_len) || dxy_len % 8) goto fail;
        m = dxy_len / 8;
        if (m > (size_t)lim->max_points) goto fail;
    }
    /* traffic lights: the count */
    if (top[T_TLS] == ABSENT || tp[L_STATE] == ABSENT || tp[L_PHASE] == ABSENT || tp[L_NEXT] == ABSENT) goto fail;
    if (!rd_at(r, tp[L_ID]) || (o.tls_ids = rd_strs(r, -1, 1, lim->max_str, PREV_NONE)) == NULL) goto fail;
    k = (size_t)PyList_GET_SIZE(o.tls_ids);
    if (!rd_at(r, tp[L_STATE]) || (o.tls_state = rd_strs(r, (Py_ssize_t)k, 0, lim->max_str, PREV_NONE)) == NULL) goto fail;
    if (tp[L_PROGRAM] != ABSENT &&
        (!rd_at(r, tp[L_PROGRAM]) || (o.tls_program = rd_strs(r, (Py_ssize_t)k, 0, lim->max_str, PREV_NONE)) == NULL))
        goto fail;

    /* one buffer for every array */
    if (!add_sz(&total, n, 4 * 8) || !add_sz(&total, m, 2 * 8) || !add_sz(&total, n, 5 * 4) ||
        !add_sz(&total, k, 4) || !add_sz(&total, n, 4) || !add_sz(&total, k, 4) ||
        !add_sz(&total, has_path ? n + 1 : 0, 4) || !add_sz(&total, n, 2 * 2) || !add_sz(&total, n, 2) ||
        total > (size_t)PY_SSIZE_T_MAX)
        goto fail;
    /* never empty: an empty bytearray's storage is a static string, not aligned for doubles */
    o.buf = PyByteArray_FromStringAndSize(NULL, (Py_ssize_t)(total ? total : 8));
    if (o.buf == NULL) goto fail;
    {
        uint8_t *base = (uint8_t *)PyByteArray_AS_STRING(o.buf);
        double *x = (double *)base, *y = x + n, *lax = y + n, *lay = lax + n, *pxy = lay + n;
        float *f4 = (float *)(pxy + 2 * m), *nxt = f4 + 5 * n;
        int32_t *lane = (int32_t *)(nxt + k), *phase = lane + n;
        uint32_t *off = (uint32_t *)(phase + k);
        uint16_t *vtype = (uint16_t *)(off + (has_path ? n + 1 : 0)), *signals = vtype + n;
        uint8_t *cls = (uint8_t *)(signals + n), *flags = cls + n;
        static const int F4[5] = {S_ANGLE, S_SPEED, S_ACCEL, S_LENGTH, S_WIDTH};
        const column_t *C = STEP_COLS;

        if (!put_f8(x, col[S_X].p, n, C[S_X].lo, C[S_X].hi) || !put_f8(y, col[S_Y].p, n, C[S_Y].lo, C[S_Y].hi))
            goto fail;
        for (int c = 0; c < 5; c++)
            if (!put_f4(f4 + (size_t)c * n, col[F4[c]].p, n, C[F4[c]].lo, C[F4[c]].hi)) goto fail;
        /* look-ahead: float64 position + float32 offset (as numpy adds them) */
        for (size_t i = 0; i < n; i++) {
            double dx = (double)load_f4(col[S_LADX].p + 4 * i), dy = (double)load_f4(col[S_LADY].p + 4 * i);
            if (!(dx >= C[S_LADX].lo && dx <= C[S_LADX].hi && dy >= C[S_LADY].lo && dy <= C[S_LADY].hi)) goto fail;
            lax[i] = x[i] + dx;
            lay[i] = y[i] + dy;
        }
        if (!put_int(cls, col[S_CLS].p, n, &C[S_CLS], C[S_CLS].lo, C[S_CLS].hi, C[S_CLS].bounded)) goto fail;
        if (!put_int(flags, col[S_FLAGS].p, n, &C[S_FLAGS], C[S_FLAGS].lo, C[S_FLAGS].hi, C[S_FLAGS].bounded))
            goto fail;
        if (!put_int(signals, col[S_SIGNALS].p, n, &C[S_SIGNALS], C[S_SIGNALS].lo, C[S_SIGNALS].hi,
                     C[S_SIGNALS].bounded))
            goto fail;
        if (!put_int(lane, col[S_LANE].p, n, &C[S_LANE], C[S_LANE].lo, C[S_LANE].hi, C[S_LANE].bounded)) goto fail;
        /* vtype indexes the step's vtype table when it carries one (any table fits no agents) */
        if (o.vtypes != NULL && n && nvt == 0) goto fail;
        if (!put_int(vtype, col[S_VTYPE].p, n, &C[S_VTYPE], 0, (double)nvt - 1, o.vtypes != NULL)) goto fail;
        if (has_path) {
            /* offsets rising from 0 to m, checked before any vertex is touched: every vertex
             * read and written is then within the m */
            uint32_t bad = 0;
            memcpy(off, off_bin.p, (n + 1) * 4);
            for (size_t i = 0; i < n; i++) bad |= off[i + 1] < off[i];
            if (bad || off[0] != 0 || off[n] != m) goto fail;
            /* every offset within +-the look-ahead bound, tested on the float32 bits before
             * any vertex is made: |v| <= lim <=> (bits & 0x7fffffff) <= bits(lim) for a
             * non-negative float lim, and NaN (all of whose patterns are above infinity's)
             * fails it too. Integer compares with no branch compile to vector code; the
             * float tests with a branch per value took half the decode. */
            if (!bits_within(dxy_bin.p, 2 * m, g_path_lim_bits)) goto fail;
            /* vertices = float32 offset + the agent's float64 position */
            for (size_t i = 0; i < n; i++)
                add_anchor(pxy + 2 * (size_t)off[i], dxy_bin.p + 8 * (size_t)off[i], off[i + 1] - off[i], x[i], y[i]);
        }
        /* traffic lights: phase integers 0..2^31-1, next finite numbers within +-1e9 (float32) */
        {
            size_t cnt;
            if (!rd_at(r, tp[L_PHASE]) || !rd_array(r, &cnt) || cnt != k) goto fail;
            for (size_t i = 0; i < k; i++) {
                int64_t v;
                if (!rd_int_in(r, 0, (int64_t)TLS_PHASE_HI, &v)) goto fail;
                phase[i] = (int32_t)v;
            }
            if (!rd_at(r, tp[L_NEXT]) || !rd_array(r, &cnt) || cnt != k) goto fail;
            for (size_t i = 0; i < k; i++) {
                uint8_t tag;
                double d;
                if (!rd_peek(r, &tag)) goto fail;
                if (is_float_tag(tag)) {
                    if (!rd_float(r, &d)) goto fail;
                } else {
                    int64_t v;
                    if (!rd_int_in(r, -(int64_t)TLS_NEXT_LIM, (int64_t)TLS_NEXT_LIM, &v)) goto fail;
                    d = (double)v;
                }
                if (!(d >= -TLS_NEXT_LIM && d <= TLS_NEXT_LIM)) goto fail;
                nxt[i] = (float)d;
            }
        }
    }
    /* ids last: the most Python objects, built only for a message that passed the rest */
    if (!rd_at(r, ap[A_ID]) || (o.ids = rd_strs(r, (Py_ssize_t)n, 1, lim->max_str, PREV_STEP)) == NULL) goto fail;

    res = Py_BuildValue("(iOLddLOLOOOnnOOOOn)", KIND_STEP, o.run, (long long)step, t, dt, (long long)sv,
                        final ? Py_True : Py_False, (long long)epoch, o.vtypes ? o.vtypes : Py_None, o.ids,
                        o.buf, (Py_ssize_t)n, (Py_ssize_t)m, has_path ? Py_True : Py_False, o.tls_ids,
                        o.tls_state, o.tls_program ? o.tls_program : Py_None, (Py_ssize_t)k);
    if (res == NULL) PyErr_Clear();
fail:
    objs_clear(&o);
    return res;
}

/* ------------------------------------------------------------------ decode: physics */

/* Each physics column's place in AGENT_KEYS (set by configure). */
static int PHYS_KEY[PHYS_NCOL];

/* ``counters``: a map of counter name -> integer; a dict (NULL: failed). */
static PyObject *rd_counters(rd_t *r, size_t pos) {
    size_t n;
    PyObject *d;
    if (!rd_at(r, pos) || !rd_map(r, &n)) return NULL;
    d = PyDict_New();
    if (d == NULL) goto fail;
    for (size_t i = 0; i < n; i++) {
        const char *s;
        size_t len;
        int64_t v;
        int big, ok;
        PyObject *key, *val;
        /* names as any str (the Python decoder bounds nothing here but msgpack's length) */
        if (!rd_str(r, &s, &len)) goto fail;
        key = mk_str(s, len, PY_SSIZE_T_MAX);
        if (key == NULL) goto fail;
        if (!rd_int(r, &v, &big)) {
            Py_DECREF(key);
            goto fail;
        }
        val = big ? NULL : PyLong_FromLongLong(v);
        if (big) {  /* re-read the unsigned value */
            uint64_t u = 0;
            for (int b = 0; b < 8; b++) u = (u << 8) | r->p[r->pos - 8 + (size_t)b];
            val = PyLong_FromUnsignedLongLong(u);
        }
        if (val == NULL) {
            Py_DECREF(key);
            goto fail;
        }
        ok = PyDict_SetItem(d, key, val) == 0;
        Py_DECREF(key);
        Py_DECREF(val);
        if (!ok) goto fail;
    }
    return d;
fail:
    PyErr_Clear();
    Py_XDECREF(d);
    return NULL;
}

/* Output layout: float64 x, y [n each]; float32 z .. err_lat [10 n]; uint8 cls, mode [n each]. */
static PyObject *decode_physics(rd_t *r, const scan_t *sc, const limits_t *lim) {
    objs_t o = {0};
    const size_t *top = sc->top, *ap = sc->ag;
    int used[N_AGENT_KEYS] = {0};
    bin_t col[PHYS_NCOL];
    int64_t n64, tick, sumo_step;
    double t;
    size_t n, total = 0;
    PyObject *res = NULL;
    const column_t *C = PHYS_COLS;

    for (int j = T_DT; j <= T_VTYPES; j++)
        if (j != T_AGENTS && top[j] != ABSENT) return NULL;
    if (top[T_STEP] != ABSENT) return NULL;
    used[A_N] = used[A_ID] = 1;
    for (int c = 0; c < PHYS_NCOL; c++) used[PHYS_KEY[c]] = 1;
    for (int j = 0; j < N_AGENT_KEYS; j++)  /* the step's columns */
        if (!used[j] && ap[j] != ABSENT) return NULL;
    if (!rd_run(r, top[T_RUN], lim->max_str, &o.run)) goto fail;
    if (!rd_at(r, top[T_TICK]) || !rd_int_in(r, 0, INT64_MAX, &tick)) goto fail;
    if (!rd_number(r, top[T_T], -FINITE_MAX, FINITE_MAX, &t)) goto fail;
    if (!rd_at(r, top[T_SUMO_STEP]) || !rd_int_in(r, -1, INT64_MAX, &sumo_step)) goto fail;
    if ((o.counters = rd_counters(r, top[T_COUNTERS])) == NULL) goto fail;

    if (!rd_at(r, ap[A_N]) || !rd_int_in(r, 0, lim->max_agents, &n64)) goto fail;
    n = (size_t)n64;
    for (int c = 0; c < PHYS_NCOL; c++)
        if (!rd_column(r, ap[PHYS_KEY[c]], n, C[c].size, &col[c])) goto fail;
    if (!add_sz(&total, n, 2 * 8 + 10 * 4 + 2) || total > (size_t)PY_SSIZE_T_MAX) goto fail;
    o.buf = PyByteArray_FromStringAndSize(NULL, (Py_ssize_t)(total ? total : 8));  /* as in decode_step */
    if (o.buf == NULL) goto fail;
    {
        uint8_t *base = (uint8_t *)PyByteArray_AS_STRING(o.buf);
        double *f8 = (double *)base;
        float *f4 = (float *)(f8 + 2 * n);
        uint8_t *u1 = (uint8_t *)(f4 + 10 * n);
        for (int c = 0; c < 2; c++)
            if (!put_f8(f8 + (size_t)c * n, col[2 + c].p, n, C[2 + c].lo, C[2 + c].hi)) goto fail;
        for (int c = 0; c < 10; c++)
            if (!put_f4(f4 + (size_t)c * n, col[4 + c].p, n, C[4 + c].lo, C[4 + c].hi)) goto fail;
        for (int c = 0; c < 2; c++)
            if (!put_int(u1 + (size_t)c * n, col[c].p, n, &C[c], C[c].lo, C[c].hi, C[c].bounded)) goto fail;
    }
    if (!rd_at(r, ap[A_ID]) || (o.ids = rd_strs(r, (Py_ssize_t)n, 1, lim->max_str, PREV_PHYSICS)) == NULL) goto fail;
    res = Py_BuildValue("(iOLdLOOOn)", KIND_PHYSICS, o.run, (long long)tick, t, (long long)sumo_step, o.counters,
                        o.ids, o.buf, (Py_ssize_t)n);
    if (res == NULL) PyErr_Clear();
fail:
    objs_clear(&o);
    return res;
}

/* ------------------------------------------------------------------ decode: entry */

static int limits_from(PyObject *tup, limits_t *lim, rd_t *r) {
    Py_ssize_t v[6];
    if (!PyTuple_Check(tup) || PyTuple_GET_SIZE(tup) != 6) return 0;
    for (int i = 0; i < 6; i++) {
        v[i] = PyLong_AsSsize_t(PyTuple_GET_ITEM(tup, i));
        if (v[i] < 0) {
            PyErr_Clear();
            return 0;
        }
    }
    lim->max_agents = v[0];
    lim->max_points = v[1];
    lim->max_str = v[2];
    r->max_str_bytes = (size_t)v[3];
    r->max_bin = (size_t)v[4];
    r->max_array = (size_t)v[5];
    return 1;
}

static PyObject *py_decode(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    Py_buffer view;
    rd_t r;
    limits_t lim;
    scan_t sc;
    PyObject *res = NULL;
    (void)self;
    if (nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "decode(data, limits)");
        return NULL;
    }
    if (!g_ready || !limits_from(args[1], &lim, &r)) Py_RETURN_NONE;
    if (PyObject_GetBuffer(args[0], &view, PyBUF_FULL_RO) < 0) {
        PyErr_Clear();
        Py_RETURN_NONE;
    }
    if (view.itemsize == 1 && PyBuffer_IsContiguous(&view, 'C') && view.len > 0) {
        const char *kind;
        size_t klen;
        r.p = (const uint8_t *)view.buf;
        r.len = (size_t)view.len;
        r.pos = 0;
        /* the whole document one map of known keys, nothing after it (msgpack: ExtraData) */
        if (scan(&r, &sc) && r.pos == r.len && check_version(&r, sc.top[T_V]) && rd_at(&r, sc.top[T_KIND]) &&
            rd_str(&r, &kind, &klen) && sc.top[T_AGENTS] != ABSENT) {
            if (klen == 4 && memcmp(kind, "step", 4) == 0)
                res = decode_step(&r, &sc, &lim);
            else if (klen == 7 && memcmp(kind, "physics", 7) == 0)
                res = decode_physics(&r, &sc, &lim);
        }
    }
    PyBuffer_Release(&view);
    if (res == NULL) {
        PyErr_Clear();
        Py_RETURN_NONE;
    }
    return res;
}

/* ------------------------------------------------------------------ writing */

typedef struct {
    uint8_t *b;   /* NULL: count only */
    size_t pos, cap;
    int bad;
} wr_t;

static uint8_t *w_room(wr_t *w, size_t k) {  /* k bytes to write at the end, or NULL */
    if (w->bad) return NULL;
    if (w->b == NULL) {
        if (k > SIZE_MAX - w->pos) w->bad = 1;
        else w->pos += k;
        return NULL;
    }
    if (k > w->cap - w->pos) {
        w->bad = 1;
        return NULL;
    }
    w->pos += k;
    return w->b + w->pos - k;
}

static void w_raw(wr_t *w, const void *s, size_t k) {
    uint8_t *d = w_room(w, k);
    if (d != NULL && k) memcpy(d, s, k);
}

static void w_tag(wr_t *w, uint8_t tag, uint64_t v, int bytes) {  /* tag + big-endian value */
    uint8_t *d = w_room(w, 1 + (size_t)bytes);
    if (d == NULL) return;
    d[0] = tag;
    for (int i = bytes; i >= 1; i--) {
        d[i] = (uint8_t)(v & 0xff);
        v >>= 8;
    }
}

/* msgpack's own choices (msgpack-python with use_bin_type=True): the shortest form */
static void w_map(wr_t *w, size_t n) {
    if (n < 16) w_tag(w, (uint8_t)(0x80 | n), 0, 0);
    else if (n < 65536) w_tag(w, 0xde, n, 2);
    else w_tag(w, 0xdf, n, 4);
}

static void w_array(wr_t *w, size_t n) {
    if (n > 0xffffffffu) { w->bad = 1; return; }
    if (n < 16) w_tag(w, (uint8_t)(0x90 | n), 0, 0);
    else if (n < 65536) w_tag(w, 0xdc, n, 2);
    else w_tag(w, 0xdd, n, 4);
}

static void w_str(wr_t *w, const char *s, size_t n) {
    if (n > 0xffffffffu) { w->bad = 1; return; }
    if (n < 32) w_tag(w, (uint8_t)(0xa0 | n), 0, 0);
    else if (n < 256) w_tag(w, 0xd9, n, 1);
    else if (n < 65536) w_tag(w, 0xda, n, 2);
    else w_tag(w, 0xdb, n, 4);
    w_raw(w, s, n);
}

static void w_bin_head(wr_t *w, size_t n) {
    if (n > 0xffffffffu) { w->bad = 1; return; }
    if (n < 256) w_tag(w, 0xc4, n, 1);
    else if (n < 65536) w_tag(w, 0xc5, n, 2);
    else w_tag(w, 0xc6, n, 4);
}

static void w_i64(wr_t *w, int64_t d) {
    if (d < -(1LL << 5)) {
        if (d < -(1LL << 15)) {
            if (d < -(1LL << 31)) w_tag(w, 0xd3, (uint64_t)d, 8);
            else w_tag(w, 0xd2, (uint64_t)d & 0xffffffffu, 4);
        } else if (d < -(1LL << 7)) w_tag(w, 0xd1, (uint64_t)d & 0xffffu, 2);
        else w_tag(w, 0xd0, (uint64_t)d & 0xffu, 1);
    } else if (d < (1LL << 7)) {
        w_tag(w, (uint8_t)((uint64_t)d & 0xffu), 0, 0);
    } else if (d < (1LL << 8)) w_tag(w, 0xcc, (uint64_t)d, 1);
    else if (d < (1LL << 16)) w_tag(w, 0xcd, (uint64_t)d, 2);
    else if (d < (1LL << 32)) w_tag(w, 0xce, (uint64_t)d, 4);
    else w_tag(w, 0xcf, (uint64_t)d, 8);
}

static void w_u64(wr_t *w, uint64_t d) {
    if (d <= (uint64_t)INT64_MAX) w_i64(w, (int64_t)d);
    else w_tag(w, 0xcf, d, 8);
}

static void w_double(wr_t *w, double d) {
    uint64_t u;
    memcpy(&u, &d, 8);
    w_tag(w, 0xcb, u, 8);
}

static void w_key(wr_t *w, const char *k) { w_str(w, k, strlen(k)); }

/* A Python str, as msgpack packs it (UTF-8; a surrogate fails: the Python encoder raises). */
static void w_pystr(wr_t *w, PyObject *s) {
    Py_ssize_t n;
    const char *u;
    if (!PyUnicode_Check(s)) { w->bad = 1; return; }
    if (PyUnicode_IS_COMPACT_ASCII(s)) {  /* its characters are its UTF-8 */
        w_str(w, (const char *)PyUnicode_DATA(s), (size_t)PyUnicode_GET_LENGTH(s));
        return;
    }
    u = PyUnicode_AsUTF8AndSize(s, &n);
    if (u == NULL) {
        PyErr_Clear();
        w->bad = 1;
        return;
    }
    w_str(w, u, (size_t)n);
}

/* A Python int (exactly an int: what int(...) returned), as msgpack packs it. */
static void w_pyint(wr_t *w, PyObject *v) {
    int overflow;
    long long x;
    if (!PyLong_CheckExact(v)) { w->bad = 1; return; }
    x = PyLong_AsLongLongAndOverflow(v, &overflow);
    if (overflow > 0) {
        unsigned long long u = PyLong_AsUnsignedLongLong(v);
        if (u == (unsigned long long)-1 && PyErr_Occurred()) {
            PyErr_Clear();
            w->bad = 1;
            return;
        }
        w_u64(w, u);
    } else if (overflow < 0 || (x == -1 && PyErr_Occurred())) {
        PyErr_Clear();
        w->bad = 1;
    } else {
        w_i64(w, x);
    }
}

/* A list or tuple of str (list(...) of anything else is the Python encoder's business). */
static void w_pystrs(wr_t *w, PyObject *seq) {
    Py_ssize_t n;
    PyObject **items;
    if (!PyList_Check(seq) && !PyTuple_Check(seq)) { w->bad = 1; return; }
    n = PySequence_Fast_GET_SIZE(seq);
    items = PySequence_Fast_ITEMS(seq);
    w_array(w, (size_t)n);
    for (Py_ssize_t i = 0; i < n && !w->bad; i++) w_pystr(w, items[i]);
}

/* ------------------------------------------------------------------ encode: arrays */

typedef struct {
    Py_buffer v;
    int held;
    char kind;    /* 'f', 'i', 'u' */
    int size;
    size_t count; /* items */
} arr_t;

/* A C-contiguous little-endian numeric buffer (a numpy array); 0 when it is anything else. */
static int arr_get(PyObject *obj, arr_t *a) {
    const char *f;
    char c;
    a->held = 0;
    if (PyObject_GetBuffer(obj, &a->v, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0) {
        PyErr_Clear();
        return 0;
    }
    a->held = 1;
    f = a->v.format ? a->v.format : "B";
    if (*f == '<' || *f == '=' || *f == '@') f++;
    if (f[0] == '\0' || f[1] != '\0') return 0;
    c = f[0];
    if (c == 'f' || c == 'd') a->kind = 'f';
    else if (c == 'b' || c == 'h' || c == 'i' || c == 'l' || c == 'q') a->kind = 'i';
    else if (c == 'B' || c == 'H' || c == 'I' || c == 'L' || c == 'Q') a->kind = 'u';
    else return 0;
    a->size = (int)a->v.itemsize;
    if (a->size != 1 && a->size != 2 && a->size != 4 && a->size != 8) return 0;
    if (a->kind == 'f' && a->size != 4 && a->size != 8) return 0;
    if (a->v.len < 0 || (size_t)a->v.len % (size_t)a->size) return 0;
    a->count = (size_t)a->v.len / (size_t)a->size;
    return 1;
}

static int arr_is(const arr_t *a, char kind, int size) { return a->kind == kind && a->size == size; }

static int arr_1d(const arr_t *a) { return a->v.ndim == 1; }

static double arr_f(const arr_t *a, size_t i) {  /* a float array's item as float64 */
    const uint8_t *p = (const uint8_t *)a->v.buf;
    if (a->size == 8) {
        double d;
        memcpy(&d, p + 8 * i, 8);
        return d;
    }
    return (double)load_f4(p + 4 * i);
}

static int64_t arr_i(const arr_t *a, size_t i) {  /* an integer array's item, as int64 */
    const uint8_t *p = (const uint8_t *)a->v.buf + (size_t)a->size * i;
    if (a->kind == 'i') {
        if (a->size == 1) { int8_t v; memcpy(&v, p, 1); return v; }
        if (a->size == 2) { int16_t v; memcpy(&v, p, 2); return v; }
        if (a->size == 4) { int32_t v; memcpy(&v, p, 4); return v; }
        { int64_t v; memcpy(&v, p, 8); return v; }
    }
    if (a->size == 1) return *p;
    if (a->size == 2) { uint16_t v; memcpy(&v, p, 2); return v; }
    if (a->size == 4) { uint32_t v; memcpy(&v, p, 4); return v; }
    { uint64_t v; memcpy(&v, p, 8); return v > (uint64_t)INT64_MAX ? -1 : (int64_t)v; }
}

static void w_col(wr_t *w, const arr_t *a) {  /* a column: its bytes as one bin */
    w_bin_head(w, (size_t)a->v.len);
    w_raw(w, a->v.buf, (size_t)a->v.len);
}

static double load_f8(const uint8_t *p) {
    double d;
    memcpy(&d, p, 8);
    return d;
}

/* float32(a - b) per item, float64 difference rounded once (numpy's subtract then cast);
 * b is float64. */
static void w_diff_f4(wr_t *w, const arr_t *a, const arr_t *b) {
    uint8_t *d;
    const uint8_t *pa = (const uint8_t *)a->v.buf, *pb = (const uint8_t *)b->v.buf;
    w_bin_head(w, a->count * 4);
    d = w_room(w, a->count * 4);
    if (d == NULL) return;
    if (a->size == 4) {
        for (size_t i = 0; i < a->count; i++) {
            float f = (float)((double)load_f4(pa + 4 * i) - load_f8(pb + 8 * i));
            memcpy(d + 4 * i, &f, 4);
        }
    } else {
        for (size_t i = 0; i < a->count; i++) {
            float f = (float)(load_f8(pa + 8 * i) - load_f8(pb + 8 * i));
            memcpy(d + 4 * i, &f, 4);
        }
    }
}

/* The anchored path: for each agent i, float32(vertex - (x_i, y_i)) of its vertices. */
static void w_dxy(uint8_t *d, const arr_t *off, const arr_t *pxy, const arr_t *x, const arr_t *y, size_t first) {
    const uint8_t *px = (const uint8_t *)x->v.buf, *py = (const uint8_t *)y->v.buf;
    const uint8_t *pv = (const uint8_t *)pxy->v.buf;
    size_t n = off->count - 1;
    for (size_t i = 0; i < n; i++) {
        size_t a = (size_t)arr_i(off, i), b = (size_t)arr_i(off, i + 1);
        double xi = load_f8(px + 8 * i), yi = load_f8(py + 8 * i);
        uint8_t *o = d + 8 * (a - first);
        if (pxy->size == 4) {
            for (size_t j = a; j < b; j++, o += 8) {
                float f[2];
                f[0] = (float)((double)load_f4(pv + 8 * j) - xi);
                f[1] = (float)((double)load_f4(pv + 8 * j + 4) - yi);
                memcpy(o, f, 8);
            }
        } else {
            for (size_t j = a; j < b; j++, o += 8) {
                float f[2];
                f[0] = (float)(load_f8(pv + 16 * j) - xi);
                f[1] = (float)(load_f8(pv + 16 * j + 8) - yi);
                memcpy(o, f, 8);
            }
        }
    }
}

/* Owned references and buffers of one encode call. */
#define MAX_OBJS 48
#define MAX_ARRS 24
typedef struct {
    PyObject *obj[MAX_OBJS];
    int nobj;
    arr_t arr[MAX_ARRS];
    int narr;
} hold_t;

/* The attribute names the encoders read, as interned str made once: PyObject_GetAttrString
 * makes a str of the name and hashes it on every call, and the instance dict then finds it
 * by comparing characters (an interned key matches by identity). Keyed by the name's
 * address (string literals and the column tables), which is stable. */
#define MAX_NAMES 64
static struct {
    const char *key;
    PyObject *str;
} g_names[MAX_NAMES];

static PyObject *get_attr(PyObject *o, const char *name) {
    int i;
    for (i = 0; i < MAX_NAMES && g_names[i].key != NULL; i++)
        if (g_names[i].key == name) return PyObject_GetAttr(o, g_names[i].str);
    if (i < MAX_NAMES) {
        PyObject *u = PyUnicode_InternFromString(name);
        if (u == NULL) return NULL;
        g_names[i].key = name;
        g_names[i].str = u;  /* kept for the life of the process */
        return PyObject_GetAttr(o, u);
    }
    return PyObject_GetAttrString(o, name);
}

static PyObject *hold_attr(hold_t *h, PyObject *o, const char *name) {
    PyObject *v;
    if (h->nobj >= MAX_OBJS) return NULL;
    v = get_attr(o, name);
    if (v == NULL) {
        PyErr_Clear();
        return NULL;
    }
    h->obj[h->nobj++] = v;
    return v;
}

static PyObject *hold_new(hold_t *h, PyObject *v) {  /* take a new reference (or NULL) */
    if (v == NULL) {
        PyErr_Clear();
        return NULL;
    }
    if (h->nobj >= MAX_OBJS) {
        Py_DECREF(v);
        return NULL;
    }
    h->obj[h->nobj++] = v;
    return v;
}

static arr_t *hold_arr(hold_t *h, PyObject *o, const char *name) {
    PyObject *v = hold_attr(h, o, name);
    arr_t *a;
    if (v == NULL || h->narr >= MAX_ARRS) return NULL;
    a = &h->arr[h->narr++];
    return arr_get(v, a) ? a : NULL;
}

static void hold_release(hold_t *h) {
    for (int i = 0; i < h->narr; i++)
        if (h->arr[i].held) PyBuffer_Release(&h->arr[i].v);
    for (int i = 0; i < h->nobj; i++) Py_DECREF(h->obj[i]);
    h->narr = h->nobj = 0;
}

/* Count, allocate, write: `emit` runs twice, the second time into bytes of exactly the
 * counted size. */
typedef void (*emit_fn)(wr_t *w, void *ctx);

static PyObject *emit_bytes(emit_fn emit, void *ctx) {
    wr_t w = {NULL, 0, 0, 0};
    PyObject *out;
    emit(&w, ctx);
    if (w.bad || w.pos > (size_t)PY_SSIZE_T_MAX) return NULL;
    out = PyBytes_FromStringAndSize(NULL, (Py_ssize_t)w.pos);
    if (out == NULL) {
        PyErr_Clear();
        return NULL;
    }
    w.b = (uint8_t *)PyBytes_AS_STRING(out);
    w.cap = w.pos;
    w.pos = 0;
    emit(&w, ctx);
    if (w.bad || w.pos != w.cap) {
        Py_DECREF(out);
        return NULL;
    }
    return out;
}

static int64_t g_minor = -1;

static void w_head(wr_t *w, const char *kind) {
    w_key(w, "v");
    w_array(w, 2);
    w_i64(w, g_major);
    w_i64(w, g_minor);
    w_key(w, "kind");
    w_key(w, kind);
}

/* ------------------------------------------------------------------ encode: step */

typedef struct {
    PyObject *run, *step, *t, *dt, *sv, *epoch, *vtypes, *n, *ids, *tls_ids, *tls_state, *tls_program;
    int has_epoch, final, has_path;
    arr_t *col[STEP_NCOL];  /* la_dx, la_dy: la_x, la_y (any float width) */
    arr_t *off, *pxy, *phase, *next;
    size_t first, last;     /* the path's vertex range */
} step_in_t;

static void emit_step(wr_t *w, void *ctx) {
    step_in_t *s = (step_in_t *)ctx;
    w_map(w, 9 + (size_t)s->has_epoch + (s->vtypes != NULL) + (size_t)s->final);
    w_head(w, "step");
    w_key(w, "run"); w_pystr(w, s->run);
    w_key(w, "step"); w_pyint(w, s->step);
    w_key(w, "t"); w_double(w, PyFloat_AS_DOUBLE(s->t));
    w_key(w, "dt"); w_double(w, PyFloat_AS_DOUBLE(s->dt));
    w_key(w, "sv"); w_pyint(w, s->sv);
    if (s->has_epoch) { w_key(w, "epoch"); w_pyint(w, s->epoch); }
    w_key(w, "agents");
    w_map(w, 2 + STEP_NCOL + (size_t)s->has_path);
    w_key(w, "n"); w_pyint(w, s->n);
    w_key(w, "id"); w_pystrs(w, s->ids);
    for (int c = 0; c < STEP_NCOL; c++) {
        w_key(w, STEP_COLS[c].name);
        if (c == S_LADX) w_diff_f4(w, s->col[c], s->col[S_X]);
        else if (c == S_LADY) w_diff_f4(w, s->col[c], s->col[S_Y]);
        else w_col(w, s->col[c]);
    }
    if (s->has_path) {
        size_t n = s->off->count - 1, rows = s->last - s->first;
        uint8_t *d;
        w_key(w, "path");
        w_map(w, 2);
        w_key(w, "off");
        w_bin_head(w, 4 * s->off->count);
        d = w_room(w, 4 * s->off->count);
        if (d != NULL)
            for (size_t i = 0; i <= n; i++) {
                uint32_t u = (uint32_t)((size_t)arr_i(s->off, i) - s->first);
                memcpy(d + 4 * i, &u, 4);
            }
        w_key(w, "dxy");
        w_bin_head(w, 8 * rows);
        d = w_room(w, 8 * rows);
        if (d != NULL) w_dxy(d, s->off, s->pxy, s->col[S_X], s->col[S_Y], s->first);
    }
    w_key(w, "tls");
    w_map(w, 4 + (s->tls_program != NULL));
    w_key(w, "id"); w_pystrs(w, s->tls_ids);
    w_key(w, "state"); w_pystrs(w, s->tls_state);
    w_key(w, "phase");
    w_array(w, s->phase->count);
    for (size_t i = 0; i < s->phase->count && !w->bad; i++) w_i64(w, arr_i(s->phase, i));
    w_key(w, "next");
    w_array(w, s->next->count);
    for (size_t i = 0; i < s->next->count && !w->bad; i++) w_double(w, arr_f(s->next, i));
    if (s->tls_program != NULL) { w_key(w, "program"); w_pystrs(w, s->tls_program); }
    if (s->vtypes != NULL) {
        Py_ssize_t nv = PySequence_Fast_GET_SIZE(s->vtypes);
        PyObject **items = PySequence_Fast_ITEMS(s->vtypes);
        w_key(w, "vtypes");
        w_array(w, (size_t)nv);
        for (Py_ssize_t i = 0; i < nv && !w->bad; i++) {
            /* [v.id, v.vclass]: checked to be str before (prep_vtypes) */
            PyObject *id = PyTuple_GET_ITEM(items[i], 0), *vc = PyTuple_GET_ITEM(items[i], 1);
            w_array(w, 2);
            w_pystr(w, id);
            w_pystr(w, vc);
        }
    }
    if (s->final) { w_key(w, "final"); w_tag(w, 0xc3, 0, 0); }
}

/* [(v.id, v.vclass), ...] of msg.vtypes (a list or tuple of objects with str attributes). */
static PyObject *prep_vtypes(PyObject *vt) {
    Py_ssize_t n;
    PyObject *out;
    if (!PyList_Check(vt) && !PyTuple_Check(vt)) return NULL;
    n = PySequence_Fast_GET_SIZE(vt);
    out = PyTuple_New(n);
    if (out == NULL) return NULL;
    for (Py_ssize_t i = 0; i < n; i++) {
        PyObject *v = PySequence_Fast_GET_ITEM(vt, i), *id, *vc, *pair;
        id = get_attr(v, "id");
        vc = id ? get_attr(v, "vclass") : NULL;
        if (id == NULL || vc == NULL || !PyUnicode_Check(id) || !PyUnicode_Check(vc)) {
            Py_XDECREF(id);
            Py_XDECREF(vc);
            Py_DECREF(out);
            return NULL;
        }
        pair = PyTuple_Pack(2, id, vc);
        Py_DECREF(id);
        Py_DECREF(vc);
        if (pair == NULL) {
            Py_DECREF(out);
            return NULL;
        }
        PyTuple_SET_ITEM(out, i, pair);
    }
    return out;
}

static int truth(PyObject *o, int *b) {
    int t = PyObject_IsTrue(o);
    if (t < 0) {
        PyErr_Clear();
        return 0;
    }
    *b = t;
    return 1;
}

static PyObject *py_encode_step(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    hold_t h;
    step_in_t s;
    PyObject *msg, *ag, *tl, *v, *out = NULL;
    static const char EXPECT_KIND[STEP_NCOL] = {'u', 'u', 'f', 'f', 'f', 'f', 'f', 'u', 'f', 'f', 'f', 'f', 'i', 'u'};
    (void)self;
    if (nargs != 3) {
        PyErr_SetString(PyExc_TypeError, "encode_step(msg, agents, tls)");
        return NULL;
    }
    if (!g_ready) Py_RETURN_NONE;
    msg = args[0];
    ag = args[1];
    tl = args[2];
    memset(&s, 0, sizeof s);
    h.nobj = h.narr = 0;
    /* the scalars exactly as _encode_step converts them */
    if ((v = hold_attr(&h, msg, "run")) == NULL || !PyUnicode_Check(v)) goto done;
    s.run = v;
    if ((v = hold_attr(&h, msg, "step")) == NULL || (s.step = hold_new(&h, PyNumber_Long(v))) == NULL) goto done;
    if ((v = hold_attr(&h, msg, "time")) == NULL || (s.t = hold_new(&h, PyNumber_Float(v))) == NULL) goto done;
    if ((v = hold_attr(&h, msg, "step_length")) == NULL || (s.dt = hold_new(&h, PyNumber_Float(v))) == NULL)
        goto done;
    if ((v = hold_attr(&h, msg, "static_version")) == NULL || (s.sv = hold_new(&h, PyNumber_Long(v))) == NULL)
        goto done;
    if ((v = hold_attr(&h, msg, "epoch")) == NULL || !truth(v, &s.has_epoch)) goto done;
    if (s.has_epoch && (s.epoch = hold_new(&h, PyNumber_Long(v))) == NULL) goto done;
    if ((v = hold_attr(&h, msg, "final")) == NULL || !truth(v, &s.final)) goto done;
    if ((v = hold_attr(&h, msg, "vtypes")) == NULL) goto done;
    if (v != Py_None && (s.vtypes = hold_new(&h, prep_vtypes(v))) == NULL) goto done;
    /* agents: columns of the wire dtypes; x, y float64; la_x, la_y float32 or float64 */
    if ((s.n = hold_attr(&h, ag, "n")) == NULL || (s.ids = hold_attr(&h, ag, "ids")) == NULL) goto done;
    for (int c = 0; c < STEP_NCOL; c++) {
        const char *name = c == S_LADX ? "la_x" : c == S_LADY ? "la_y" : STEP_COLS[c].name;
        arr_t *a = hold_arr(&h, ag, name);
        if (a == NULL || a->kind != EXPECT_KIND[c]) goto done;
        if (c == S_LADX || c == S_LADY) {
            if (!arr_1d(a)) goto done;
        } else if (a->size != STEP_COLS[c].size) {
            goto done;
        }
    }
    for (int c = 0; c < STEP_NCOL; c++) s.col[c] = &h.arr[c];
    if (!arr_1d(s.col[S_X]) || !arr_1d(s.col[S_Y])) goto done;
    /* la_x - x broadcasts in numpy; here the lengths must agree */
    if (s.col[S_LADX]->count != s.col[S_X]->count || s.col[S_LADY]->count != s.col[S_Y]->count) goto done;
    if ((s.off = hold_arr(&h, ag, "path_offsets")) == NULL || !arr_1d(s.off) || s.off->kind == 'f') goto done;
    s.has_path = s.off->count > 0;
    if (s.has_path) {
        size_t n = s.col[S_X]->count, rows;
        int64_t prev;
        if ((s.pxy = hold_arr(&h, ag, "path_xy")) == NULL || s.pxy->kind != 'f' || s.pxy->count % 2) goto done;
        /* np.repeat(column_stack((x, y)), diff(off)): n + 1 offsets, rising, within the vertices */
        if (s.col[S_Y]->count != n || s.off->count != n + 1) goto done;
        rows = s.pxy->count / 2;
        prev = arr_i(s.off, 0);
        if (prev < 0) goto done;
        s.first = (size_t)prev;
        for (size_t i = 1; i <= n; i++) {
            int64_t cur = arr_i(s.off, i);
            if (cur < prev) goto done;
            prev = cur;
        }
        s.last = (size_t)prev;
        if (s.last > rows || s.last - s.first > 0xffffffffu) goto done;  /* offsets - first as uint32 */
    }
    /* traffic lights: phase integers, next floats (1-D), the string lists */
    if ((s.tls_ids = hold_attr(&h, tl, "ids")) == NULL || (s.tls_state = hold_attr(&h, tl, "state")) == NULL)
        goto done;
    if ((s.phase = hold_arr(&h, tl, "phase")) == NULL || s.phase->kind == 'f' || !arr_1d(s.phase)) goto done;
    if (s.phase->kind == 'u' && s.phase->size == 8) goto done;  /* uint64 above int64 does not fit int64 */
    if ((s.next = hold_arr(&h, tl, "next_switch")) == NULL || s.next->kind != 'f' || !arr_1d(s.next)) goto done;
    if ((v = hold_attr(&h, tl, "program")) == NULL) goto done;
    s.tls_program = v == Py_None ? NULL : v;
    out = emit_bytes(emit_step, &s);
done:
    hold_release(&h);
    PyErr_Clear();
    if (out == NULL) Py_RETURN_NONE;
    return out;
}

/* ------------------------------------------------------------------ encode: physics */

typedef struct {
    PyObject *run, *tick, *t, *sumo_step, *n, *ids, *counters;
    arr_t *col[PHYS_NCOL];
} phys_in_t;

static void emit_physics(wr_t *w, void *ctx) {
    phys_in_t *s = (phys_in_t *)ctx;
    Py_ssize_t pos = 0;
    PyObject *k, *v;
    w_map(w, 8);
    w_head(w, "physics");
    w_key(w, "run"); w_pystr(w, s->run);
    w_key(w, "tick"); w_pyint(w, s->tick);
    w_key(w, "t"); w_double(w, PyFloat_AS_DOUBLE(s->t));
    w_key(w, "sumo_step"); w_pyint(w, s->sumo_step);
    w_key(w, "agents");
    w_map(w, 2 + PHYS_NCOL);
    w_key(w, "n"); w_pyint(w, s->n);
    w_key(w, "id"); w_pystrs(w, s->ids);
    for (int c = 0; c < PHYS_NCOL; c++) {
        w_key(w, PHYS_COLS[c].name);
        w_col(w, s->col[c]);
    }
    w_key(w, "counters");
    w_map(w, (size_t)PyDict_GET_SIZE(s->counters));
    while (!w->bad && PyDict_Next(s->counters, &pos, &k, &v)) {
        w_pystr(w, k);  /* str(k) of a str is itself */
        w_pyint(w, v);
    }
}

static PyObject *py_encode_physics(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    hold_t h;
    phys_in_t s;
    PyObject *msg, *ag, *v, *out = NULL;
    (void)self;
    if (nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "encode_physics(msg, agents)");
        return NULL;
    }
    if (!g_ready) Py_RETURN_NONE;
    msg = args[0];
    ag = args[1];
    memset(&s, 0, sizeof s);
    h.nobj = h.narr = 0;
    if ((v = hold_attr(&h, msg, "run")) == NULL || !PyUnicode_Check(v)) goto done;
    s.run = v;
    if ((v = hold_attr(&h, msg, "tick")) == NULL || (s.tick = hold_new(&h, PyNumber_Long(v))) == NULL) goto done;
    if ((v = hold_attr(&h, msg, "time")) == NULL || (s.t = hold_new(&h, PyNumber_Float(v))) == NULL) goto done;
    if ((v = hold_attr(&h, msg, "sumo_step")) == NULL || (s.sumo_step = hold_new(&h, PyNumber_Long(v))) == NULL)
        goto done;
    /* {str(k): int(v)}: here only an exact dict of str keys and int values (nothing to convert) */
    if ((v = hold_attr(&h, msg, "counters")) == NULL || !PyDict_CheckExact(v)) goto done;
    {
        Py_ssize_t pos = 0;
        PyObject *k, *val;
        while (PyDict_Next(v, &pos, &k, &val))
            if (!PyUnicode_CheckExact(k) || !PyLong_CheckExact(val)) goto done;
    }
    s.counters = v;
    if ((s.n = hold_attr(&h, ag, "n")) == NULL || (s.ids = hold_attr(&h, ag, "ids")) == NULL) goto done;
    for (int c = 0; c < PHYS_NCOL; c++) {
        arr_t *a = hold_arr(&h, ag, PHYS_COLS[c].name);
        if (a == NULL || !arr_is(a, PHYS_COLS[c].kind, PHYS_COLS[c].size)) goto done;
        s.col[c] = a;
    }
    out = emit_bytes(emit_physics, &s);
done:
    hold_release(&h);
    PyErr_Clear();
    if (out == NULL) Py_RETURN_NONE;
    return out;
}

/* ------------------------------------------------------------------ module */

static int fill_bounds(column_t *cols, int ncol, PyObject *fb, PyObject *ib) {
    for (int c = 0; c < ncol; c++) {
        column_t *col = &cols[c];
        PyObject *b = PyDict_GetItemString(col->kind == 'f' ? fb : ib, col->name);  /* borrowed */
        double lo, hi;
        if (b == NULL) {
            if (col->kind == 'f') {  /* FLOAT_BOUNDS has no entry: any finite value */
                col->bounded = 1;
                col->lo = -FINITE_MAX;
                col->hi = FINITE_MAX;
            } else {
                col->bounded = 0;
            }
            continue;
        }
        if (!PyTuple_Check(b) || PyTuple_GET_SIZE(b) != 2) {
            PyErr_Format(PyExc_ValueError, "bounds of %s: expected (lo, hi)", col->name);
            return 0;
        }
        lo = PyFloat_AsDouble(PyTuple_GET_ITEM(b, 0));
        hi = PyFloat_AsDouble(PyTuple_GET_ITEM(b, 1));
        if (PyErr_Occurred()) return 0;
        col->bounded = 1;
        col->lo = lo;
        col->hi = hi;
    }
    return 1;
}

static PyObject *py_configure(PyObject *self, PyObject *args) {
    long long major, minor;
    PyObject *fb, *ib;
    (void)self;
    if (!PyArg_ParseTuple(args, "LLO!O!", &major, &minor, &PyDict_Type, &fb, &PyDict_Type, &ib)) return NULL;
    g_ready = 0;
    if (!fill_bounds(STEP_COLS, STEP_NCOL, fb, ib) || !fill_bounds(PHYS_COLS, PHYS_NCOL, fb, ib)) return NULL;
    /* the path's offsets share la_dx's symmetric bounds (OFFSET_LIMIT) */
    if (STEP_COLS[S_LADX].lo != -STEP_COLS[S_LADX].hi) {
        PyErr_SetString(PyExc_ValueError, "la_dx bounds must be symmetric");
        return NULL;
    }
    /* integer bounds must be integers within the column type (the checks compare as double) */
    for (int c = 0; c < PHYS_NCOL; c++) {
        int j;
        for (j = A_COL0; j < N_AGENT_KEYS; j++)
            if (strcmp(AGENT_KEYS[j].s, PHYS_COLS[c].name) == 0) break;
        if (j == N_AGENT_KEYS) {
            PyErr_Format(PyExc_ValueError, "no agent key %s", PHYS_COLS[c].name);
            return NULL;
        }
        PHYS_KEY[c] = j;
    }
    for (int c = 0; c < STEP_NCOL; c++)
        if (strcmp(AGENT_KEYS[A_COL0 + c].s, STEP_COLS[c].name) != 0) {
            PyErr_Format(PyExc_ValueError, "agent key %d is not %s", A_COL0 + c, STEP_COLS[c].name);
            return NULL;
        }
    {  /* the largest float32 within the bound, as bits: path offsets are tested on their bits */
        double lim = STEP_COLS[S_LADX].hi;
        float f;
        if (!(lim >= 0)) {
            PyErr_SetString(PyExc_ValueError, "la_dx bounds must be a non-negative range");
            return NULL;
        }
        f = lim >= (double)FLT_MAX ? FLT_MAX : (float)lim;
        memcpy(&g_path_lim_bits, &f, 4);
        if ((double)f > lim) g_path_lim_bits--;  /* rounded up: the float below it */  /* rounded up: the float below it */
    }
    g_major = major;
    g_minor = minor;
    g_ready = host_is_little();
    return PyBool_FromLong(g_ready);
}

static PyObject *py_clear_cache(PyObject *self, PyObject *unused) {
    (void)self;
    (void)unused;
    id_cache_clear();
    Py_RETURN_NONE;
}

static PyObject *py_cache_size(PyObject *self, PyObject *unused) {
    (void)self;
    (void)unused;
    return Py_BuildValue("(nn)", (Py_ssize_t)g_ids_used, (Py_ssize_t)g_ids_cap);
}

static PyMethodDef methods[] = {
    {"clear_cache", py_clear_cache, METH_NOARGS, "clear_cache(): drop the cached id strings."},
    {"cache_size", py_cache_size, METH_NOARGS, "cache_size() -> (ids cached, slots)."},
    {"configure", py_configure, METH_VARARGS,
     "configure(major, minor, float_bounds, int_bounds) -> bool: set the version and the column "
     "bounds; False when this host cannot use the fast path (big-endian)."},
    {"decode", (PyCFunction)(void (*)(void))py_decode, METH_FASTCALL,
     "decode(data, limits) -> tuple | None: a step or physics message's parts, or None (use the Python decoder)."},
    {"encode_step", (PyCFunction)(void (*)(void))py_encode_step, METH_FASTCALL,
     "encode_step(msg, agents, tls) -> bytes | None: the msgpack of a StepMessage, or None."},
    {"encode_physics", (PyCFunction)(void (*)(void))py_encode_physics, METH_FASTCALL,
     "encode_physics(msg, agents) -> bytes | None: the msgpack of a PhysicsState, or None."},
    {NULL, NULL, 0, NULL},
};

SC_MODULE(PyInit__fastcodec, "protocol._fastcodec",
          "C fast path of protocol.codec for step and physics messages (None: use the Python codec).", methods)
