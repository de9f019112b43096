/* Quads in the kernel (issue 30): the map's quad lookups, and the image's quads and their keys.
 *
 * Lookups: a k-d tree over a quad index's tree points, looked up for image quads in one call.
 *
 * The points are what quads.QuadIndex made them: four invariants, the label key (LABEL_GAP apart) and, for an
 * index with positions, the weighted centroid.  A lookup answers what scipy's cKDTree.query(query, k,
 * distance_upper_bound=bound) followed by QuadIndex.lookup's filters answered: per query the k nearest points
 * with squared distance below bound^2, the squared distance summed dimension by dimension in order (as scipy's
 * sqeuclidean_distance_double does: its four partial sums start at zero, so they add to the same bits), the
 * distance its square root; then, without positions, the hits within the query's radius; with positions, the
 * distance split into the invariants' part (within the radius) and the position's (within the reach).  Hits come
 * query by query, nearest first; equal distances in point order, or, for an index without positions looked up near a
 * place, nearest that place first (scipy's order among ties depends on its tree: the one difference, see
 * tests/test_kernel_quads.py; on a perfect lattice, where thousands of quads tie, the k nearest taken in point order
 * all lay outside the prior's disc).  Several trees (a prior's tiles) are looked up in one call,
 * their hits tree by tree, as successive lookups gave them.
 *
 * The tree: the points of each label key first gathered under one subtree (three-way partitions around a key), then
 * sliding-midpoint splits of the widest side of the cell the parents' splits leave (scipy's cKDTree's default
 * rule, with no pass over the points to measure them), leaves of at most QUADS_LEAF points copied in tree order so
 * that a leaf is read in one stretch, each node's tight box made from its children's.  A subtree is skipped when its
 * lower bound (the squared gaps to its box, summed in dimension order like a distance, so never above the computed
 * distance of a point in it) is beyond the k-th distance so far or reaches the bound.
 *
 * The image side (hypotheses.anchor_batches, hypotheses._quad_keys): each anchor's nearest objects, its quads in
 * rounds, each quad once; the frames of each quad, their lookup radii and orderings; numpy's arithmetic (cabs_np,
 * cdiv) so that the same inputs give the same bits.  Equal lengths and equal distances are ranked in pair and
 * object order (numpy's default argsort and the KD-tree leave the order of ties to the machine and the tree).
 */
#include "_kernel.h"

#include <float.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

#define QUADS_LEAF 16
#define QUADS_MAX_DIM 16
#define QUADS_KEY 4  /* the label key's column */
#define QUADS_CAPSULE "mapdb.match._kernel.quads_tree"

typedef struct {
    Py_ssize_t lo, hi;   /* the node's points, tree order [lo, hi) */
    Py_ssize_t left;     /* children (left + 1 is not the right one); -1 for a leaf */
    Py_ssize_t right;
} QuadsNode;

typedef struct {
    Py_ssize_t n, d, n_nodes, cap;
    double *pts;         /* n * d, tree order */
    int64_t *idx;        /* tree order -> row of the points given */
    QuadsNode *nodes;
    const double *src;   /* the points given, during the build */
    double *box;         /* per node, the least then the greatest coordinate per dimension (2 d) */
} QuadsTree;

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

/* Partition [lo, hi) by ``split`` along ``dim``: returns the first point not below it. */
static Py_ssize_t quads_partition(QuadsTree *t, Py_ssize_t lo, Py_ssize_t hi, int dim, double split)
{
    const double *src = t->src + dim;  /* locals: the swaps cannot then be taken to change them */
    int64_t *idx = t->idx;
    Py_ssize_t d = t->d, i = lo, j = hi - 1;
    for (;;) {
        while (i <= j && src[idx[i] * d] < split) {
            i++;
        }
        while (i <= j && !(src[idx[j] * d] < split)) {
            j--;
        }
        if (i >= j) {
            return i;
        }
        int64_t k = idx[i];
        idx[i++] = idx[j];
        idx[j--] = k;
    }
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
    double *box = t->box + 2 * d * me;
    const double *bl = t->box + 2 * d * left, *br = t->box + 2 * d * right;
    for (Py_ssize_t j = 0; j < d; j++) {
        box[j] = bl[j] < br[j] ? bl[j] : br[j];
        box[d + j] = bl[d + j] > br[d + j] ? bl[d + j] : br[d + j];
    }
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
    Py_ssize_t d = t->d;
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
    double *box = t->box + 2 * d * me;
    const double *bl = t->box + 2 * d * left, *br = t->box + 2 * d * right;
    for (Py_ssize_t j = 0; j < d; j++) {
        box[j] = bl[j] < br[j] ? bl[j] : br[j];
        box[d + j] = bl[d + j] > br[d + j] ? bl[d + j] : br[d + j];
    }
    t->nodes[me] = (QuadsNode){lo, hi, left, right};
    return me;
}

static void quads_free(QuadsTree *t)
{
    if (t) {
        free(t->pts);
        free(t->idx);
        free(t->nodes);
        free(t->box);
        free(t);
    }
}

static void quads_capsule_free(PyObject *capsule)
{
    quads_free((QuadsTree *)PyCapsule_GetPointer(capsule, QUADS_CAPSULE));
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
    QuadsTree *t = calloc(1, sizeof(QuadsTree));
    if (t) {
        t->cap = 4 * (n / QUADS_LEAF) + 16;  /* grown when splits peel off small parts */
        t->n = n;
        t->d = d;
        t->pts = malloc(sizeof(double) * n * d);
        t->idx = malloc(sizeof(int64_t) * n);
        t->nodes = malloc(sizeof(QuadsNode) * t->cap);
        t->box = malloc(sizeof(double) * 2 * d * t->cap);
    }
    if (!t || !t->pts || !t->idx || !t->nodes || !t->box) {
        quads_free(t);
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

/* ------------------------------------------------------------------ lookup */

typedef struct {
    double d2;
    double tie;         /* among equal distances, the nearer to the prior's place first (0 without) */
    int64_t i;          /* the point's row */
    Py_ssize_t at;      /* its place in tree order */
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
} QuadsBest;

static void quads_offer(QuadsBest *b, double d2, int64_t i, Py_ssize_t at_tree)
{
    QuadsHit x = {d2, 0.0, i, at_tree};
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

/* One tree's hits for every query, filtered as QuadIndex.lookup did, appended to ``o``; -1 out of memory. */
static int quads_lookup_tree(const QuadsTree *t, const double *quad_z, const QuadsAsk *ask, QuadsHit *heap,
                             QuadsOut *o)
{
    double q[QUADS_MAX_DIM];
    int positions = t->d == 7;
    QuadsBest b = {heap, 0, ask->k < t->n ? ask->k : t->n, ask->bound * ask->bound, quad_z, ask->px, ask->py,
                   ask->by_place && !positions};
    for (Py_ssize_t r = 0; r < ask->m; r++) {
        memcpy(q, ask->inv + 4 * r, sizeof(double) * 4);
        q[4] = ask->key[r];
        q[5] = ask->px;
        q[6] = ask->py;
        b.n = 0;
        b.bound2 = quads_query_bound(ask, ask->radius[r], positions);
        if (quads_within(&b, quads_low(t->box, q, t->d))) {
            quads_search(t, 0, q, &b);
        }
        qsort(heap, (size_t)b.n, sizeof(QuadsHit), qhit_cmp);
        double rad = ask->radius[r];
        for (Py_ssize_t c = 0; c < b.n; c++) {
            double dist = sqrt(heap[c].d2);
            int keep = dist <= (positions ? ask->bound : rad);
            if (keep && positions) {
                /* The tree's distance mixes the invariants' with the position's: split them (as lookup() did). */
                const double *p = t->pts + heap[c].at * t->d;
                double ex = p[5] - ask->px, ey = p[6] - ask->py;
                double off2 = ex * ex + ey * ey;
                keep = dist * dist - off2 <= rad * rad && off2 <= ask->reach * ask->reach;
            }
            if (keep && quads_push(o, r, quad_z + 8 * heap[c].i) < 0) {
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

static PyObject *quads_lookup(PyObject *self, PyObject *args)
{
    PyObject *trees, *zs, *oinv, *okey, *orad;
    QuadsAsk ask;
    Arr a[3] = {{{0}}};
    if (!PyArg_ParseTuple(args, "O!O!OOOnddddp:quads_lookup", &PyTuple_Type, &trees, &PyTuple_Type, &zs, &oinv,
                          &okey, &orad, &ask.k, &ask.px, &ask.py, &ask.reach, &ask.bound, &ask.by_place)) {
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
    QuadsOut o = {NULL, NULL, 0, 0};
    QuadsHit *heap = NULL;
    int failed = quads_take_trees(trees, zs, za, tt, nt);
    Py_ssize_t most = 1;
    for (Py_ssize_t i = 0; i < nt && !failed; i++) {
        most = tt[i]->n > most ? tt[i]->n : most;
    }
    most = ask.k < most ? ask.k : most;
    if (!failed) {
        heap = malloc(sizeof(QuadsHit) * (size_t)most);
        failed = heap ? 0 : (PyErr_NoMemory(), -1);
    }
    for (Py_ssize_t i = 0; i < nt && !failed; i++) {
        int bad;
        Py_BEGIN_ALLOW_THREADS
        bad = quads_lookup_tree(tt[i], D(za[i]), &ask, heap, &o);
        Py_END_ALLOW_THREADS
        failed = bad ? (PyErr_NoMemory(), -1) : 0;
    }
    PyObject *out = failed ? NULL : quads_result(&o);
    free(heap);
    free(o.rows);
    free(o.z);
    arr_release(za, (int)nt);
    arr_release(a, 3);
    return out;
}

/* ------------------------------------------------------------------ the image's quads and their keys */

/* The six point pairs of a quad and, for each, the two other points (quads.PAIRS, quads.OTHERS). */
static const int QUADS_PAIRS[6][4] = {{0, 1, 2, 3}, {0, 2, 1, 3}, {0, 3, 1, 2}, {1, 2, 0, 3}, {1, 3, 0, 2}, {2, 3, 0, 1}};

/* One frame of a quad looked up: vertex order, t_C and t_D (re, im), the radius. */
typedef struct {
    int64_t row;
    int order[4];
    double t[4];
    double radius;
} QuadsFrame;

/* The frame of quad ``z`` (4 complex) by pair ``pair``: its order and invariants (numpy's arithmetic). */
static void quads_frame(const double *z, int pair, QuadsFrame *f)
{
    memcpy(f->order, QUADS_PAIRS[pair], sizeof(f->order));
    const double *a = z + 2 * f->order[0], *b = z + 2 * f->order[1];
    double br = b[0] - a[0], bi = b[1] - a[1];
    for (int c = 0; c < 2; c++) {
        const double *p = z + 2 * f->order[2 + c];
        cdiv(p[0] - a[0], p[1] - a[1], br, bi, &f->t[2 * c], &f->t[2 * c + 1]);
    }
}

/* The lookup radius of a frame (hypotheses._quad_keys): per point P of C, D sigma_P^2 + sigma_A^2 |1 - t|^2 +
 * sigma_B^2 |t|^2, summed, its root times ``factor`` over |AB|. */
static double quads_radius(const QuadsFrame *f, const double *s, double factor, double length)
{
    double spread = 0.0;
    for (int c = 0; c < 2; c++) {
        double re = f->t[2 * c], im = f->t[2 * c + 1];
        double u = cabs_np(1.0 - re, 0.0 - im), v = cabs_np(re, im);
        double sp = s[f->order[2 + c]] * s[f->order[2 + c]], sa = s[f->order[0]] * s[f->order[0]];
        double sb = s[f->order[1]] * s[f->order[1]];
        double e = sp + sa * (u * u) + sb * (v * v);
        spread = c ? spread + e : e;
    }
    return factor * sqrt(spread) / length;
}

/* The frames of ``m`` quads (``zq`` m x 4 complex, ``sigma`` m x 4 or NULL for ``one``): every quad's longest pair's,
 * then, where the second longest is within ``tie_factor`` sigma of it, the second's (the lengths' order a stable
 * one).  Returns how many, written to ``frames`` (room for 2 m); ``*block``, how many are first frames. */
static Py_ssize_t quads_frames(const double *zq, const double *sigma, Py_ssize_t m, double one, double tie_factor,
                               double factor, QuadsFrame *frames, Py_ssize_t *block)
{
    Py_ssize_t h = 0;
    for (int rank = 0; rank < 2; rank++) {
        if (rank == 1) {
            *block = h;
        }
        for (Py_ssize_t i = 0; i < m; i++) {
            const double *z = zq + 8 * i;
            double d[6];
            int by[6];
            for (int j = 0; j < 6; j++) {
                const double *p = z + 2 * QUADS_PAIRS[j][0], *q = z + 2 * QUADS_PAIRS[j][1];
                d[j] = cabs_np(p[0] - q[0], p[1] - q[1]);
                int at = j;  /* insertion by -d, ties in pair order */
                while (at > 0 && np_less(-d[j], -d[by[at - 1]])) {
                    by[at] = by[at - 1];
                    at--;
                }
                by[at] = j;
            }
            double s[4] = {one, one, one, one};
            if (sigma) {
                memcpy(s, sigma + 4 * i, sizeof(s));
            }
            double smax = s[0];
            for (int j = 1; j < 4; j++) {
                smax = (s[j] > smax || isnan(s[j])) && !isnan(smax) ? s[j] : smax;
            }
            double len = d[by[rank]];
            int use = rank == 0 ? len > 0.0 : (d[by[0]] - d[by[1]] < tie_factor * smax) && len > 0.0;
            if (use) {
                frames[h].row = i;
                quads_frame(z, by[rank], &frames[h]);
                frames[h].radius = quads_radius(&frames[h], s, factor, len);
                h++;
            }
        }
    }
    return h;
}

/* Ordering ``w`` (A, B swapped or not, C, D swapped or not) of a frame. */
static void quads_ordering(const QuadsFrame *f, int w, int *order, double *t)
{
    int c = (w & 1) ? 1 : 0, ab = w >= 2;
    order[0] = f->order[ab ? 1 : 0];
    order[1] = f->order[ab ? 0 : 1];
    order[2] = f->order[2 + c];
    order[3] = f->order[3 - c];
    for (int k = 0; k < 2; k++) {
        const double *src = f->t + 2 * (k ^ c);
        t[2 * k] = ab ? 1.0 - src[0] : src[0];
        t[2 * k + 1] = ab ? 0.0 - src[1] : src[1];
    }
}

static PyObject *quads_keys(PyObject *self, PyObject *args)
{
    PyObject *ozq, *osigma;
    double one, tie_factor, factor, max_radius;
    Arr a[2] = {{{0}}};
    if (!PyArg_ParseTuple(args, "OOdddd:quads_keys", &ozq, &osigma, &one, &tie_factor, &factor, &max_radius)) {
        return NULL;
    }
    if (arr_take(ozq, &a[0], "zq", 'Z', 2, 0, 0) || arr_take(osigma, &a[1], "sigma", 'd', 2, 0, 1)
        || arr_check_shape(&a[0], "zq", arr_dim(&a[0], 0), 4) || arr_check_shape(&a[1], "sigma", arr_dim(&a[0], 0), 4)) {
        arr_release(a, 2);
        return NULL;
    }
    Py_ssize_t m = arr_dim(&a[0], 0);
    QuadsFrame *frames = malloc(sizeof(QuadsFrame) * (size_t)(2 * m + 1));
    PyObject *rows = NULL, *orders = NULL, *inv = NULL, *radius = NULL, *out = NULL;
    if (!frames) {
        arr_release(a, 2);
        return PyErr_NoMemory();
    }
    Py_ssize_t block = 0;
    Py_ssize_t h = quads_frames(D(a[0]), a[1].held ? D(a[1]) : NULL, m, one, tie_factor, factor, frames, &block);
    rows = PyByteArray_FromStringAndSize(NULL, (Py_ssize_t)sizeof(int64_t) * 4 * h);
    orders = PyByteArray_FromStringAndSize(NULL, (Py_ssize_t)sizeof(int64_t) * 16 * h);
    inv = PyByteArray_FromStringAndSize(NULL, (Py_ssize_t)sizeof(double) * 16 * h);
    radius = PyByteArray_FromStringAndSize(NULL, (Py_ssize_t)sizeof(double) * 4 * h);
    if (rows && orders && inv && radius) {
        int64_t *r = (int64_t *)PyByteArray_AS_STRING(rows), *o = (int64_t *)PyByteArray_AS_STRING(orders);
        double *t = (double *)PyByteArray_AS_STRING(inv), *rad = (double *)PyByteArray_AS_STRING(radius);
        Py_ssize_t n = 0;
        for (int part = 0; part < 2; part++) {  /* frame block, then ordering, then quad */
            Py_ssize_t lo = part ? block : 0, hi = part ? h : block;
            for (int w = 0; w < 4; w++) {
                for (Py_ssize_t i = lo; i < hi; i++) {
                    int order[4];
                    double tt[4], slack = frames[i].radius * 1.4142135623730951;
                    quads_ordering(&frames[i], w, order, tt);
                    if (!(tt[0] + tt[2] - 1.0 <= slack && tt[0] - tt[2] <= slack && frames[i].radius <= max_radius)) {
                        continue;
                    }
                    r[n] = frames[i].row;
                    for (int j = 0; j < 4; j++) {
                        o[4 * n + j] = order[j];
                        t[4 * n + j] = tt[j];
                    }
                    rad[n++] = frames[i].radius;
                }
            }
        }
        if (PyByteArray_Resize(rows, sizeof(int64_t) * n) == 0 && PyByteArray_Resize(orders, sizeof(int64_t) * 4 * n) == 0
            && PyByteArray_Resize(inv, sizeof(double) * 4 * n) == 0 && PyByteArray_Resize(radius, sizeof(double) * n) == 0) {
            out = PyTuple_Pack(4, rows, orders, inv, radius);
        }
    }
    Py_XDECREF(rows);
    Py_XDECREF(orders);
    Py_XDECREF(inv);
    Py_XDECREF(radius);
    free(frames);
    arr_release(a, 2);
    return out;
}

/* ------------------------------------------------------------------ the image's quads in rounds */

/* The ``k`` nearest other points of each of ``n`` points ``xy`` (n x 2) into ``nn`` (n x k): the k + 1 nearest
 * (squared distances as a KD-tree sums them, equal ones in point order), the point itself dropped (the last of them
 * when another point sits on it and it is not among them: quads.nearest_others); only for the points whose ``wanted`` is not negative. */
static inline int quads_less(double a, double b)  /* np_less, inlined: NaN last */
{
    return isnan(b) ? !isnan(a) : a < b;
}

static void quads_nearest(const double *xy, Py_ssize_t n, Py_ssize_t k, const int64_t *wanted, int64_t *nn)
{
    Keyed near[65];  /* the k + 1 nearest so far, in order (k <= 64) */
    for (Py_ssize_t i = 0; i < n; i++) {
        if (wanted[i] < 0) {
            continue;
        }
        Py_ssize_t have = 0;
        for (Py_ssize_t j = 0; j < n; j++) {
            double dx = xy[2 * j] - xy[2 * i], dy = xy[2 * j + 1] - xy[2 * i + 1];
            Keyed x = {dx * dx + dy * dy, j};
            if (have == k + 1 && !quads_less(x.v, near[k].v)) {
                continue;  /* not nearer than the (k+1)-th: equal ones come later in point order */
            }
            Py_ssize_t at = have < k + 1 ? have++ : k;
            while (at > 0 && quads_less(x.v, near[at - 1].v)) {
                near[at] = near[at - 1];
                at--;
            }
            near[at] = x;
        }
        Py_ssize_t out = 0, own = -1;
        for (Py_ssize_t c = 0; c <= k && own < 0; c++) {
            own = near[c].i == i ? c : -1;
        }
        for (Py_ssize_t c = 0; c <= k; c++) {
            if (c != (own < 0 ? k : own)) {
                nn[i * k + out++] = near[c].i;
            }
        }
    }
}

/* The sorted object ids of anchor ``i``'s quad of its neighbours ``a < b < c`` (positions in ``nn``'s row). */
static void quads_sorted(const int64_t *nn, const int64_t *members, Py_ssize_t k, Py_ssize_t i, Py_ssize_t a,
                         Py_ssize_t b, Py_ssize_t c, int64_t *id)
{
    int64_t v[4] = {i, nn[i * k + a], nn[i * k + b], nn[i * k + c]};
    for (int x = 1; x < 4; x++) {
        for (int y = x; y > 0 && v[y] < v[y - 1]; y--) {
            int64_t tmp = v[y];
            v[y] = v[y - 1];
            v[y - 1] = tmp;
        }
    }
    for (int x = 0; x < 4; x++) {
        id[x] = members[v[x]];  /* members ascend: the ids stay sorted */
    }
}

/* Whether quad ``id`` is new to the set ``seen`` (open addressing, ``mask + 1`` slots of 4 ids, -1 empty); adds it. */
static int quads_first(int64_t *seen, uint64_t mask, const int64_t *id)
{
    uint64_t h = 1469598103934665603ULL;
    for (int x = 0; x < 4; x++) {
        h = (h ^ (uint64_t)id[x]) * 1099511628211ULL;
    }
    for (uint64_t at = h & mask;; at = (at + 1) & mask) {
        int64_t *slot = seen + 4 * at;
        if (slot[0] < 0) {
            memcpy(slot, id, sizeof(int64_t) * 4);
            return 1;
        }
        if (memcmp(slot, id, sizeof(int64_t) * 4) == 0) {
            return 0;
        }
    }
}

/* The quads in rounds: anchors by round (``batch``, ascending; member order within), each anchor's quads in triple
 * order, each quad where it first comes, rounds below ``n_batches``: written to ``out`` (4 ids a quad) with each
 * round's count in ``counts``.  Returns how many, or -1 out of memory. */
static Py_ssize_t quads_rounds(const int64_t *nn, const int64_t *members, const int64_t *batch, Py_ssize_t p,
                               Py_ssize_t k, Py_ssize_t n_batches, int64_t *out, int64_t *counts)
{
    Py_ssize_t q = p * (k * (k - 1) * (k - 2) / 6), used = 0;
    uint64_t slots = 16;
    while (slots < 2 * (uint64_t)q) {
        slots *= 2;
    }
    int64_t *seen = malloc(sizeof(int64_t) * 4 * slots);
    if (!seen) {
        return -1;
    }
    memset(seen, 0xff, sizeof(int64_t) * 4 * slots);
    for (Py_ssize_t b = 0; b < n_batches; b++) {
        for (Py_ssize_t i = 0; i < p; i++) {
            for (Py_ssize_t x = 0; x < k && batch[i] == b; x++) {
                for (Py_ssize_t y = x + 1; y < k; y++) {
                    for (Py_ssize_t z = y + 1; z < k; z++) {
                        quads_sorted(nn, members, k, i, x, y, z, out + 4 * used);
                        if (quads_first(seen, slots - 1, out + 4 * used)) {
                            counts[b]++;
                            used++;
                        }
                    }
                }
            }
        }
    }
    free(seen);
    return used;
}

static PyObject *quads_batches(PyObject *self, PyObject *args)
{
    PyObject *oz, *omembers;
    Py_ssize_t neighbours, per_batch, max_batches;
    Arr a[2] = {{{0}}};
    if (!PyArg_ParseTuple(args, "OOnnn:quads_batches", &oz, &omembers, &neighbours, &per_batch, &max_batches)) {
        return NULL;
    }
    if (arr_take(oz, &a[0], "z", 'Z', 1, 0, 0) || arr_take(omembers, &a[1], "members", 'q', 1, 0, 0)) {
        arr_release(a, 2);
        return NULL;
    }
    Py_ssize_t n = arr_dim(&a[0], 0), p = arr_dim(&a[1], 0), k = neighbours < p - 1 ? neighbours : p - 1;
    const double *z = D(a[0]);
    const int64_t *members = Q(a[1]);
    int bad = per_batch < 1 || max_batches < 0 || neighbours > 64;
    for (Py_ssize_t i = 0; i < p && !bad; i++) {
        bad = members[i] < 0 || members[i] >= n || (i > 0 && members[i] <= members[i - 1]);
    }
    if (bad) {
        arr_release(a, 2);
        return PyErr_Format(PyExc_ValueError, "need ascending members in [0, len(z)), per_batch >= 1, max_batches >= 0 "
                            "and at most 64 neighbours");
    }
    Py_ssize_t triples = k < 3 ? 0 : k * (k - 1) * (k - 2) / 6, q = p * triples;
    double *xy = malloc(sizeof(double) * (size_t)(2 * p + 1));
    int64_t *nn = malloc(sizeof(int64_t) * (size_t)(p * (k > 0 ? k : 0) + 1));
    int64_t *rank = malloc(sizeof(int64_t) * (size_t)(n + 1));
    int64_t *batch = malloc(sizeof(int64_t) * (size_t)(p + 1));
    Keyed *by = malloc(sizeof(Keyed) * (size_t)(n + 1));
    int64_t *ids = malloc(sizeof(int64_t) * (size_t)(4 * q + 1));
    int64_t *counts = calloc((size_t)max_batches + 1, sizeof(int64_t));
    PyObject *out = NULL;
    Py_ssize_t used = 0, n_batches = 0;
    if (!xy || !nn || !rank || !batch || !by || !ids || !counts) {
        PyErr_NoMemory();
    } else if (q > 0) {
        for (Py_ssize_t i = 0; i < n; i++) {  /* anchors nearest the image centre first (a stable order) */
            by[i].v = cabs_np(z[2 * i], z[2 * i + 1]);
            by[i].i = i;
        }
        sort_keyed(by, n);
        for (Py_ssize_t i = 0; i < n; i++) {
            rank[by[i].i] = i;
        }
        int64_t last = 0;
        for (Py_ssize_t i = 0; i < p; i++) {
            xy[2 * i] = z[2 * members[i]];
            xy[2 * i + 1] = z[2 * members[i] + 1];
            batch[i] = rank[members[i]] / per_batch;
            last = batch[i] > last ? batch[i] : last;
        }
        n_batches = last + 1 < max_batches ? last + 1 : max_batches;
        for (Py_ssize_t i = 0; i < p; i++) {  /* later rounds' anchors are never read */
            batch[i] = batch[i] < n_batches ? batch[i] : -1;
        }
        quads_nearest(xy, p, k, batch, nn);
        used = quads_rounds(nn, members, batch, p, k, n_batches, ids, counts);
        if (used < 0) {
            PyErr_NoMemory();
        }
    }
    if (!PyErr_Occurred()) {
        PyObject *quads = PyByteArray_FromStringAndSize((const char *)ids, sizeof(int64_t) * 4 * used);
        PyObject *ends = quads ? PyByteArray_FromStringAndSize((const char *)counts, sizeof(int64_t) * n_batches)
                               : NULL;
        out = ends ? PyTuple_Pack(2, quads, ends) : NULL;
        Py_XDECREF(quads);
        Py_XDECREF(ends);
    }
    free(batch);
    free(ids);
    free(xy);
    free(nn);
    free(rank);
    free(by);
    free(counts);
    arr_release(a, 2);
    return out;
}

/* ------------------------------------------------------------------ the poses a search may answer */

/* hypotheses.allowed_poses: finite a != 0; with a prior, |b - centre| <= reach; with a scale range, lo <= |a| <= hi. */
static PyObject *quads_allowed(PyObject *self, PyObject *args)
{
    PyObject *oa, *ob, *oout;
    int with_prior, with_scale;
    double cx, cy, reach, lo, hi;
    Arr a[3] = {{{0}}};
    if (!PyArg_ParseTuple(args, "OOpdddpddO:quads_allowed", &oa, &ob, &with_prior, &cx, &cy, &reach, &with_scale, &lo,
                          &hi, &oout)) {
        return NULL;
    }
    if (arr_take(oa, &a[0], "a", 'Z', 1, 0, 0) || arr_take(ob, &a[1], "b", 'Z', 1, 0, 0)
        || arr_take(oout, &a[2], "out", '?', 1, 1, 0) || arr_check_shape(&a[1], "b", arr_dim(&a[0], 0), 0)
        || arr_check_shape(&a[2], "out", arr_dim(&a[0], 0), 0)) {
        arr_release(a, 3);
        return NULL;
    }
    const double *av = D(a[0]), *bv = D(a[1]);
    unsigned char *ok = B(a[2]);
    for (Py_ssize_t i = 0; i < arr_dim(&a[0], 0); i++) {
        double scale = cabs_np(av[2 * i], av[2 * i + 1]);
        int yes = isfinite(av[2 * i]) && isfinite(av[2 * i + 1]) && scale > 0.0;
        if (with_prior) {
            yes = yes && cabs_np(bv[2 * i] - cx, bv[2 * i + 1] - cy) <= reach;
        }
        if (with_scale) {
            yes = yes && scale >= lo && scale <= hi;
        }
        ok[i] = (unsigned char)yes;
    }
    arr_release(a, 3);
    Py_RETURN_NONE;
}

PyMethodDef quads_methods[] = {
    {"quads_build", quads_build, METH_VARARGS,
     "quads_build(points): a k-d tree over a quad index's tree points (n, 5 or 7), float64."},
    {"quads_lookup", quads_lookup, METH_VARARGS,
     "quads_lookup(trees, quad_zs, invariants, key, radius, k, px, py, reach, bound, by_place): the hits of image quads in "
     "each tree, tree by tree: (query rows, map points) as bytearrays of int64 and of complex128 (h, 4)."},
    {"quads_keys", quads_keys, METH_VARARGS,
     "quads_keys(zq, sigma, one, tie_factor, factor, max_radius): every frame and ordering of image quads worth "
     "looking up (hypotheses._quad_keys): quad rows, orders (h, 4), invariants (h, 4), radii, as bytearrays."},
    {"quads_batches", quads_batches, METH_VARARGS,
     "quads_batches(z, members, neighbours, per_batch, max_batches): the image's quads in rounds "
     "(hypotheses.anchor_batches): sorted object ids (q, 4) and each round's count, as bytearrays of int64."},
    {"quads_allowed", quads_allowed, METH_VARARGS,
     "quads_allowed(a, b, with_prior, cx, cy, reach, with_scale, lo, hi, out): hypotheses.allowed_poses into out."},
    {NULL, NULL, 0, NULL},
};
