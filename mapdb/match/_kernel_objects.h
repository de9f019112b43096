/* The map objects' KD-trees per label: what _kernel_objects.c (the build, k nearest) and _kernel_object_discs.c
 * (discs, densities) share: reading a node as it is walked. */
#ifndef MAPDB_KERNEL_OBJECTS_H
#define MAPDB_KERNEL_OBJECTS_H

#include "_kernel.h"

#include <math.h>

/* ------------------------------------------------------------------ the tree */

/* Whether node ``nd`` lies in the arrays with its positions, and its children after it (so a walk ends); checked
 * as each node is read, since the arrays come from Python at every call and a whole check costs a walk of all. */
static inline int objects_node_ok(ObjectsTree *t, int64_t nd)
{
    const int64_t *nn = t->node + 3 * nd;
    if (nd < 0 || nd >= t->m || nn[0] < 0 || nn[1] > t->n || nn[0] > nn[1]
        || (nn[2] != -1 && (nn[2] <= nd + 1 || nn[2] >= t->m))) {
        t->bad = 1;
        return 0;
    }
    return 1;
}

/* The squared distance from (qx, qy) to the nearest point of node ``nd``'s box (0 inside it). */
static inline double objects_box_near2(const ObjectsTree *t, int64_t nd, double qx, double qy)
{
    const double *b = t->box + 4 * nd;
    double dx = qx < b[0] ? b[0] - qx : (qx > b[2] ? qx - b[2] : 0.0);
    double dy = qy < b[1] ? b[1] - qy : (qy > b[3] ? qy - b[3] : 0.0);
    return dx * dx + dy * dy;
}

/* The squared distance from (qx, qy) to the farthest corner of node ``nd``'s box. */
static inline double objects_box_far2(const ObjectsTree *t, int64_t nd, double qx, double qy)
{
    const double *b = t->box + 4 * nd;
    double ax = fabs(qx - b[0]), bx = fabs(qx - b[2]), ay = fabs(qy - b[1]), by = fabs(qy - b[3]);
    double dx = ax > bx ? ax : bx, dy = ay > by ? ay : by;
    return dx * dx + dy * dy;
}

static inline double objects_d2(const double *p, double qx, double qy)
{
    double dx = p[0] - qx, dy = p[1] - qy;
    return dx * dx + dy * dy;
}


/* The root of label ``l``'s tree, -1 when it has none (or is not a label). */
static inline int64_t objects_root(ObjectsTree *t, int64_t l)
{
    if (l < 0 || l >= t->n_labels || t->root[l] == -1) {
        return -1;
    }
    return objects_node_ok(t, t->root[l]) ? t->root[l] : -1;
}

#endif
