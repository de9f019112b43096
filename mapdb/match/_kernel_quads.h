/* The map's quad trees (_kernel_quad_tree.c builds them, _kernel_quads.c looks image quads up in them).
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
 * their hits tree by tree, as successive lookups gave them; or jointly (a block of tiles), as one tree over their
 * points concatenated would answer: per query the k nearest of all the trees, equal distances in the concatenated
 * point order (the search's answer does not depend on the tree's shape, only on the points and their rows).
 *
 * The tree: the points of each label key first gathered under one subtree (three-way partitions around a key), then
 * sliding-midpoint splits of the widest side of the cell the parents' splits leave (scipy's cKDTree's default
 * rule, with no pass over the points to measure them), leaves of at most QUADS_LEAF points copied in tree order so
 * that a leaf is read in one stretch, each node's tight box made from its children's.  A subtree is skipped when its
 * lower bound (the squared gaps to its box, summed in dimension order like a distance, so never above the computed
 * distance of a point in it) is beyond the k-th distance so far or reaches the bound.
 */
#ifndef MAPDB_KERNEL_QUADS_H
#define MAPDB_KERNEL_QUADS_H

#include "_kernel.h"

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
    int64_t *work;       /* n places of room, during the build (the partitions' swaps) */
} QuadsTree;

/* ------------------------------------------------------------------ a quad's frames, shared by the image's quads
 * (_kernel_image_quads.c) and the map's (_kernel_map_quads.c) so that both sides make the same bits. */

/* The six point pairs of a quad and, for each, the two other points (quads.PAIRS, quads.OTHERS). */
static inline const int *quads_pair(int pair)
{
    static const int pairs[6][4] = {{0, 1, 2, 3}, {0, 2, 1, 3}, {0, 3, 1, 2}, {1, 2, 0, 3}, {1, 3, 0, 2}, {2, 3, 0, 1}};
    return pairs[pair];
}

/* One frame of a quad: vertex order, t_C and t_D (re, im), the radius (an image quad's lookup). */
typedef struct {
    int64_t row;
    int order[4];
    double t[4];
    double radius;
} QuadsFrame;

/* The frame of quad ``z`` (4 complex) by pair ``pair``: its order and invariants (numpy's arithmetic). */
static inline void quads_frame(const double *z, int pair, QuadsFrame *f)
{
    memcpy(f->order, quads_pair(pair), sizeof(f->order));
    const double *a = z + 2 * f->order[0], *b = z + 2 * f->order[1];
    CDivisor by;  /* one denominator, B - A, for both points */
    cdiv_by(b[0] - a[0], b[1] - a[1], &by);
    for (int c = 0; c < 2; c++) {
        const double *p = z + 2 * f->order[2 + c];
        cdiv_apply(&by, p[0] - a[0], p[1] - a[1], &f->t[2 * c], &f->t[2 * c + 1]);
    }
}

/* ------------------------------------------------------------------ scratch kept between calls (a tile's build)
 *
 * A buffer of a file's own, grown as needed and never freed: a tile's scratch arrays are then memory already
 * faulted in, not fresh pages each call.  Claimed and given back with the GIL held; a call that finds it claimed
 * (another thread's build, which released the GIL) takes memory of its own. */
typedef struct {
    void *buf;
    size_t cap;
    int busy;
} QuadsScratch;

/* ``bytes`` of room (at least one): the scratch's when free, else malloc'd; NULL when out of memory. */
static inline void *quads_scratch_claim(QuadsScratch *s, size_t bytes)
{
    bytes = bytes ? bytes : 1;
    if (s->busy) {
        return malloc(bytes);
    }
    if (s->cap < bytes) {
        size_t cap = bytes > 2 * s->cap ? bytes : 2 * s->cap;
        void *buf = malloc(cap);  /* not realloc: the old contents are not wanted */
        if (!buf) {
            return NULL;
        }
        free(s->buf);
        s->buf = buf;
        s->cap = cap;
    }
    s->busy = 1;
    return s->buf;
}

/* Give back what quads_scratch_claim gave (NULL allowed). */
static inline void quads_scratch_release(QuadsScratch *s, void *p)
{
    if (p && p == s->buf) {
        s->busy = 0;
    } else {
        free(p);
    }
}

/* hypotheses.allowed_poses of one similarity a, b (re, im pairs): finite a != 0; with a prior, |b - (cx, cy)| <=
 * reach; with a scale range, lo <= |a| <= hi (_kernel_image_quads.c). */
int quads_pose_allowed(const double *a, const double *b, int with_prior, double cx, double cy, double reach,
                       int with_scale, double lo, double hi);

#endif
