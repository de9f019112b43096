/* The map objects' KD-trees per label (see _kernel_objects.c): the objects of a label within discs, counted or
 * listed, and each label's density in discs over several trees (a paged index's forest). */
#include "_kernel_objects.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

/* ------------------------------------------------------------------ discs */

/* The objects of node ``nd`` within squared distance ``r2`` of (qx, qy): counted, and written to ``out`` (when not
 * NULL, at most ``room``). */
static Py_ssize_t objects_disc_node(ObjectsTree *t, int64_t nd, double qx, double qy, double r2,
                                    int64_t *out, Py_ssize_t room)
{
    const int64_t *nn = t->node + 3 * nd;
    if (!objects_node_ok(t, nd) || objects_box_near2(t, nd, qx, qy) > r2 || isnan(r2)) {
        return 0;
    }
    if (objects_box_far2(t, nd, qx, qy) <= r2) {
        Py_ssize_t c = (Py_ssize_t)(nn[1] - nn[0]);
        for (Py_ssize_t j = 0; out != NULL && j < c && j < room; j++) {
            out[j] = t->pid[nn[0] + j];
        }
        return c;
    }
    if (nn[2] < 0) {
        Py_ssize_t c = 0;
        for (int64_t j = nn[0]; j < nn[1]; j++) {
            if (objects_d2(t->pts + 2 * j, qx, qy) <= r2) {
                if (out != NULL && c < room) {
                    out[c] = t->pid[j];
                }
                c++;
            }
        }
        return c;
    }
    Py_ssize_t c = objects_disc_node(t, nd + 1, qx, qy, r2, out, room);
    return c + objects_disc_node(t, nn[2], qx, qy, r2, out ? out + c : NULL, room - c);
}

static int objects_cmp_index(const void *a, const void *b)
{
    int64_t x = *(const int64_t *)a, y = *(const int64_t *)b;
    return (x > y) - (x < y);
}

/* One disc's members (sorted) or count: -1 radius or none: nothing. */
static Py_ssize_t objects_disc(ObjectsTree *t, int64_t l, double qx, double qy, double r, int64_t *out,
                               Py_ssize_t room)
{
    int64_t root = isfinite(qx) && isfinite(qy) ? objects_root(t, l) : -1;
    if (root < 0 || !(r >= 0.0)) {
        return 0;
    }
    Py_ssize_t c = objects_disc_node(t, root, qx, qy, r * r, out, room);
    if (out != NULL && c == room) {
        qsort(out, (size_t)c, sizeof(int64_t), objects_cmp_index);
    }
    return c;
}

/* objects_disc(tree..., w, labels, r, offsets, out): with ``offsets`` None, each disc's count into ``out`` (q,);
 * else its members into out[offsets[j] .. offsets[j + 1]), which must be its count. */
static PyObject *objects_disc_query(PyObject *self, PyObject *args)
{
    PyObject *o[5], *oq, *olab, *or, *ooff, *oout;
    Arr a[10] = {{{0}}};
    ObjectsTree t;
    if (!PyArg_ParseTuple(args, "OOOOOOOOOO:objects_disc", &o[0], &o[1], &o[2], &o[3], &o[4], &oq, &olab, &or,
                          &ooff, &oout)) {
        return NULL;
    }
    if (objects_take_tree(o, a, &t) || arr_take(oq, &a[5], "w", 'Z', 1, 0, 0)
        || arr_take(olab, &a[6], "labels", 'q', 1, 0, 0) || arr_take(or, &a[7], "r", 'd', 1, 0, 0)
        || arr_take(ooff, &a[8], "offsets", 'q', 1, 0, 1) || arr_take(oout, &a[9], "out", 'q', 1, 1, 0)) {
        arr_release(a, 10);
        return NULL;
    }
    Py_ssize_t q = arr_dim(&a[5], 0), total = arr_dim(&a[9], 0);
    if (!arr_check_shape(&a[6], "labels", q, 0) && !arr_check_shape(&a[7], "r", q, 0)) {
        if (!a[8].held) {
            arr_check_shape(&a[9], "out", q, 0);
        } else if (!arr_check_shape(&a[8], "offsets", q + 1, 0)) {
            const int64_t *off = Q(a[8]);
            for (Py_ssize_t j = 0; j < q && !PyErr_Occurred(); j++) {
                if (off[0] != 0 || off[j] > off[j + 1] || off[q] != total) {
                    PyErr_SetString(PyExc_ValueError, "offsets must rise from 0 to len(out)");
                }
            }
        }
    }
    if (PyErr_Occurred()) {
        arr_release(a, 10);
        return NULL;
    }
    const double *w = D(a[5]), *r = D(a[7]);
    const int64_t *lab = Q(a[6]), *off = a[8].held ? Q(a[8]) : NULL;
    int64_t *out = Q(a[9]);
    Py_ssize_t bad = -1;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t j = 0; j < q; j++) {
        if (off == NULL) {
            out[j] = objects_disc(&t, lab[j], w[2 * j], w[2 * j + 1], r[j], NULL, 0);
        } else if (objects_disc(&t, lab[j], w[2 * j], w[2 * j + 1], r[j], out + off[j], off[j + 1] - off[j])
                   != off[j + 1] - off[j] && bad < 0) {
            bad = j;
        }
    }
    Py_END_ALLOW_THREADS
    arr_release(a, 10);
    if (t.bad) {
        return objects_checked(&t);
    }
    if (bad >= 0) {
        PyErr_Format(PyExc_ValueError, "offsets give disc %zd a room other than its count", bad);
        return NULL;
    }
    Py_RETURN_NONE;
}

/* ------------------------------------------------------------------ label densities in discs */

/* ObjectIndex.local_density of one disc (centre cx + i cy, radius r): the share of the fixed disc sample inside
 * the bounds (numpy's complex product r (1 + 0i) * disc and sum, as local_density computed it), the disc's area,
 * and each present label's count over all the trees (at least 1; within min(r, half_gap)), per square metre; the
 * labels not present count 1. */
static void objects_density_row(ObjectsTree *t, Py_ssize_t n_trees, double cx, double cy, double r, const double *disc,
                                Py_ssize_t nd, const double *bounds, const int64_t *present, Py_ssize_t np_,
                                double half_gap, Py_ssize_t n_labels, double *out)
{
    Py_ssize_t inside = 0;
    for (Py_ssize_t j = 0; j < nd; j++) {
        double pr, pi;
        cmul(r, 0.0, disc[2 * j], disc[2 * j + 1], &pr, &pi);
        double x = cx + pr, y = cy + pi;
        inside += x >= bounds[0] && x <= bounds[2] && y >= bounds[1] && y <= bounds[3];
    }
    double share = (double)inside / (double)nd, least = 1.0 / (double)nd;
    double area = (M_PI * (r * r)) * (share >= least ? share : least);
    double rr = half_gap < r ? half_gap : r;  /* numpy's minimum(r, half_gap): NaN kept */
    rr = isnan(r) ? r : rr;
    for (Py_ssize_t l = 0; l < n_labels; l++) {
        out[l] = 1.0 / area;
    }
    for (Py_ssize_t j = 0; j < np_ && n_trees > 0; j++) {
        Py_ssize_t found = 0;
        for (Py_ssize_t k = 0; k < n_trees; k++) {
            found += objects_disc(&t[k], present[j], cx, cy, rr, NULL, 0);
        }
        out[present[j]] = (double)(found > 1 ? found : 1) / area;
    }
}

/* The trees of a sequence of (pts, pid, box, node, root) tuples into t[0 .. n) (their buffers into ta, five a tree;
 * both allocated by the caller, NULL when that failed): 0, or -1 with an error set. */
static int objects_take_trees(PyObject *seq, Py_ssize_t n_trees, ObjectsTree *t, Arr *ta)
{
    if (t == NULL || ta == NULL) {
        PyErr_NoMemory();
        return -1;
    }
    for (Py_ssize_t k = 0; k < n_trees; k++) {
        PyObject *item = PySequence_Fast_GET_ITEM(seq, k), *o[5];
        if (!PyTuple_Check(item) || !PyArg_ParseTuple(item, "OOOOO", &o[0], &o[1], &o[2], &o[3], &o[4])
            || objects_take_tree(o, ta + 5 * k, &t[k])) {
            if (!PyErr_Occurred() || PyErr_ExceptionMatches(PyExc_TypeError)) {
                PyErr_Clear();
                PyErr_SetString(PyExc_TypeError, "each tree must be a tuple (pts, pid, box, node, root)");
            }
            return -1;
        }
    }
    return 0;
}

static PyObject *objects_density(PyObject *self, PyObject *args)
{
    PyObject *otrees, *oc, *or, *odisc, *obounds, *opresent, *oout;
    double half_gap;
    Arr a[6] = {{{0}}};
    if (!PyArg_ParseTuple(args, "OOOOOOdO:objects_density", &otrees, &oc, &or, &odisc, &obounds, &opresent, &half_gap,
                          &oout)) {
        return NULL;
    }
    PyObject *seq = PySequence_Fast(otrees, "trees must be a sequence of (pts, pid, box, node, root)");
    if (seq == NULL) {
        return NULL;
    }
    Py_ssize_t n_trees = PySequence_Fast_GET_SIZE(seq);
    ObjectsTree *t = PyMem_Calloc((size_t)n_trees + 1, sizeof(ObjectsTree));
    Arr *ta = PyMem_Calloc(5 * (size_t)n_trees + 1, sizeof(Arr));
    int failed = objects_take_trees(seq, n_trees, t, ta);
    if (!failed && (arr_take(oc, &a[0], "centres", 'Z', 1, 0, 0) || arr_take(or, &a[1], "radius", 'd', 1, 0, 0)
                    || arr_take(odisc, &a[2], "disc", 'Z', 1, 0, 0) || arr_take(obounds, &a[3], "bounds", 'd', 1, 0, 0)
                    || arr_take(opresent, &a[4], "present", 'q', 1, 0, 0)
                    || arr_take(oout, &a[5], "out", 'd', 2, 1, 0))) {
        failed = 1;
    }
    Py_ssize_t h = arr_dim(&a[0], 0), nl = arr_dim(&a[5], 1), nd = arr_dim(&a[2], 0), np_ = arr_dim(&a[4], 0);
    if (!failed && (arr_check_shape(&a[1], "radius", h, 0) || arr_check_shape(&a[3], "bounds", 4, 0)
                    || arr_check_shape(&a[5], "out", h, nl))) {
        failed = 1;
    }
    for (Py_ssize_t j = 0; !failed && j < np_; j++) {
        if (Q(a[4])[j] < 0 || Q(a[4])[j] >= nl) {
            PyErr_Format(PyExc_ValueError, "present holds %lld, outside 0..%zd", (long long)Q(a[4])[j], nl - 1);
            failed = 1;
        }
    }
    if (!failed && nd < 1) {
        PyErr_SetString(PyExc_ValueError, "disc must hold a point at least");
        failed = 1;
    }
    for (Py_ssize_t r = 0; !failed && r < h; r++) {
        objects_density_row(t, n_trees, D(a[0])[2 * r], D(a[0])[2 * r + 1], D(a[1])[r], D(a[2]), nd, D(a[3]), Q(a[4]),
                            np_, half_gap, nl, D(a[5]) + r * nl);
    }
    int bad = 0;
    for (Py_ssize_t k = 0; t != NULL && k < n_trees; k++) {
        bad |= t[k].bad;
    }
    if (ta != NULL) {
        arr_release(ta, 5 * (int)n_trees);
    }
    PyMem_Free(ta);
    PyMem_Free(t);
    arr_release(a, 6);
    Py_DECREF(seq);
    if (failed) {
        return NULL;
    }
    if (bad) {
        PyErr_SetString(PyExc_ValueError, "node or root holds a position or child outside the tree");
        return NULL;
    }
    Py_RETURN_NONE;
}

PyMethodDef object_discs_methods[] = {
    {"objects_disc", objects_disc_query, METH_VARARGS,
     "objects_disc(pts, pid, box, node, root, w, labels, r, offsets, out): objects of each point's label within "
     "r: counts (offsets None) or sorted members."},
    {"objects_density", objects_density, METH_VARARGS,
     "objects_density(trees, centres, radius, disc, bounds, present, half_gap, out): objects per square metre of "
     "each label in each disc (inside the bounds), over all the trees given."},
    {NULL, NULL, 0, NULL},
};
