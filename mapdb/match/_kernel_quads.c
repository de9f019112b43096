/* Image quads looked up in the map's quad trees (see _kernel_quads.h). */
#include "_kernel_quads.h"

#include <float.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

/* ------------------------------------------------------------------ lookup */

typedef struct {
    double d2;
    double tie;         /* among equal distances, the nearer to the prior's place first (0 without) */
    int64_t i;          /* the point's row (in a joint lookup, its tree's first row added: the merged tree's row) */
    int64_t own;        /* its row in its own tree */
    Py_ssize_t at;      /* its place in its tree's order */
    Py_ssize_t tree;    /* which tree */
} QuadsHit;

/* (d2, tie, i) ordering: nearer first; equal distances nearer the prior's place (an index without positions looked
 * up near one), then by point row. */
static int quads_before(const QuadsHit *x, const QuadsHit *y)
{
    if (x->d2 != y->d2) {
        return x->d2 < y->d2;
    }
    return x->tie < y->tie || (x->tie == y->tie && x->i < y->i);
}

/* The k best so far, a max-heap (its worst at 0). */
typedef struct {
    QuadsHit *h;
    Py_ssize_t n, k;
    double bound2;
    const double *quad_z;  /* with ``by_place``: equal distances ranked by the squared distance of the quad's */
    double cx, cy;         /* centroid to (cx, cy) */
    int by_place;
    int64_t offset;        /* the tree searched: its first row among the trees looked up jointly, and which */
    Py_ssize_t tree;
} QuadsBest;

static void quads_offer(QuadsBest *b, double d2, int64_t i, Py_ssize_t at_tree)
{
    QuadsHit x = {d2, 0.0, b->offset + i, i, at_tree, b->tree};
    if (b->by_place) {
        const double *z = b->quad_z + 8 * i;
        double ex = 0.25 * (z[0] + z[2] + z[4] + z[6]) - b->cx, ey = 0.25 * (z[1] + z[3] + z[5] + z[7]) - b->cy;
        x.tie = ex * ex + ey * ey;
    }
    Py_ssize_t at;
    if (b->n < b->k) {
        if (!(d2 < b->bound2)) {
            return;
        }
        at = b->n++;
        while (at > 0 && quads_before(&b->h[(at - 1) / 2], &x)) {
            b->h[at] = b->h[(at - 1) / 2];
            at = (at - 1) / 2;
        }
        b->h[at] = x;
        return;
    }
    if (!quads_before(&x, &b->h[0])) {
        return;
    }
    at = 0;
    for (;;) {
        Py_ssize_t c = 2 * at + 1;
        if (c >= b->n) {
            break;
        }
        if (c + 1 < b->n && quads_before(&b->h[c], &b->h[c + 1])) {
            c++;
        }
        if (!quads_before(&x, &b->h[c])) {
            break;
        }
        b->h[at] = b->h[c];
        at = c;
    }
    b->h[at] = x;
}

/* The least squared distance from ``q`` to a node's box, summed in dimension order with each gap the difference a
 * point's distance takes (p - q): never above the computed distance of a point in the box. */
static double quads_low(const double *box, const double *q, Py_ssize_t d)
{
    double low = 0.0;
    for (Py_ssize_t j = 0; j < d; j++) {
        double g = box[j] > q[j] ? box[j] - q[j] : q[j] > box[d + j] ? box[d + j] - q[j] : 0.0;
        low += g * g;
    }
    return low;
}

/* The limit a distance must stay within (below the bound, or at most the k-th so far). */
static int quads_within(const QuadsBest *b, double s)
{
    return b->n < b->k ? s < b->bound2 : s <= b->h[0].d2;
}

static void quads_search(const QuadsTree *t, Py_ssize_t node, const double *q, QuadsBest *b)
{
    const QuadsNode *nd = &t->nodes[node];
    Py_ssize_t d = t->d;
    if (nd->left < 0) {
        for (Py_ssize_t i = nd->lo; i < nd->hi; i++) {
            const double *p = t->pts + i * d;
            double s = 0.0;
            Py_ssize_t j = 0;
            for (; j < d && quads_within(b, s); j++) {  /* partial sums only grow: stop once beyond */
                double e = p[j] - q[j];
                s += e * e;
            }
            if (j == d) {
                quads_offer(b, s, t->idx[i], i);
            }
        }
        return;
    }
    double l = quads_low(t->box + 2 * d * nd->left, q, d), r = quads_low(t->box + 2 * d * nd->right, q, d);
    Py_ssize_t first = l <= r ? nd->left : nd->right, second = l <= r ? nd->right : nd->left;
    double lf = l <= r ? l : r, ls = l <= r ? r : l;
    if (quads_within(b, lf)) {
        quads_search(t, first, q, b);
    }
    if (quads_within(b, ls)) {
        quads_search(t, second, q, b);
    }
}

static int qhit_cmp(const void *x, const void *y)
{
    const QuadsHit *u = x, *v = y;
    return quads_before(u, v) ? -1 : quads_before(v, u) ? 1 : 0;
}

/* Growing outputs: query rows and map points (4 complex a hit). */
typedef struct {
    int64_t *rows;
    double *z;
    Py_ssize_t n, cap;
} QuadsOut;

static int quads_push(QuadsOut *o, int64_t row, const double *z4)
{
    if (o->n == o->cap) {
        Py_ssize_t cap = o->cap ? 2 * o->cap : 256;
        int64_t *rows = realloc(o->rows, sizeof(int64_t) * cap);
        if (rows) {
            o->rows = rows;
        }
        double *z = rows ? realloc(o->z, sizeof(double) * 8 * cap) : NULL;
        if (!z) {
            return -1;
        }
        o->z = z;
        o->cap = cap;
    }
    o->rows[o->n] = row;
    memcpy(o->z + 8 * o->n, z4, sizeof(double) * 8);
    o->n++;
    return 0;
}

/* What a lookup is asked: the queries' invariants, label keys and radii, k, the prior's place and reach (tree
 * units; positions only) and the bound of the tree's distance. */
typedef struct {
    const double *inv, *key, *radius;
    Py_ssize_t m, k;
    double px, py, reach, bound;
    int by_place;  /* an index without positions looked up near (px, py) metres: ties broken by the place */
} QuadsAsk;

/* The squared distance a query's search stays below: the lookup's bound, or less where the query's own filter
 * (its radius, and with positions the reach) keeps no point beyond: a hit kept has dist^2 <= radius^2 + reach^2
 * (dist^2 - off^2 <= radius^2 with off^2 <= reach^2), so the search below that (widened far beyond rounding) finds
 * every point the filter keeps, and when k of them are nearer than it, the same k nearest.  The whole lookup's
 * bound is its largest radius plus the reach: a query of a small radius searched a ball as wide as the widest's. */
static double quads_query_bound(const QuadsAsk *ask, double radius, int positions)
{
    double bound2 = ask->bound * ask->bound;
    double mine = (radius * radius + (positions ? ask->reach * ask->reach : 0.0)) * (1.0 + 1e-9) + DBL_MIN;
    return mine <= bound2 ? mine : bound2;
}

/* Query ``r``'s hits in trees [from, to) (their map points ``zs``, first rows ``offsets``), filtered as
 * QuadIndex.lookup did, appended to ``o``: one tree's k nearest, or with several the k nearest of them all, as one
 * tree over their points concatenated (QuadIndex.merged) would find them; -1 out of memory. */
static int quads_lookup_query(QuadsTree *const *tt, const double *const *zs, const int64_t *offsets, Py_ssize_t from,
                              Py_ssize_t to, const QuadsAsk *ask, Py_ssize_t r, QuadsBest *b, QuadsOut *o)
{
    double q[QUADS_MAX_DIM];
    int positions = tt[from]->d == 7;
    memcpy(q, ask->inv + 4 * r, sizeof(double) * 4);
    q[4] = ask->key[r];
    q[5] = ask->px;
    q[6] = ask->py;
    b->n = 0;
    b->bound2 = quads_query_bound(ask, ask->radius[r], positions);
    for (Py_ssize_t t = from; t < to; t++) {
        b->quad_z = zs[t];
        b->offset = offsets[t];
        b->tree = t;
        if (quads_within(b, quads_low(tt[t]->box, q, tt[t]->d))) {
            quads_search(tt[t], 0, q, b);
        }
    }
    qsort(b->h, (size_t)b->n, sizeof(QuadsHit), qhit_cmp);
    double rad = ask->radius[r];
    for (Py_ssize_t c = 0; c < b->n; c++) {
        const QuadsHit *hit = &b->h[c];
        double dist = sqrt(hit->d2);
        int keep = dist <= (positions ? ask->bound : rad);
        if (keep && positions) {
            /* The tree's distance mixes the invariants' with the position's: split them (as lookup() did). */
            const double *p = tt[hit->tree]->pts + hit->at * tt[hit->tree]->d;
            double ex = p[5] - ask->px, ey = p[6] - ask->py;
            double off2 = ex * ex + ey * ey;
            keep = dist * dist - off2 <= rad * rad && off2 <= ask->reach * ask->reach;
        }
        if (keep && quads_push(o, r, zs[hit->tree] + 8 * hit->own) < 0) {
            return -1;
        }
    }
    return 0;
}

/* Every query's hits: tree by tree (each tree's k nearest), or with ``joint`` query by query over all the trees
 * (their k nearest together, the rows of later trees after those of earlier ones); -1 out of memory. */
static int quads_lookup_trees(QuadsTree *const *tt, const double *const *zs, Py_ssize_t nt, int joint,
                              const QuadsAsk *ask, QuadsHit *heap, QuadsOut *o)
{
    int64_t offsets[256];
    Py_ssize_t total = 0;
    for (Py_ssize_t t = 0; t < nt; t++) {
        offsets[t] = joint ? total : 0;
        total += tt[t]->n;
    }
    QuadsBest b = {heap, 0, 0, 0.0, NULL, ask->px, ask->py, ask->by_place && tt[0]->d != 7, 0, 0};
    if (joint) {
        b.k = ask->k < total ? ask->k : total;
        for (Py_ssize_t r = 0; r < ask->m; r++) {
            if (quads_lookup_query(tt, zs, offsets, 0, nt, ask, r, &b, o) < 0) {
                return -1;
            }
        }
        return 0;
    }
    for (Py_ssize_t t = 0; t < nt; t++) {
        b.k = ask->k < tt[t]->n ? ask->k : tt[t]->n;
        b.by_place = ask->by_place && tt[t]->d != 7;
        for (Py_ssize_t r = 0; r < ask->m; r++) {
            if (quads_lookup_query(tt, zs, offsets, t, t + 1, ask, r, &b, o) < 0) {
                return -1;
            }
        }
    }
    return 0;
}

/* The trees and their map points, checked: 0, or -1 with an error set. */
static int quads_take_trees(PyObject *trees, PyObject *zs, Arr *za, QuadsTree **tt, Py_ssize_t nt)
{
    for (Py_ssize_t i = 0; i < nt; i++) {
        PyObject *cap = PyTuple_GET_ITEM(trees, i);
        tt[i] = PyCapsule_IsValid(cap, QUADS_CAPSULE) ? PyCapsule_GetPointer(cap, QUADS_CAPSULE) : NULL;
        if (!tt[i]) {
            PyErr_SetString(PyExc_TypeError, "trees must hold quads_build's trees");
            return -1;
        }
        if (arr_take(PyTuple_GET_ITEM(zs, i), &za[i], "quad_z", 'Z', 2, 0, 0)
            || arr_check_shape(&za[i], "quad_z", tt[i]->n, 4)) {
            return -1;
        }
        if (tt[i]->d != 5 && tt[i]->d != 7) {
            PyErr_SetString(PyExc_ValueError, "a quad tree has 5 columns (7 with positions)");
            return -1;
        }
    }
    return 0;
}

static PyObject *quads_result(QuadsOut *o)
{
    PyObject *rows = PyByteArray_FromStringAndSize((const char *)o->rows, (Py_ssize_t)sizeof(int64_t) * o->n);
    PyObject *z = rows ? PyByteArray_FromStringAndSize((const char *)o->z, (Py_ssize_t)sizeof(double) * 8 * o->n)
                       : NULL;
    PyObject *out = z ? PyTuple_Pack(2, rows, z) : NULL;
    Py_XDECREF(rows);
    Py_XDECREF(z);
    return out;
}

/* The hits of trees ``tt`` (checked, their map points ``za``): -1 with an error set when they cannot be looked up
 * jointly (trees of different columns) or out of memory. */
static PyObject *quads_hits(QuadsTree *const *tt, const Arr *za, Py_ssize_t nt, int joint, const QuadsAsk *ask)
{
    const double *zs[256];
    Py_ssize_t most = 1, total = 0;
    for (Py_ssize_t i = 0; i < nt; i++) {
        if (joint && tt[i]->d != tt[0]->d) {
            return PyErr_Format(PyExc_ValueError, "trees looked up jointly have the same columns");
        }
        zs[i] = D(za[i]);
        most = tt[i]->n > most ? tt[i]->n : most;
        total += tt[i]->n;
    }
    most = joint && total > most ? total : most;
    most = ask->k < most ? ask->k : most;
    QuadsHit *heap = malloc(sizeof(QuadsHit) * (size_t)most);
    if (!heap) {
        return PyErr_NoMemory();
    }
    QuadsOut o = {NULL, NULL, 0, 0};
    int bad = 0;
    if (nt) {
        Py_BEGIN_ALLOW_THREADS
        bad = quads_lookup_trees(tt, zs, nt, joint, ask, heap, &o);
        Py_END_ALLOW_THREADS
    }
    PyObject *out = bad ? PyErr_NoMemory() : quads_result(&o);
    free(heap);
    free(o.rows);
    free(o.z);
    return out;
}

static PyObject *quads_lookup(PyObject *self, PyObject *args)
{
    PyObject *trees, *zs, *oinv, *okey, *orad;
    QuadsAsk ask;
    int joint = 0;
    Arr a[3] = {{{0}}};
    if (!PyArg_ParseTuple(args, "O!O!OOOnddddp|p:quads_lookup", &PyTuple_Type, &trees, &PyTuple_Type, &zs, &oinv,
                          &okey, &orad, &ask.k, &ask.px, &ask.py, &ask.reach, &ask.bound, &ask.by_place, &joint)) {
        return NULL;
    }
    Py_ssize_t nt = PyTuple_GET_SIZE(trees);
    if (PyTuple_GET_SIZE(zs) != nt || nt > 256 || ask.k < 1) {
        return PyErr_Format(PyExc_ValueError, "need as many quad_z as trees (at most 256) and k >= 1");
    }
    if (arr_take(oinv, &a[0], "invariants", 'd', 2, 0, 0) || arr_take(okey, &a[1], "key", 'd', 1, 0, 0)
        || arr_take(orad, &a[2], "radius", 'd', 1, 0, 0)) {
        arr_release(a, 3);
        return NULL;
    }
    ask.m = arr_dim(&a[0], 0);
    if (arr_check_shape(&a[0], "invariants", ask.m, 4) || arr_check_shape(&a[1], "key", ask.m, 0)
        || arr_check_shape(&a[2], "radius", ask.m, 0)) {
        arr_release(a, 3);
        return NULL;
    }
    ask.inv = D(a[0]);
    ask.key = D(a[1]);
    ask.radius = D(a[2]);
    Arr za[256];
    QuadsTree *tt[256];
    memset(za, 0, sizeof(Arr) * (size_t)nt);
    PyObject *out = quads_take_trees(trees, zs, za, tt, nt) ? NULL : quads_hits(tt, za, nt, joint, &ask);
    arr_release(za, (int)nt);
    arr_release(a, 3);
    return out;
}

PyMethodDef quads_methods[] = {
    {"quads_lookup", quads_lookup, METH_VARARGS,
     "quads_lookup(trees, quad_zs, invariants, key, radius, k, px, py, reach, bound, by_place, joint=False): the hits of "
     "image quads in each tree, tree by tree, or with joint in all the trees as one (the k nearest of them all, rows "
     "numbered through the trees in turn): (query rows, map points) as bytearrays of int64 and of complex128 (h, 4)."},
    {NULL, NULL, 0, NULL},
};
