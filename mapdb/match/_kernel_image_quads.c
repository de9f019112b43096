/* The image's quads in the kernel (hypotheses.anchor_batches, _quad_keys, allowed_poses): each anchor's nearest
 * objects, its quads in rounds, each quad once; the frames of each quad, their lookup radii and orderings; numpy's
 * arithmetic (cabs_np, cdiv) so that the same inputs give the same bits.  Equal lengths and equal distances are
 * ranked in pair and object order (numpy's default argsort and the KD-tree leave the order of ties to the machine
 * and the tree).
 */
#include "_kernel_quads.h"

#include <float.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

/* ------------------------------------------------------------------ the image's quads and their keys */

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
                const double *p = z + 2 * quads_pair(j)[0], *q = z + 2 * quads_pair(j)[1];
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

/* The keys worth looking up of the frames (rows, orders, invariants, radii written): frame block, then ordering,
 * then quad; their count. */
static Py_ssize_t quads_keys_fill(const QuadsFrame *frames, Py_ssize_t block, Py_ssize_t h, double max_radius,
                                  int64_t *r, int64_t *o, double *t, double *rad)
{
    Py_ssize_t n = 0;
    for (int part = 0; part < 2; part++) {
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
    return n;
}

/* With the quads' image ids and the image's labels (a[2], a[3]): each key's ids (its quad's in its order) and their
 * labels, 0; or -1 with ValueError set when a quad names an object the labels do not have. */
static int quads_key_ids(const Arr *a, const int64_t *r, const int64_t *o, Py_ssize_t n, int64_t *ids, int64_t *labs)
{
    const int64_t *quads = Q(a[2]), *label = Q(a[3]);
    Py_ssize_t n_labels = arr_dim(&a[3], 0);
    for (Py_ssize_t i = 0; i < 4 * n; i++) {
        int64_t id = quads[4 * r[i / 4] + o[i]];
        if (id < 0 || id >= n_labels) {
            PyErr_SetString(PyExc_ValueError, "a quad names an image object out of range");
            return -1;
        }
        ids[i] = id;
        labs[i] = label[id];
    }
    return 0;
}

/* quads_keys' answer with the keys' ids and labels (quads_key_ids) after its four. */
static PyObject *quads_keys_ids(const Arr *a, PyObject *rows, PyObject *orders, PyObject *inv, PyObject *radius,
                                Py_ssize_t n)
{
    PyObject *ids = PyByteArray_FromStringAndSize(NULL, (Py_ssize_t)sizeof(int64_t) * 4 * n);
    PyObject *labs = PyByteArray_FromStringAndSize(NULL, (Py_ssize_t)sizeof(int64_t) * 4 * n), *out = NULL;
    if (ids && labs
        && !quads_key_ids(a, (const int64_t *)PyByteArray_AS_STRING(rows), (const int64_t *)PyByteArray_AS_STRING(orders),
                          n, (int64_t *)PyByteArray_AS_STRING(ids), (int64_t *)PyByteArray_AS_STRING(labs))) {
        out = PyTuple_Pack(6, rows, orders, inv, radius, ids, labs);
    }
    Py_XDECREF(ids);
    Py_XDECREF(labs);
    return out;
}

static PyObject *quads_keys(PyObject *self, PyObject *args)
{
    PyObject *ozq, *osigma, *oquads = Py_None, *olabel = Py_None;
    double one, tie_factor, factor, max_radius;
    Arr a[4] = {{{0}}};
    if (!PyArg_ParseTuple(args, "OOdddd|OO:quads_keys", &ozq, &osigma, &one, &tie_factor, &factor, &max_radius, &oquads,
                          &olabel)) {
        return NULL;
    }
    if (arr_take(ozq, &a[0], "zq", 'Z', 2, 0, 0) || arr_take(osigma, &a[1], "sigma", 'd', 2, 0, 1)
        || arr_check_shape(&a[0], "zq", arr_dim(&a[0], 0), 4) || arr_check_shape(&a[1], "sigma", arr_dim(&a[0], 0), 4)
        || arr_take(oquads, &a[2], "quads", 'q', 2, 0, 1) || arr_take(olabel, &a[3], "labels", 'q', 1, 0, 1)
        || arr_check_shape(&a[2], "quads", arr_dim(&a[0], 0), 4)) {
        arr_release(a, 4);
        return NULL;
    }
    if (a[2].held != a[3].held) {
        PyErr_SetString(PyExc_ValueError, "quads and labels come together");
        arr_release(a, 4);
        return NULL;
    }
    Py_ssize_t m = arr_dim(&a[0], 0);
    QuadsFrame *frames = malloc(sizeof(QuadsFrame) * (size_t)(2 * m + 1));
    PyObject *rows = NULL, *orders = NULL, *inv = NULL, *radius = NULL, *out = NULL;
    if (!frames) {
        arr_release(a, 4);
        return PyErr_NoMemory();
    }
    Py_ssize_t block = 0;
    Py_ssize_t h = quads_frames(D(a[0]), a[1].held ? D(a[1]) : NULL, m, one, tie_factor, factor, frames, &block);
    rows = PyByteArray_FromStringAndSize(NULL, (Py_ssize_t)sizeof(int64_t) * 4 * h);
    orders = PyByteArray_FromStringAndSize(NULL, (Py_ssize_t)sizeof(int64_t) * 16 * h);
    inv = PyByteArray_FromStringAndSize(NULL, (Py_ssize_t)sizeof(double) * 16 * h);
    radius = PyByteArray_FromStringAndSize(NULL, (Py_ssize_t)sizeof(double) * 4 * h);
    if (rows && orders && inv && radius) {
        Py_ssize_t n = quads_keys_fill(frames, block, h, max_radius, (int64_t *)PyByteArray_AS_STRING(rows),
                                       (int64_t *)PyByteArray_AS_STRING(orders), (double *)PyByteArray_AS_STRING(inv),
                                       (double *)PyByteArray_AS_STRING(radius));
        if (PyByteArray_Resize(rows, sizeof(int64_t) * n) == 0 && PyByteArray_Resize(orders, sizeof(int64_t) * 4 * n) == 0
            && PyByteArray_Resize(inv, sizeof(double) * 4 * n) == 0 && PyByteArray_Resize(radius, sizeof(double) * n) == 0) {
            out = a[2].held ? quads_keys_ids(a, rows, orders, inv, radius, n) : PyTuple_Pack(4, rows, orders, inv, radius);
        }
    }
    Py_XDECREF(rows);
    Py_XDECREF(orders);
    Py_XDECREF(inv);
    Py_XDECREF(radius);
    free(frames);
    arr_release(a, 4);
    return out;
}

/* ------------------------------------------------------------------ the image's quads in rounds */

/* The ``k`` nearest other points of each of ``n`` points ``xy`` (n x 2) into ``nn`` (n x k): the k + 1 nearest
 * (squared distances as a KD-tree sums them, equal ones in point order), the point itself dropped (the last of them
 * when another point sits on it and it is not among them: nearest.nearest_others); only for the points whose ``wanted`` is not negative. */
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
            if (have == k + 1 && !np_less(x.v, near[k].v)) {
                continue;  /* not nearer than the (k+1)-th: equal ones come later in point order */
            }
            Py_ssize_t at = have < k + 1 ? have++ : k;
            while (at > 0 && np_less(x.v, near[at - 1].v)) {
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

/* quads_batches' work arrays (xy: 2 p, nn: p k, rank: n, batch: p, by: n, ids: 4 q, counts: max_batches). */
typedef struct {
    double *xy;
    int64_t *nn, *rank, *batch;
    Keyed *by;
    int64_t *ids, *counts;
} QuadsBatchesWork;

/* The image's quads in rounds into ``w->ids`` (rows a round in ``w->counts``): anchors ranked by their distance
 * from the image centre (a stable order), ``per_batch`` a round, at most ``max_batches`` rounds (``*n_batches``).
 * Returns the number of quads, or -1 out of memory. */
static Py_ssize_t quads_batches_fill(const double *z, Py_ssize_t n, const int64_t *members, Py_ssize_t p, Py_ssize_t k,
                                     Py_ssize_t per_batch, Py_ssize_t max_batches, QuadsBatchesWork *w,
                                     Py_ssize_t *n_batches)
{
    for (Py_ssize_t i = 0; i < n; i++) {  /* anchors nearest the image centre first (a stable order) */
        w->by[i].v = cabs_np(z[2 * i], z[2 * i + 1]);
        w->by[i].i = i;
    }
    sort_keyed(w->by, n);
    for (Py_ssize_t i = 0; i < n; i++) {
        w->rank[w->by[i].i] = i;
    }
    int64_t last = 0;
    for (Py_ssize_t i = 0; i < p; i++) {
        w->xy[2 * i] = z[2 * members[i]];
        w->xy[2 * i + 1] = z[2 * members[i] + 1];
        w->batch[i] = w->rank[members[i]] / per_batch;
        last = w->batch[i] > last ? w->batch[i] : last;
    }
    *n_batches = last + 1 < max_batches ? last + 1 : max_batches;
    for (Py_ssize_t i = 0; i < p; i++) {  /* later rounds' anchors are never read */
        w->batch[i] = w->batch[i] < *n_batches ? w->batch[i] : -1;
    }
    quads_nearest(w->xy, p, k, w->batch, w->nn);
    return quads_rounds(w->nn, members, w->batch, p, k, *n_batches, w->ids, w->counts);
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
        QuadsBatchesWork w = {xy, nn, rank, batch, by, ids, counts};
        used = quads_batches_fill(z, n, members, p, k, per_batch, max_batches, &w, &n_batches);
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

int quads_pose_allowed(const double *a, const double *b, int with_prior, double cx, double cy, double reach,
                       int with_scale, double lo, double hi)
{
    double scale = cabs_np(a[0], a[1]);
    int yes = isfinite(a[0]) && isfinite(a[1]) && scale > 0.0;
    if (with_prior) {
        yes = yes && cabs_np(b[0] - cx, b[1] - cy) <= reach;
    }
    if (with_scale) {
        yes = yes && scale >= lo && scale <= hi;
    }
    return yes;
}

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
        ok[i] = (unsigned char)quads_pose_allowed(av + 2 * i, bv + 2 * i, with_prior, cx, cy, reach, with_scale, lo, hi);
    }
    arr_release(a, 3);
    Py_RETURN_NONE;
}

PyMethodDef image_quads_methods[] = {
    {"quads_keys", quads_keys, METH_VARARGS,
     "quads_keys(zq, sigma, one, tie_factor, factor, max_radius[, quads, labels]): every frame and ordering of image "
     "quads worth looking up (hypotheses._quad_keys): quad rows, orders (h, 4), invariants (h, 4), radii, and with the "
     "quads' image ids and the image's labels each key's ids (h, 4) and labels (h, 4), as bytearrays."},
    {"quads_batches", quads_batches, METH_VARARGS,
     "quads_batches(z, members, neighbours, per_batch, max_batches): the image's quads in rounds "
     "(hypotheses.anchor_batches): sorted object ids (q, 4) and each round's count, as bytearrays of int64."},
    {"quads_allowed", quads_allowed, METH_VARARGS,
     "quads_allowed(a, b, with_prior, cx, cy, reach, with_scale, lo, hi, out): hypotheses.allowed_poses into out."},
    {NULL, NULL, 0, NULL},
};
