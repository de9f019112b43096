/* An image's quad lookups turned into hypotheses in few calls (mapdb.match.hypotheses, mapdb.match.index.stored).
 *
 * hits_stored_lookup: StoredQuadIndex.lookup's query rows prepared (each row's label key and its combination's cell
 * side, rows with labels out of range, non-finite invariants or radius, negative radius or an unknown combination
 * left out, radii clamped to the cell side as np.minimum does) and looked up (stored_run) in one call, the answer's
 * rows those of the caller's query.
 * hits_points: StoredQuadIndex.coordinates of objects whose coordinate blocks are decoded.
 * hits_hypotheses: round_hypotheses' hits made hypotheses: each hit's image ids (its key row's), the similarity
 * fitted to its four points (fit_row, numpy's arithmetic) and the poses the search may answer (quads_pose_allowed).
 */
#include "_kernel_quads.h"
#include "_kernel_stored.h"

#include <stdlib.h>
#include <string.h>

/* Query rows kept by hits_stored_lookup, in the caller's order. */
typedef struct {
    int64_t *rows, *lk;
    double *q, *r, *cell;
    Py_ssize_t n;
    int fresh;  /* a kept row's combination not audited yet */
} HitsKept;

static void hits_kept_free(HitsKept *h)
{
    free(h->rows), free(h->lk), free(h->q), free(h->r), free(h->cell);
}

/* The combination of a row's labels (index into keys), or -1 (labels out of range, combination absent). */
static Py_ssize_t hits_combo(const int64_t *lab, int64_t n_labels, const int64_t *keys, Py_ssize_t c)
{
    int64_t key = 0, base = n_labels > 1 ? n_labels : 1;
    for (int j = 0; j < 4; j++) {
        if (lab[j] < 0 || lab[j] >= n_labels) {
            return -1;
        }
        key = key * base + lab[j];
    }
    Py_ssize_t lo = 0, hi = c;  /* np.searchsorted(keys, key): the first at or above */
    while (lo < hi) {
        Py_ssize_t mid = lo + (hi - lo) / 2;
        if (keys[mid] < key) {
            lo = mid + 1;
        } else {
            hi = mid;
        }
    }
    return lo < c && keys[lo] == key ? lo : -1;
}

/* The rows worth looking up (a[0..5]: invariants, labels, radius, combination keys, cells, audited). */
static int hits_keep(Arr *a, int64_t n_labels, HitsKept *h)
{
    Py_ssize_t m = arr_dim(&a[0], 0), c = arr_dim(&a[3], 0);
    const double *inv = D(a[0]), *radius = D(a[2]), *cells = D(a[4]);
    const int64_t *lab = Q(a[1]), *keys = Q(a[3]);
    const unsigned char *audited = B(a[5]);
    size_t room = (size_t)m + 1;
    h->rows = malloc(room * 8), h->lk = malloc(room * 8), h->q = malloc(room * 32), h->r = malloc(room * 8);
    h->cell = malloc(room * 8);
    if (!h->rows || !h->lk || !h->q || !h->r || !h->cell) {
        PyErr_NoMemory();
        return -1;
    }
    for (Py_ssize_t i = 0; i < m; i++) {
        const double *qi = inv + 4 * i;
        double r = radius[i];
        Py_ssize_t at = hits_combo(lab + 4 * i, n_labels, keys, c);
        if (at < 0 || !isfinite(qi[0]) || !isfinite(qi[1]) || !isfinite(qi[2]) || !isfinite(qi[3]) || !isfinite(r)
            || !(r >= 0)) {
            continue;
        }
        double cell = cells[at];
        h->rows[h->n] = i, h->lk[h->n] = keys[at], h->cell[h->n] = cell;
        h->r[h->n] = (r <= cell || isnan(r)) ? r : cell;  /* np.minimum */
        memcpy(h->q + 4 * h->n, qi, 32);
        h->fresh |= !audited[at];
        h->n++;
    }
    return 0;
}

static int hits_take_ask(PyObject **o, Arr *a)
{
    if (arr_take(o[0], &a[0], "invariants", 'd', 2, 0, 0) || arr_take(o[1], &a[1], "labels", 'q', 2, 0, 0)
        || arr_take(o[2], &a[2], "radius", 'd', 1, 0, 0) || arr_take(o[3], &a[3], "combination keys", 'q', 1, 0, 0)
        || arr_take(o[4], &a[4], "cells", 'd', 1, 0, 0) || arr_take(o[5], &a[5], "audited", '?', 1, 0, 0)) {
        return -1;
    }
    Py_ssize_t m = arr_dim(&a[0], 0), c = arr_dim(&a[3], 0);
    return arr_check_shape(&a[0], "invariants", m, 4) || arr_check_shape(&a[1], "labels", m, 4)
        || arr_check_shape(&a[2], "radius", m, 0) || arr_check_shape(&a[4], "cells", c, 0)
        || arr_check_shape(&a[5], "audited", c, 0) ? -1 : 0;
}

/* hits_stored_lookup(tables, invariants, labels, radius, combo_keys, combo_cells, n_labels, audited, k, limit). */
static PyObject *hits_stored_lookup(PyObject *self, PyObject *args)
{
    PyObject *ot, *o[6], *out = NULL;
    long long n_labels;
    StoredAsk ask = {0};
    if (!PyArg_ParseTuple(args, "OOOOOOLOnn:hits_stored_lookup", &ot, &o[0], &o[1], &o[2], &o[3], &o[4], &n_labels,
                          &o[5], &ask.k, &ask.limit)) {
        return NULL;
    }
    StoredTables t;
    memset(&t, 0, sizeof(t));  /* released below whichever check fails */
    Arr a[6] = {{{0}}};
    HitsKept h = {0};
    if (ask.k < 1 || ask.limit < 1) {
        PyErr_SetString(PyExc_ValueError, "k and limit must be at least 1");
    } else if (!stored_take_tables(ot, &t) && !hits_take_ask(o, a) && !hits_keep(a, n_labels, &h)) {
        if (h.fresh) {  /* the caller audits these combinations first (StoredQuadIndex._audit), then asks again */
            PyObject *lk = PyBytes_FromStringAndSize((const char *)h.lk, h.n * 8);
            out = lk ? Py_BuildValue("(iN)", 3, lk) : NULL;
        } else {
            ask.q = h.q, ask.r = h.r, ask.cell = h.cell, ask.lk = h.lk, ask.m = h.n;
            out = stored_run(&t, &ask, h.rows);
        }
    }
    hits_kept_free(&h);
    arr_release(t.a, STORED_TABLES), arr_release(a, 6);
    return out;
}

/* hits_points(tables, ids): (0, positions as a bytearray of complex), (1,) when a block is not decoded yet, (2,)
 * when an id is out of range. */
static PyObject *hits_points(PyObject *self, PyObject *args)
{
    PyObject *ot, *oi, *out = NULL;
    if (!PyArg_ParseTuple(args, "OO:hits_points", &ot, &oi)) {
        return NULL;
    }
    StoredTables t;
    memset(&t, 0, sizeof(t));
    Arr a = {{0}};
    if (!stored_take_tables(ot, &t) && !arr_take(oi, &a, "ids", 'q', 1, 0, 0)) {
        Py_ssize_t n = arr_dim(&a, 0);
        const int64_t *ids = Q(a);
        int code = 0;
        for (Py_ssize_t i = 0; i < n && !code; i++) {
            code = ids[i] < 0 || ids[i] >= t.n_objects ? 2 : !t.co_decoded[ids[i] / STORED_NB_BLOCK];
        }
        PyObject *z = code ? NULL : PyByteArray_FromStringAndSize(NULL, n * 16);
        if (z != NULL) {
            double *p = (double *)PyByteArray_AS_STRING(z);
            for (Py_ssize_t i = 0; i < n; i++) {  /* (xy + origin) * quantum, as coordinates' int64 and float64 */
                p[2 * i] = (double)((int64_t)t.xy[2 * ids[i]] + t.ox) * t.quantum;
                p[2 * i + 1] = (double)((int64_t)t.xy[2 * ids[i] + 1] + t.oy) * t.quantum;
            }
            out = Py_BuildValue("(iN)", 0, z);
        } else if (code) {
            out = Py_BuildValue("(i)", code);
        }
    }
    arr_release(t.a, STORED_TABLES), arr_release(&a, 1);
    return out;
}

/* The pose filter of hits_hypotheses' arguments. */
typedef struct {
    int with_prior, with_scale;
    double cx, cy, reach, lo, hi;
} HitsPoses;

/* Each hit's image ids, fitted similarity and whether it is allowed; the kept ones written compactly, their count
 * returned (-1 with ValueError set when a hit names a key row or an image object out of range). */
static Py_ssize_t hits_fit(Arr *a, const HitsPoses *ps, int64_t *ids_out, double *map_out, double **ab_out)
{
    Py_ssize_t n = arr_dim(&a[0], 0), keys = arr_dim(&a[2], 0), h = arr_dim(&a[3], 0), kept = 0;
    const double *z = D(a[0]), *w = a[1].held ? D(a[1]) : NULL, *map_z = D(a[4]);
    const int64_t *key_ids = Q(a[2]), *row = Q(a[3]);
    double src[8], wt[4], buf[12], fit[4];
    for (Py_ssize_t i = 0; i < h; i++) {
        if (row[i] < 0 || row[i] >= keys) {
            PyErr_SetString(PyExc_ValueError, "a hit's query row is out of range");
            return -1;
        }
        const int64_t *ids = key_ids + 4 * row[i];
        for (int j = 0; j < 4; j++) {
            if (ids[j] < 0 || ids[j] >= n) {
                PyErr_SetString(PyExc_ValueError, "a quad's image object is out of range");
                return -1;
            }
            src[2 * j] = z[2 * ids[j]], src[2 * j + 1] = z[2 * ids[j] + 1];
            wt[j] = w ? w[ids[j]] : 1.0;
        }
        fit_row(src, map_z + 8 * i, wt, 4, buf, fit);
        if (!quads_pose_allowed(fit, fit + 2, ps->with_prior, ps->cx, ps->cy, ps->reach, ps->with_scale, ps->lo,
                                ps->hi)) {
            continue;
        }
        memcpy(ids_out + 4 * kept, ids, 32);
        memcpy(map_out + 8 * kept, map_z + 8 * i, 64);
        memcpy(ab_out[0] + 2 * kept, fit, 16);
        memcpy(ab_out[1] + 2 * kept, fit + 2, 16);
        kept++;
    }
    return kept;
}

/* hits_hypotheses(z, weight, key_ids, rows, map_z, with_prior, cx, cy, reach, with_scale, lo, hi): the kept hits'
 * image ids (H, 4) int64, map points (H, 4) complex and similarities a, b (H,) complex, as bytearrays. */
static PyObject *hits_hypotheses(PyObject *self, PyObject *args)
{
    PyObject *o[5], *out = NULL;
    HitsPoses ps;
    if (!PyArg_ParseTuple(args, "OOOOOpdddpdd:hits_hypotheses", &o[0], &o[1], &o[2], &o[3], &o[4], &ps.with_prior,
                          &ps.cx, &ps.cy, &ps.reach, &ps.with_scale, &ps.lo, &ps.hi)) {
        return NULL;
    }
    Arr a[5] = {{{0}}};
    if (arr_take(o[0], &a[0], "z", 'Z', 1, 0, 0) || arr_take(o[1], &a[1], "weight", 'd', 1, 0, 1)
        || arr_take(o[2], &a[2], "key ids", 'q', 2, 0, 0) || arr_take(o[3], &a[3], "rows", 'q', 1, 0, 0)
        || arr_take(o[4], &a[4], "map_z", 'Z', 2, 0, 0) || arr_check_shape(&a[1], "weight", arr_dim(&a[0], 0), 0)
        || arr_check_shape(&a[2], "key ids", arr_dim(&a[2], 0), 4)
        || arr_check_shape(&a[4], "map_z", arr_dim(&a[3], 0), 4)) {
        arr_release(a, 5);
        return NULL;
    }
    Py_ssize_t h = arr_dim(&a[3], 0);
    PyObject *ids = PyByteArray_FromStringAndSize(NULL, h * 32), *mz = PyByteArray_FromStringAndSize(NULL, h * 64);
    PyObject *oa = PyByteArray_FromStringAndSize(NULL, h * 16), *ob = PyByteArray_FromStringAndSize(NULL, h * 16);
    Py_ssize_t kept = -1;
    if (ids && mz && oa && ob) {
        double *ab[2] = {(double *)PyByteArray_AS_STRING(oa), (double *)PyByteArray_AS_STRING(ob)};
        kept = hits_fit(a, &ps, (int64_t *)PyByteArray_AS_STRING(ids), (double *)PyByteArray_AS_STRING(mz), ab);
    }
    if (kept >= 0 && PyByteArray_Resize(ids, kept * 32) == 0 && PyByteArray_Resize(mz, kept * 64) == 0
        && PyByteArray_Resize(oa, kept * 16) == 0 && PyByteArray_Resize(ob, kept * 16) == 0) {
        out = PyTuple_Pack(4, ids, mz, oa, ob);
    }
    Py_XDECREF(ids), Py_XDECREF(mz), Py_XDECREF(oa), Py_XDECREF(ob);
    arr_release(a, 5);
    return out;
}

PyMethodDef hits_methods[] = {
    {"hits_stored_lookup", hits_stored_lookup, METH_VARARGS,
     "hits_stored_lookup(tables, invariants, labels, radius, combo_keys, combo_cells, n_labels, audited, k, limit): "
     "StoredQuadIndex.lookup's rows prepared and looked up: stored_lookup's answers, its rows the query's, or "
     "(3, label keys) when a combination must be audited first."},
    {"hits_points", hits_points, METH_VARARGS,
     "hits_points(tables, ids): (0, positions as complex bytes), (1,) when a coordinate block is not decoded, (2,) "
     "when an id is out of range."},
    {"hits_hypotheses", hits_hypotheses, METH_VARARGS,
     "hits_hypotheses(z, weight, key_ids, rows, map_z, with_prior, cx, cy, reach, with_scale, lo, hi): the hits "
     "made hypotheses (round_hypotheses): the kept ones' image ids, map points, a and b, as bytearrays."},
    {NULL, NULL, 0, NULL},
};
