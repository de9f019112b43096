/* The map objects' spatial queries (mapdb.match.mapobjects.label_trees): a 2-D KD-tree per label.
 *
 * The objects are grouped by label (ascending index within a label) and each label's run is split at the middle of
 * the wider side of its tight bounding box (sliding midpoint, as scipy's cKDTree splits: one pass a level, half the
 * build time of median splits) until a node holds at most OBJECTS_LEAF objects (a node whose objects all lie at
 * one place stays a leaf however many it holds).  The tree lives in arrays the Python caller
 * allocates (so it pickles and needs no object type here):
 *
 *   pts  (n, 2) float64  the objects' x, y in tree order
 *   pid  (n,)   int64    each tree position's object index
 *   box  (m, 4) float64  each node's tight box: min x, min y, max x, max y
 *   node (m, 3) int64    each node's first and end tree position, and its right child (-1: a leaf); the left
 *                        child is the next node
 *   root (L,)   int64    each label's root node (-1: no object of the label)
 *
 * Queries answer as scipy's cKDTree over (x, y, label * gap) did: a squared distance is dx * dx + dy * dy, a
 * neighbour counts when its squared distance is below the bound's square (strictly), a disc member when it is at
 * most the radius' square; distances are square roots of squared distances.  A query point that is not finite
 * finds nothing (cKDTree refused it).  Where distances tie (duplicate
 * objects), the lower object index comes first (cKDTree's order there was its heap's).  Pruning by a box is exact:
 * rounding is monotonic, so no object in a box is nearer (farther) than the box's computed nearest (farthest)
 * point.
 */
#include "_kernel_objects.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

#define OBJECTS_LEAF 16

/* ------------------------------------------------------------------ building */

/* An object as the build moves it: its place and index side by side, so that splits read memory in order. */
typedef struct {
    double c[2];
    int64_t i;
} ObjectsRec;

static inline void objects_rec_swap(ObjectsRec *a, ObjectsRec *b)
{
    ObjectsRec s = *a;
    *a = *b;
    *b = s;
}

/* Split k[0 .. n) (n >= 2, not all at one place along ``ax``) at the middle of its extent [lo, hi] along ``ax``,
 * sliding the split to the nearest object when one side would be empty (scipy's sliding midpoint): the
 * objects before the split first.  Returns how many there are (1 .. n - 1). */
static Py_ssize_t objects_split(ObjectsRec *k, Py_ssize_t n, int ax, double lo, double hi)
{
    double split = lo + 0.5 * (hi - lo);
    Py_ssize_t i = 0, j = n - 1;
    while (i <= j) {
        if (k[i].c[ax] < split) {
            i++;
        } else if (!(k[j].c[ax] < split)) {
            j--;
        } else {
            objects_rec_swap(&k[i++], &k[j--]);
        }
    }
    Py_ssize_t at = 0;
    if (i == 0) {  /* nothing below the split (it rounded to lo): the lowest alone goes first */
        for (Py_ssize_t t = 1; t < n; t++) {
            at = k[t].c[ax] < k[at].c[ax] ? t : at;
        }
        objects_rec_swap(&k[0], &k[at]);
        return 1;
    }
    if (i == n) {  /* nothing at or above it: the highest alone goes last */
        for (Py_ssize_t t = 1; t < n; t++) {
            at = k[t].c[ax] > k[at].c[ax] ? t : at;
        }
        objects_rec_swap(&k[n - 1], &k[at]);
        return n - 1;
    }
    return i;
}

typedef struct {
    ObjectsRec *rec;
    double *box;
    int64_t *node;
    Py_ssize_t used, capacity;
} ObjectsBuild;

/* Node over tree positions [s, e); returns its number, or -1 when the node arrays are full. */
static int64_t objects_build_node(ObjectsBuild *b, Py_ssize_t s, Py_ssize_t e)
{
    if (b->used >= b->capacity) {
        return -1;
    }
    int64_t nd = b->used++;
    double *bx = b->box + 4 * nd;
    const ObjectsRec *r = b->rec;
    double x0 = INFINITY, y0 = INFINITY, x1 = -INFINITY, y1 = -INFINITY;  /* NaN places stay out: never an answer */
    for (Py_ssize_t j = s; j < e; j++) {
        double px = r[j].c[0], py = r[j].c[1];
        x0 = px < x0 ? px : x0;
        y0 = py < y0 ? py : y0;
        x1 = px > x1 ? px : x1;
        y1 = py > y1 ? py : y1;
    }
    bx[0] = x0;
    bx[1] = y0;
    bx[2] = x1;
    bx[3] = y1;
    int64_t *nn = b->node + 3 * nd;
    nn[0] = s;
    nn[1] = e;
    nn[2] = -1;
    double wx = bx[2] - bx[0], wy = bx[3] - bx[1];
    if (e - s <= OBJECTS_LEAF || !(wx > 0.0 || wy > 0.0)) {
        return nd;  /* few objects, or all at one place (or not finite): a leaf */
    }
    int ax = wx >= wy ? 0 : 1;
    Py_ssize_t half = objects_split(b->rec + s, e - s, ax, bx[ax], bx[ax + 2]);
    if (objects_build_node(b, s, s + half) < 0) {
        return -1;
    }
    int64_t right = objects_build_node(b, s + half, e);
    if (right < 0) {
        return -1;
    }
    nn[2] = right;
    return nd;
}

/* Group the objects by label (counting sort: ascending index within a label) and build each label's tree. */
static int objects_build_all(ObjectsBuild *b, const double *x, const double *y, const int64_t *label, Py_ssize_t n,
                             Py_ssize_t n_labels, int64_t *root, Py_ssize_t *start)
{
    for (Py_ssize_t l = 0; l <= n_labels; l++) {
        start[l] = 0;
    }
    for (Py_ssize_t j = 0; j < n; j++) {
        start[label[j] + 1]++;
    }
    for (Py_ssize_t l = 0; l < n_labels; l++) {
        start[l + 1] += start[l];
    }
    for (Py_ssize_t j = 0; j < n; j++) {
        ObjectsRec *r = &b->rec[start[label[j]]++];
        r->c[0] = x[j];
        r->c[1] = y[j];
        r->i = j;
    }
    for (Py_ssize_t l = n_labels; l > 0; l--) {
        start[l] = start[l - 1];
    }
    start[0] = 0;
    for (Py_ssize_t l = 0; l < n_labels; l++) {
        root[l] = start[l + 1] > start[l] ? objects_build_node(b, start[l], start[l + 1]) : -1;
        if (start[l + 1] > start[l] && root[l] < 0) {
            return -1;
        }
    }
    return 0;
}

static PyObject *objects_build(PyObject *self, PyObject *args)
{
    PyObject *ox, *oy, *olab, *opts, *opid, *obox, *onode, *oroot;
    Arr a[8] = {{{0}}};
    if (!PyArg_ParseTuple(args, "OOOOOOOO:objects_build", &ox, &oy, &olab, &opts, &opid, &obox, &onode, &oroot)) {
        return NULL;
    }
    if (arr_take(ox, &a[0], "x", 'd', 1, 0, 0) || arr_take(oy, &a[1], "y", 'd', 1, 0, 0)
        || arr_take(olab, &a[2], "label", 'q', 1, 0, 0) || arr_take(opts, &a[3], "pts", 'd', 2, 1, 0)
        || arr_take(opid, &a[4], "pid", 'q', 1, 1, 0) || arr_take(obox, &a[5], "box", 'd', 2, 1, 0)
        || arr_take(onode, &a[6], "node", 'q', 2, 1, 0) || arr_take(oroot, &a[7], "root", 'q', 1, 1, 0)) {
        arr_release(a, 8);
        return NULL;
    }
    Py_ssize_t n = arr_dim(&a[0], 0), m = arr_dim(&a[5], 0), n_labels = arr_dim(&a[7], 0);
    if (!arr_check_shape(&a[1], "y", n, 0) && !arr_check_shape(&a[2], "label", n, 0)
        && !arr_check_shape(&a[3], "pts", n, 2) && !arr_check_shape(&a[4], "pid", n, 0)
        && !arr_check_shape(&a[5], "box", m, 4)) {
        arr_check_shape(&a[6], "node", m, 3);
    }
    for (Py_ssize_t j = 0; j < n && !PyErr_Occurred(); j++) {
        if (Q(a[2])[j] < 0 || Q(a[2])[j] >= n_labels) {
            PyErr_Format(PyExc_ValueError, "label must lie in 0..%zd", n_labels - 1);
        }
    }
    if (PyErr_Occurred()) {
        arr_release(a, 8);
        return NULL;
    }
    ObjectsBuild b = {NULL, D(a[5]), Q(a[6]), 0, m};
    b.rec = PyMem_Malloc(sizeof(ObjectsRec) * (size_t)(n + 1));
    Py_ssize_t *start = PyMem_Malloc(sizeof(Py_ssize_t) * (size_t)(n_labels + 1));
    if (b.rec == NULL || start == NULL) {
        PyMem_Free(b.rec);
        PyMem_Free(start);
        arr_release(a, 8);
        return PyErr_NoMemory();
    }
    int status;
    Py_BEGIN_ALLOW_THREADS
    status = objects_build_all(&b, D(a[0]), D(a[1]), Q(a[2]), n, n_labels, Q(a[7]), start);
    for (Py_ssize_t j = 0; status == 0 && j < n; j++) {
        D(a[3])[2 * j] = b.rec[j].c[0];
        D(a[3])[2 * j + 1] = b.rec[j].c[1];
        Q(a[4])[j] = b.rec[j].i;
    }
    Py_END_ALLOW_THREADS
    PyMem_Free(b.rec);
    PyMem_Free(start);
    arr_release(a, 8);
    if (status < 0) {
        PyErr_Format(PyExc_ValueError, "node arrays of %zd rows are too few", m);
        return NULL;
    }
    return PyLong_FromSsize_t(b.used);
}

/* ------------------------------------------------------------------ taking a tree and queries */

/* The tree's five arrays (a[0 .. 5)) checked against each other; 0, or -1 with an error set. */
int objects_take_tree(PyObject **o, Arr *a, ObjectsTree *t)
{
    if (arr_take(o[0], &a[0], "pts", 'd', 2, 0, 0) || arr_take(o[1], &a[1], "pid", 'q', 1, 0, 0)
        || arr_take(o[2], &a[2], "box", 'd', 2, 0, 0) || arr_take(o[3], &a[3], "node", 'q', 2, 0, 0)
        || arr_take(o[4], &a[4], "root", 'q', 1, 0, 0)) {
        return -1;
    }
    Py_ssize_t n = arr_dim(&a[0], 0), m = arr_dim(&a[2], 0), nl = arr_dim(&a[4], 0);
    if (arr_check_shape(&a[0], "pts", n, 2) || arr_check_shape(&a[1], "pid", n, 0)
        || arr_check_shape(&a[2], "box", m, 4) || arr_check_shape(&a[3], "node", m, 3)) {
        return -1;
    }
    t->pts = D(a[0]);
    t->pid = Q(a[1]);
    t->box = D(a[2]);
    t->node = Q(a[3]);
    t->root = Q(a[4]);
    t->n = n;
    t->m = m;
    t->n_labels = nl;
    t->bad = 0;
    return 0;
}

/* None, or NULL with ValueError when a walk met a node outside the arrays. */
PyObject *objects_checked(const ObjectsTree *t)
{
    if (t->bad) {
        PyErr_SetString(PyExc_ValueError, "node or root holds a position or child outside the tree");
        return NULL;
    }
    Py_RETURN_NONE;
}

/* ------------------------------------------------------------------ k nearest */

typedef struct {
    double *d2;   /* k best squared distances, ascending (ties: lower index first) */
    int64_t *idx;
    Py_ssize_t k, count;
    double bound2;
} ObjectsBest;

static inline void objects_offer(ObjectsBest *b, double d2, int64_t i)
{
    if (!(d2 < b->bound2)) {
        return;
    }
    Py_ssize_t at = b->count;
    if (at == b->k) {
        if (!(d2 < b->d2[at - 1] || (d2 == b->d2[at - 1] && i < b->idx[at - 1]))) {
            return;
        }
        at--;
    } else {
        b->count++;
    }
    while (at > 0 && (d2 < b->d2[at - 1] || (d2 == b->d2[at - 1] && i < b->idx[at - 1]))) {
        b->d2[at] = b->d2[at - 1];
        b->idx[at] = b->idx[at - 1];
        at--;
    }
    b->d2[at] = d2;
    b->idx[at] = i;
}

/* Whether a node whose box is ``near2`` away can hold a neighbour (a tie with the k-th can: its index may be lower). */
static inline int objects_may_hold(const ObjectsBest *b, double near2)
{
    return b->count == b->k ? near2 <= b->d2[b->k - 1] : near2 < b->bound2;
}

static void objects_knn_node(ObjectsTree *t, int64_t nd, double qx, double qy, ObjectsBest *b)
{
    const int64_t *nn = t->node + 3 * nd;
    if (nn[2] < 0) {
        for (int64_t j = nn[0]; j < nn[1]; j++) {
            objects_offer(b, objects_d2(t->pts + 2 * j, qx, qy), t->pid[j]);
        }
        return;
    }
    int64_t c[2] = {nd + 1, nn[2]};
    if (!objects_node_ok(t, c[0]) || !objects_node_ok(t, c[1])) {
        return;
    }
    double near2[2] = {objects_box_near2(t, c[0], qx, qy), objects_box_near2(t, c[1], qx, qy)};
    int first = near2[1] < near2[0];  /* the nearer child first: the bound shrinks sooner */
    for (int s = 0; s < 2; s++) {
        int which = s ? 1 - first : first;
        if (objects_may_hold(b, near2[which])) {
            objects_knn_node(t, c[which], qx, qy, b);
        }
    }
}

/* objects_knn_node's walk without recursion, the same nodes in the same order: a node's farther child waits on a
 * stack with its box's distance and is entered, when popped, only if it may still hold a neighbour (the test the
 * recursion made after the nearer child's subtree).  A tree deeper than the stack (a degenerate one) finishes
 * in the recursion from the node that overflowed it. */
#define OBJECTS_STACK 64
static void objects_knn_walk(ObjectsTree *t, int64_t root, double qx, double qy, ObjectsBest *b)
{
    int64_t wait[OBJECTS_STACK];
    double wait2[OBJECTS_STACK];
    int top = 0;
    int64_t nd = root;
    for (;;) {
        const int64_t *nn = t->node + 3 * nd;
        if (nn[2] < 0) {
            for (int64_t j = nn[0]; j < nn[1]; j++) {
                objects_offer(b, objects_d2(t->pts + 2 * j, qx, qy), t->pid[j]);
            }
        } else if (top == OBJECTS_STACK) {
            objects_knn_node(t, nd, qx, qy, b);
        } else if (objects_node_ok(t, nd + 1) && objects_node_ok(t, nn[2])) {
            int64_t c0 = nd + 1, c1 = nn[2];
            double n0 = objects_box_near2(t, c0, qx, qy), n1 = objects_box_near2(t, c1, qx, qy);
            int first = n1 < n0;
            wait[top] = first ? c0 : c1;
            wait2[top++] = first ? n0 : n1;
            if (objects_may_hold(b, first ? n1 : n0)) {
                nd = first ? c1 : c0;
                continue;
            }
        }
        do {  /* the next waiting node that may still hold a neighbour */
            if (top == 0) {
                return;
            }
            top--;
        } while (!objects_may_hold(b, wait2[top]));
        nd = wait[top];
    }
}

/* The nearest object of label ``l`` to (qx, qy) with a squared distance below ``bound2`` (ties: the lower index):
 * its index, its squared distance in ``*d2``; -1 when there is none.  A k = 1 query of objects_knn, for the fused
 * queries of other files (_kernel_verify.c: verify_screen). */
int64_t objects_nearest1(ObjectsTree *t, int64_t l, double qx, double qy, double bound2, double *d2)
{
    double bd = INFINITY;
    int64_t bi = -1;
    ObjectsBest b = {&bd, &bi, 1, 0, bound2};
    int64_t r = isfinite(qx) && isfinite(qy) ? objects_root(t, l) : -1;
    if (r >= 0 && objects_may_hold(&b, objects_box_near2(t, r, qx, qy))) {
        objects_knn_walk(t, r, qx, qy, &b);
    }
    *d2 = bd;
    return b.count ? bi : -1;
}

static PyObject *objects_knn(PyObject *self, PyObject *args)
{
    PyObject *o[5], *oq, *olab, *od, *oi;
    Py_ssize_t missing;
    double bound;
    Arr a[9] = {{{0}}};
    ObjectsTree t;
    if (!PyArg_ParseTuple(args, "OOOOOOOdnOO:objects_knn", &o[0], &o[1], &o[2], &o[3], &o[4], &oq, &olab, &bound,
                          &missing, &od, &oi)) {
        return NULL;
    }
    if (objects_take_tree(o, a, &t) || arr_take(oq, &a[5], "w", 'Z', 1, 0, 0)
        || arr_take(olab, &a[6], "labels", 'q', 1, 0, 0) || arr_take(od, &a[7], "out_d", 'd', 2, 1, 0)
        || arr_take(oi, &a[8], "out_i", 'q', 2, 1, 0)) {
        arr_release(a, 9);
        return NULL;
    }
    Py_ssize_t q = arr_dim(&a[5], 0), k = arr_dim(&a[7], 1);
    if (k < 1) {
        PyErr_SetString(PyExc_ValueError, "out_d must have at least one column");
    } else if (!arr_check_shape(&a[6], "labels", q, 0) && !arr_check_shape(&a[7], "out_d", q, k)) {
        arr_check_shape(&a[8], "out_i", q, k);
    }
    if (PyErr_Occurred()) {
        arr_release(a, 9);
        return NULL;
    }
    const double *w = D(a[5]);
    const int64_t *lab = Q(a[6]);
    double *out_d = D(a[7]);
    int64_t *out_i = Q(a[8]);
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t j = 0; j < q; j++) {
        ObjectsBest b = {out_d + j * k, out_i + j * k, k, 0, bound * bound};
        int64_t r = isfinite(w[2 * j]) && isfinite(w[2 * j + 1]) ? objects_root(&t, lab[j]) : -1;
        if (r >= 0 && objects_may_hold(&b, objects_box_near2(&t, r, w[2 * j], w[2 * j + 1]))) {
            objects_knn_walk(&t, r, w[2 * j], w[2 * j + 1], &b);
        }
        for (Py_ssize_t c = 0; c < k; c++) {
            out_d[j * k + c] = c < b.count ? sqrt(out_d[j * k + c]) : INFINITY;
            out_i[j * k + c] = c < b.count ? out_i[j * k + c] : (int64_t)missing;
        }
    }
    Py_END_ALLOW_THREADS
    arr_release(a, 9);
    return objects_checked(&t);
}

/* ------------------------------------------------------------------ method table */

PyMethodDef objects_methods[] = {
    {"objects_build", objects_build, METH_VARARGS,
     "objects_build(x, y, label, pts, pid, box, node, root): a KD-tree per label into the arrays given; returns "
     "the number of nodes used."},
    {"objects_knn", objects_knn, METH_VARARGS,
     "objects_knn(pts, pid, box, node, root, w, labels, bound, missing, out_d, out_i): the k nearest objects of "
     "each point's label within bound (k: out_d's columns), nearest first."},
    {NULL, NULL, 0, NULL},
};
