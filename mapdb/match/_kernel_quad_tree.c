/* A quad index's k-d tree, built (see _kernel_quads.h). */
#include "_kernel_quads.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

/* ------------------------------------------------------------------ build */

/* During the build, points are reordered through ``idx`` alone (cheaper than moving rows); copied in tree order
 * after. */
#define QUADS_AT(t, r, j) ((t)->src[(t)->idx[r] * (t)->d + (j)])

static void quads_swap(QuadsTree *t, Py_ssize_t i, Py_ssize_t j)
{
    int64_t k = t->idx[i];
    t->idx[i] = t->idx[j];
    t->idx[j] = k;
}

/* Partition [lo, hi) by ``split`` along ``dim``: returns the first point not below it.  The swaps are a Hoare
 * partition's (the first point not below from the left with the first below from the right, and so on while they
 * cross), found without a branch on each point's side (a coin toss): the points below counted (s), then the places
 * of those not below in [lo, lo + s) and of those below in [lo + s, hi), from the right, listed in ``work`` and
 * swapped pairwise. */
static Py_ssize_t quads_partition(QuadsTree *t, Py_ssize_t lo, Py_ssize_t hi, int dim, double split)
{
    const double *src = t->src + dim;  /* locals: the stores cannot then be taken to change them */
    int64_t *idx = t->idx, *left = t->work, *right;
    Py_ssize_t d = t->d, s = lo, nl = 0, nr = 0;
    for (Py_ssize_t r = lo; r < hi; r++) {
        s += src[idx[r] * d] < split;
    }
    right = left + (s - lo);
    for (Py_ssize_t r = lo; r < s; r++) {
        left[nl] = r;
        nl += !(src[idx[r] * d] < split);
    }
    for (Py_ssize_t r = hi - 1; r >= s; r--) {
        right[nr] = r;
        nr += src[idx[r] * d] < split;
    }
    for (Py_ssize_t c = 0; c < nl; c++) {  /* nl == nr: as many above the cut as below it */
        int64_t k = idx[left[c]];
        idx[left[c]] = idx[right[c]];
        idx[right[c]] = k;
    }
    return s;
}

/* Split [lo, hi) at the middle of the widest dimension of its ``cell`` (the box its parents' splits leave it: no pass
 * over the points to find their box, as scipy's cKDTree builds by default).  When a side would be empty the cell is
 * narrowed to the points' range in that dimension and the split tried again (the extreme point alone on one side
 * when rounding leaves no middle).  Returns the first point of the right part, setting ``*dim`` and ``*split``;
 * -1 when every point is the same. */
static Py_ssize_t quads_split(QuadsTree *t, Py_ssize_t lo, Py_ssize_t hi, double *cell, int *dim, double *split)
{
    Py_ssize_t d = t->d;
    for (;;) {
        int best = -1;
        double widest = 0.0;
        for (int j = 0; j < d; j++) {
            if (cell[d + j] - cell[j] > widest) {
                widest = cell[d + j] - cell[j];
                best = j;
            }
        }
        if (best < 0) {
            return -1;
        }
        *dim = best;
        *split = cell[best] + 0.5 * widest;
        Py_ssize_t i = quads_partition(t, lo, hi, best, *split);
        if (i > lo && i < hi) {
            return i;
        }
        double mn = QUADS_AT(t, lo, best), mx = mn;
        Py_ssize_t at_mn = lo;
        for (Py_ssize_t r = lo + 1; r < hi; r++) {
            double v = QUADS_AT(t, r, best);
            at_mn = v < mn ? r : at_mn;
            mn = v < mn ? v : mn;
            mx = v > mx ? v : mx;
        }
        if (mn < cell[best] || mx > cell[d + best]) {
            return -1;  /* not the points' cell (cannot happen): one leaf rather than a wrong bound */
        }
        cell[best] = mn;
        cell[d + best] = mx;
        if (mx > mn && !(mn + 0.5 * (mx - mn) > mn)) {  /* adjacent values: the least alone on the left */
            quads_swap(t, at_mn, lo);
            *split = mx;
            return quads_partition(t, lo + 1, hi, best, mx);
        }
    }
}

/* A new node's number (its box not yet set), the arrays grown as needed; -1 when out of memory. */
static Py_ssize_t quads_new_node(QuadsTree *t)
{
    if (t->n_nodes == t->cap) {
        Py_ssize_t cap = 2 * t->cap;
        QuadsNode *nodes = realloc(t->nodes, sizeof(QuadsNode) * cap);
        if (nodes) {
            t->nodes = nodes;
        }
        double *box = nodes ? realloc(t->box, sizeof(double) * 2 * t->d * cap) : NULL;
        if (!box) {
            return -1;
        }
        t->box = box;
        t->cap = cap;
    }
    return t->n_nodes++;
}

/* The tight box of [lo, hi) into ``box`` (each row's coordinates share a cache line: one pass). */
static void quads_points_box(const QuadsTree *t, Py_ssize_t lo, Py_ssize_t hi, double *box)
{
    Py_ssize_t d = t->d;
    memcpy(box, t->src + t->idx[lo] * d, sizeof(double) * d);
    memcpy(box + d, t->src + t->idx[lo] * d, sizeof(double) * d);
    for (Py_ssize_t r = lo + 1; r < hi; r++) {
        const double *p = t->src + t->idx[r] * d;
        for (Py_ssize_t j = 0; j < d; j++) {
            box[j] = p[j] < box[j] ? p[j] : box[j];
            box[d + j] = p[j] > box[d + j] ? p[j] : box[d + j];
        }
    }
}

/* Node ``me``'s box: the union of its children's. */
static void quads_join_boxes(QuadsTree *t, Py_ssize_t me, Py_ssize_t left, Py_ssize_t right)
{
    Py_ssize_t d = t->d;
    double *box = t->box + 2 * d * me;
    const double *bl = t->box + 2 * d * left, *br = t->box + 2 * d * right;
    for (Py_ssize_t j = 0; j < d; j++) {
        box[j] = bl[j] < br[j] ? bl[j] : br[j];
        box[d + j] = bl[d + j] > br[d + j] ? bl[d + j] : br[d + j];
    }
}

/* The node over [lo, hi) in ``cell`` (its parents' splits): returns its number, or -1 when out of memory.  Its stored
 * box is tight: a leaf's from its points, a parent's the union of its children's. */
static Py_ssize_t quads_build_node(QuadsTree *t, Py_ssize_t lo, Py_ssize_t hi, const double *cell)
{
    Py_ssize_t me = quads_new_node(t), d = t->d;
    if (me < 0) {
        return -1;
    }
    t->nodes[me] = (QuadsNode){lo, hi, -1, -1};
    double sub[2 * QUADS_MAX_DIM];
    memcpy(sub, cell, sizeof(double) * 2 * d);
    int dim = 0;
    double split = 0.0;
    Py_ssize_t mid = hi - lo <= QUADS_LEAF ? -1 : quads_split(t, lo, hi, sub, &dim, &split);
    if (mid < 0) {  /* a leaf: its points are where they stay, copied in tree order and boxed in one pass */
        double *box = t->box + 2 * d * me;
        for (Py_ssize_t r = lo; r < hi; r++) {
            memcpy(t->pts + r * d, t->src + t->idx[r] * d, sizeof(double) * d);
        }
        memcpy(box, t->pts + lo * d, sizeof(double) * d);
        memcpy(box + d, t->pts + lo * d, sizeof(double) * d);
        for (Py_ssize_t r = lo + 1; r < hi; r++) {
            const double *p = t->pts + r * d;
            for (Py_ssize_t j = 0; j < d; j++) {
                box[j] = p[j] < box[j] ? p[j] : box[j];
                box[d + j] = p[j] > box[d + j] ? p[j] : box[d + j];
            }
        }
        return me;
    }
    double keep = sub[d + dim];
    sub[d + dim] = split;
    Py_ssize_t left = quads_build_node(t, lo, mid, sub);
    sub[d + dim] = keep;
    sub[dim] = split;
    Py_ssize_t right = left < 0 ? -1 : quads_build_node(t, mid, hi, sub);
    if (right < 0) {
        return -1;
    }
    quads_join_boxes(t, me, left, right);
    t->nodes[me].left = left;
    t->nodes[me].right = right;
    return me;
}

/* A node over [lo, hi) whose label keys (column QUADS_KEY) differ: split three ways around the key of its middle point
 * (less, equal, greater; a quicksort's partition), so that each key's quads form one subtree of their own before
 * any other split, in a pass over the points a level (a key's quads leave the partitions once their key is the
 * pivot).  Boxes are the union of the children's.  Returns the node's number, or -1 out of memory. */
static Py_ssize_t quads_build_keys(QuadsTree *t, Py_ssize_t lo, Py_ssize_t hi)
{
    double pivot = QUADS_AT(t, lo + (hi - lo) / 2, QUADS_KEY);
    int mixed = 0;
    for (Py_ssize_t r = lo; r < hi && !mixed; r++) {
        mixed = QUADS_AT(t, r, QUADS_KEY) != pivot;
    }
    if (!mixed) {
        double box[2 * QUADS_MAX_DIM];
        quads_points_box(t, lo, hi, box);
        return quads_build_node(t, lo, hi, box);
    }
    Py_ssize_t a = lo, i = lo, b = hi;  /* [lo, a) less, [a, i) equal, [b, hi) greater */
    while (i < b) {
        double v = QUADS_AT(t, i, QUADS_KEY);
        if (v < pivot) {
            quads_swap(t, a++, i++);
        } else if (v > pivot) {
            quads_swap(t, i, --b);
        } else {
            i++;
        }
    }
    Py_ssize_t me = quads_new_node(t);
    if (me < 0) {
        return -1;
    }
    /* less | (equal | greater), or equal | greater when nothing is less */
    Py_ssize_t cut = a > lo ? a : b;
    Py_ssize_t left = a > lo ? quads_build_keys(t, lo, a) : quads_build_keys(t, a, b);
    Py_ssize_t right = left < 0 ? -1 : quads_build_keys(t, cut, hi);
    if (right < 0) {
        return -1;
    }
    quads_join_boxes(t, me, left, right);
    t->nodes[me] = (QuadsNode){lo, hi, left, right};
    return me;
}

/* Room kept between calls for the partitions' lists of places (n int64): memory already faulted in. */
static QuadsScratch quads_tree_scratch;

static void quads_free(QuadsTree *t)
{
    if (t) {
        free(t->pts);
        free(t->idx);
        free(t->nodes);
        free(t->box);
        quads_scratch_release(&quads_tree_scratch, t->work);
        free(t);
    }
}

static void quads_capsule_free(PyObject *capsule)
{
    quads_free((QuadsTree *)PyCapsule_GetPointer(capsule, QUADS_CAPSULE));
}

/* A tree's arrays for ``n`` points of ``d`` columns, its partitions' room claimed (the GIL held); NULL when out of
 * memory. */
static QuadsTree *quads_alloc(Py_ssize_t n, Py_ssize_t d)
{
    QuadsTree *t = calloc(1, sizeof(QuadsTree));
    if (t) {
        t->cap = 4 * (n / QUADS_LEAF) + 16;  /* grown when splits peel off small parts */
        t->n = n;
        t->d = d;
        t->pts = malloc(sizeof(double) * n * d);
        t->idx = malloc(sizeof(int64_t) * n);
        t->work = quads_scratch_claim(&quads_tree_scratch, sizeof(int64_t) * (size_t)n);
        t->nodes = malloc(sizeof(QuadsNode) * t->cap);
        t->box = malloc(sizeof(double) * 2 * d * t->cap);
    }
    if (t && (!t->pts || !t->idx || !t->nodes || !t->box || !t->work)) {
        quads_free(t);
        return NULL;
    }
    return t;
}

static PyObject *quads_build(PyObject *self, PyObject *args)
{
    PyObject *opts;
    Arr a[1] = {{{0}}};
    if (!PyArg_ParseTuple(args, "O:quads_build", &opts) || arr_take(opts, &a[0], "points", 'd', 2, 0, 0)) {
        return NULL;
    }
    Py_ssize_t n = arr_dim(&a[0], 0), d = arr_dim(&a[0], 1);
    const double *pts = D(a[0]);
    if (n < 1 || (d != 5 && d != 7)) {
        arr_release(a, 1);
        return PyErr_Format(PyExc_ValueError, "points must have at least one row and 5 or 7 columns");
    }
    for (Py_ssize_t i = 0; i < n * d; i++) {
        if (!isfinite(pts[i])) {
            arr_release(a, 1);
            return PyErr_Format(PyExc_ValueError, "points must be finite");
        }
    }
    QuadsTree *t = quads_alloc(n, d);
    if (!t) {
        arr_release(a, 1);
        return PyErr_NoMemory();
    }
    t->src = pts;
    for (Py_ssize_t i = 0; i < n; i++) {
        t->idx[i] = i;
    }
    Py_ssize_t root;
    Py_BEGIN_ALLOW_THREADS
    root = quads_build_keys(t, 0, n);
    if (root >= 0 && t->n_nodes < t->cap) {  /* give back what the nodes did not use */
        QuadsNode *nodes = realloc(t->nodes, sizeof(QuadsNode) * t->n_nodes);
        double *box = realloc(t->box, sizeof(double) * 2 * d * t->n_nodes);
        t->nodes = nodes ? nodes : t->nodes;
        t->box = box ? box : t->box;
    }
    Py_END_ALLOW_THREADS
    t->src = NULL;
    quads_scratch_release(&quads_tree_scratch, t->work);
    t->work = NULL;
    arr_release(a, 1);
    if (root < 0) {
        quads_free(t);
        return PyErr_NoMemory();
    }
    PyObject *capsule = PyCapsule_New(t, QUADS_CAPSULE, quads_capsule_free);
    if (!capsule) {
        quads_free(t);
    }
    return capsule;
}

PyMethodDef quad_tree_methods[] = {
    {"quads_build", quads_build, METH_VARARGS,
     "quads_build(points): a k-d tree over a quad index's tree points (n, 5 or 7), float64."},
    {NULL, NULL, 0, NULL},
};
