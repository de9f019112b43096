/* The map's quads in the kernel (quads.neighbour_quads, canonical_quads and QuadIndex's points): a map tile's quad
 * index in one call after its anchors' nearest neighbours are found (by cKDTree, whose order among equal distances
 * decides which quads exist).
 *
 * Each anchor's quads come in triple order (itertools.combinations), each row's ids sorted, each quad kept where it
 * first comes (a quad is new unless an earlier anchor among its points reached the other three): the rows and order
 * the numpy code's first occurrences gave (tests/quadrefs.py's first_rows), or, from _PACKABLE points on,
 * np.unique's (the kept rows sorted).  Then, as QuadIndex did with numpy: the quads whose
 * four points lie on one spot dropped (no frame); each quad's frame by its most distant pair (numpy's abs of the
 * complex difference, the first maximum on ties or the first NaN), ordered so that Re t_C + Re t_D <= 1 and
 * Re t_C <= Re t_D (numpy's complex division, quads_frame shared with the image's quads); the tree points: the
 * invariants, the label key (label_keys' float arithmetic) times the gap and, with positions, the centroid (numpy's
 * mean of four complex numbers: (a + b) + (c + d), over 4) times the weight.
 */
#include "_kernel_quads.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

/* The most distant pair of quad ``z`` (4 complex) as numpy's argmax of np.abs of the six differences finds it: the
 * first maximum, a NaN the greatest (its first).  Squared lengths decide when the longest is longer than the second
 * by far more than their rounding (relative 1e-9, against a few 1e-16, in a range with no underflow or overflow):
 * np.abs' values, within a few units in the last place of the true lengths, rank the same; otherwise (ties, near
 * ties, extreme or non-finite values) np.abs' values themselves (cabs_np), which cost five times more.  With ``ab``,
 * that pair's np.abs. */
static int map_longest_pair(const double *z, double *ab)
{
    double s[6];
    int pair = 0, ok = 1;
    #pragma GCC unroll 6
    for (int j = 0; j < 6; j++) {
        const double *p = z + 2 * quads_pair(j)[0], *q = z + 2 * quads_pair(j)[1];
        double dx = p[0] - q[0], dy = p[1] - q[1];
        s[j] = dx * dx + dy * dy;
        ok = ok && s[j] >= 1e-250 && s[j] <= 1e250;
        pair = s[j] > s[pair] ? j : pair;
    }
    #pragma GCC unroll 6
    for (int j = 0; j < 6 && ok; j++) {
        ok = j == pair || s[pair] > s[j] * (1.0 + 1e-9);
    }
    if (!ok) {
        double d[6];
        pair = 0;
        for (int j = 0; j < 6; j++) {
            const double *p = z + 2 * quads_pair(j)[0], *q = z + 2 * quads_pair(j)[1];
            d[j] = cabs_np(p[0] - q[0], p[1] - q[1]);
            if (!isnan(d[pair]) && (isnan(d[j]) || d[j] > d[pair])) {
                pair = j;
            }
        }
    }
    if (ab) {
        const double *p = z + 2 * quads_pair(pair)[0], *q = z + 2 * quads_pair(pair)[1];
        *ab = cabs_np(p[0] - q[0], p[1] - q[1]);
    }
    return pair;
}

/* Canonical order (positions 0..3), invariants and, with ``ab``, |AB| of quad ``z`` (4 complex): canonical_quads'
 * row.  Inline: a tile's quads (map_points) make it in their loop. */
static inline void map_canonical_at(const double *z, int *order, double *t, double *ab)
{
    int pair = map_longest_pair(z, ab);
    QuadsFrame f;
    quads_frame(z, pair, &f);
    memcpy(order, f.order, sizeof(f.order));
    memcpy(t, f.t, sizeof(f.t));
    /* the swaps by selection, not branches: each is a coin toss */
    int swap_ab = t[0] + t[2] > 1.0;  /* t.real.sum(axis=1) > 1.0 */
    int o0 = order[0], o1 = order[1];
    order[0] = swap_ab ? o1 : o0;
    order[1] = swap_ab ? o0 : o1;
    #pragma GCC unroll 6
    for (int c = 0; c < 2; c++) {
        t[2 * c] = select_d(swap_ab, 1.0 - t[2 * c], t[2 * c]);
        t[2 * c + 1] = select_d(swap_ab, 0.0 - t[2 * c + 1], t[2 * c + 1]);
    }
    int cd = t[0] > t[2];
    int o2 = order[2], o3 = order[3];
    order[2] = cd ? o3 : o2;
    order[3] = cd ? o2 : o3;
    double c_re = t[0], c_im = t[1], d_re = t[2], d_im = t[3];
    t[0] = select_d(cd, d_re, c_re);
    t[1] = select_d(cd, d_im, c_im);
    t[2] = select_d(cd, c_re, d_re);
    t[3] = select_d(cd, c_im, d_im);
}

/* map_canonical_at for the stored index (_kernel_stored_resolve.c) and map_canonical. */
void map_canonical_row(const double *z, int *order, double *t, double *ab)
{
    map_canonical_at(z, order, t, ab);
}

static int map_row_cmp(const void *pa, const void *pb)
{
    const int64_t *a = pa, *b = pb;
    for (int x = 0; x < 4; x++) {
        if (a[x] != b[x]) {
            return a[x] < b[x] ? -1 : 1;
        }
    }
    return 0;
}

/* Sort four ids by five compare-exchanges (a sorting network of four). */
static inline void map_sort4(int64_t *v)
{
    static const int net[5][2] = {{0, 1}, {2, 3}, {0, 2}, {1, 3}, {1, 2}};
    #pragma GCC unroll 6
    for (int c = 0; c < 5; c++) {
        int64_t a = v[net[c][0]], b = v[net[c][1]];
        v[net[c][0]] = a < b ? a : b;
        v[net[c][1]] = a < b ? b : a;
    }
}

/* Where an id stands in the anchor row at hand (map_earlier's table, -1 elsewhere): the anchor itself is MAP_ANCHOR. */
#define MAP_ANCHOR 64

/* For anchor row ``r`` (id ``i``) and each neighbour x that is an earlier anchor (a lower id: rows ascend), which of
 * the row's neighbours (bit y) that anchor's own neighbours hold, when they hold ``i`` (else 0): a quad of i's
 * neighbours x, y, z came first from x when x's mask holds the other two.  ``pos`` (n, all -1) says where each id
 * stands in row r, set here and reset before returning: one look-up per neighbour of x instead of a scan of the row
 * (the row's ids are distinct, so the same masks). */
static void map_earlier(const int64_t *nn, const int64_t *row_of, Py_ssize_t r, int64_t i, Py_ssize_t k,
                        signed char *pos, uint64_t *mask)
{
    const int64_t *row = nn + r * k;
    for (Py_ssize_t y = 0; y < k; y++) {
        pos[row[y]] = (signed char)y;
    }
    pos[i] = MAP_ANCHOR;
    for (Py_ssize_t x = 0; x < k; x++) {
        mask[x] = 0;
        int64_t j = row[x];
        if (j >= i || row_of[j] < 0) {
            continue;
        }
        const int64_t *other = nn + row_of[j] * k;
        uint64_t held = 0;
        int holds_i = 0;
        for (Py_ssize_t c = 0; c < k; c++) {
            int at = pos[other[c]];
            holds_i |= at == MAP_ANCHOR;
            held |= at >= 0 && at < MAP_ANCHOR ? (uint64_t)1 << at : 0;
        }
        mask[x] = holds_i ? held : 0;
    }
    for (Py_ssize_t y = 0; y < k; y++) {
        pos[row[y]] = -1;
    }
    pos[i] = -1;
}

/* The distinct quads of anchors ``anchor`` (p, ascending) with their ``k`` nearest ``nn`` (p x k, distinct, not the
 * anchor): rows of sorted ids into ``out`` (room for p C(k, 3) rows), where they first come (anchor by anchor, in
 * triple order: a quad is new unless an earlier anchor among its points reached the other three), or sorted when
 * ``sorted``.  ``row_of`` (n): each id's anchor row, -1 for none; ``pos``: n bytes of room.  Returns how many. */
static Py_ssize_t map_combine(const int64_t *nn, const int64_t *anchor, const int64_t *row_of, Py_ssize_t p,
                              Py_ssize_t k, int sorted, signed char *pos, Py_ssize_t n, int64_t *out)
{
    Py_ssize_t used = 0;
    uint64_t mask[64];
    memset(pos, -1, (size_t)n);
    for (Py_ssize_t r = 0; r < p; r++) {
        const int64_t *row = nn + r * k;
        map_earlier(nn, row_of, r, anchor[r], k, pos, mask);
        for (Py_ssize_t x = 0; x < k; x++) {
            for (Py_ssize_t y = x + 1; y < k; y++) {
                for (Py_ssize_t z = y + 1; z < k; z++) {
                    uint64_t bx = (uint64_t)1 << x, by = (uint64_t)1 << y, bz = (uint64_t)1 << z;
                    /* written always, kept (used advanced) unless an earlier anchor made it: no branch on a coin
                     * toss (out has room for every triple) */
                    int made = ((mask[x] & (by | bz)) == (by | bz)) | ((mask[y] & (bx | bz)) == (bx | bz))
                               | ((mask[z] & (bx | by)) == (bx | by));
                    int64_t *v = out + 4 * used;
                    v[0] = anchor[r];
                    v[1] = row[x];
                    v[2] = row[y];
                    v[3] = row[z];
                    map_sort4(v);
                    used += !made;
                }
            }
        }
    }
    if (sorted) {
        qsort(out, (size_t)used, sizeof(int64_t) * 4, map_row_cmp);
    }
    return used;
}

/* 0 when the anchors ascend in [0, n) and each row of neighbours holds distinct ids in [0, n) other than its anchor;
 * ``row_of`` (n) made.  Else -1 with ValueError set. */
static int map_check(const int64_t *nn, const int64_t *anchor, const int64_t *label, Py_ssize_t p, Py_ssize_t k,
                     Py_ssize_t n, int64_t *row_of)
{
    int bad = k > 64 || n < 0;
    for (Py_ssize_t i = 0; i < n; i++) {
        row_of[i] = -1;
        bad = bad || (label && label[i] < 0);
    }
    for (Py_ssize_t r = 0; r < p && !bad; r++) {
        bad = anchor[r] < 0 || anchor[r] >= n || (r > 0 && anchor[r] <= anchor[r - 1]);
        for (Py_ssize_t x = 0; x < k && !bad; x++) {
            int64_t j = nn[r * k + x];
            bad = j < 0 || j >= n || j == anchor[r];
            for (Py_ssize_t y = 0; y < x && !bad; y++) {
                bad = nn[r * k + y] == j;
            }
        }
        if (!bad) {
            row_of[anchor[r]] = r;
        }
    }
    if (bad) {
        PyErr_SetString(PyExc_ValueError, "need ascending anchors and distinct neighbours in [0, n) other than their "
                        "anchor, at most 64 neighbours, labels >= 0, and z with label");
        return -1;
    }
    return 0;
}

/* QuadIndex's quads and tree points from the distinct quads ``ids`` (q x 4, overwritten with the kept ones in
 * canonical order): returns how many kept, their points in ``pts`` (q x dim) and complex points in ``zq``. */
static Py_ssize_t map_points(int64_t *ids, Py_ssize_t q, const double *z, const int64_t *label, Py_ssize_t n_labels,
                             double gap, double weight, int dim, double *pts, double *zq)
{
    Py_ssize_t m = 0;
    double base = (double)(n_labels > 1 ? n_labels : 1);
    CDivisor four;  /* the centroid's division by 4, its ratio and scale made once */
    cdiv_by(4.0, 0.0, &four);
    for (Py_ssize_t i = 0; i < q; i++) {
        const int64_t *id = ids + 4 * i;
        double w[8], inv[4];
        int frame = 0, order[4];
        #pragma GCC unroll 6
        for (int x = 0; x < 4; x++) {
            w[2 * x] = z[2 * id[x]];
            w[2 * x + 1] = z[2 * id[x] + 1];
            frame = frame || (x > 0 && (w[2 * x] != w[0] || w[2 * x + 1] != w[1]));
        }
        if (!frame) {  /* four objects on one spot (duplicates in the sources) */
            continue;
        }
        map_canonical_at(w, order, inv, NULL);
        int64_t kept[4];
        double key = 0.0, *out = zq + 8 * m, *pt = pts + (Py_ssize_t)dim * m;
        #pragma GCC unroll 6
        for (int x = 0; x < 4; x++) {
            kept[x] = id[order[x]];
            out[2 * x] = w[2 * order[x]];
            out[2 * x + 1] = w[2 * order[x] + 1];
            key = key * base + (double)label[kept[x]];
            pt[x] = inv[x];
        }
        memcpy(ids + 4 * m, kept, sizeof(kept));
        pt[4] = key * gap;
        if (dim == 7) {
            double re = (out[0] + out[2]) + (out[4] + out[6]), im = (out[1] + out[3]) + (out[5] + out[7]);
            double cr, ci;
            cdiv_apply(&four, re, im, &cr, &ci);
            pt[5] = weight * cr;
            pt[6] = weight * ci;
        }
        m++;
    }
    return m;
}

/* Room kept between calls for a tile's anchor rows and id places, and, when its ids are not wanted (a tile's index
 * built), its distinct quads, most of them cut after: memory already faulted in, not fresh pages a call. */
static QuadsScratch map_scratch;

/* map_quads' answer from its checked arrays ``a`` (nn, anchors, z, label) and ``row_of``: the distinct quads (when
 * ``scratch`` is NULL, else an empty bytearray: they are made in it, room for every anchor's triples), and with z and
 * label those with a frame in canonical order, their tree points and complex points, as bytearrays.  Each is made in
 * its answer's bytearray (room for every anchor's triples, cut to those kept): no copy. */
static PyObject *map_build(Arr *a, const int64_t *row_of, signed char *pos, int64_t *scratch, Py_ssize_t n,
                           Py_ssize_t p, Py_ssize_t k, int sorted, Py_ssize_t n_labels, int positions, double gap,
                           double weight)
{
    Py_ssize_t q = k < 3 ? 0 : p * (k * (k - 1) * (k - 2) / 6), m = 0, dim = a[2].held ? (positions ? 7 : 5) : 0;
    PyObject *out = NULL, *o[3] = {NULL, NULL, NULL};
    o[0] = PyByteArray_FromStringAndSize(NULL, scratch ? 0 : (Py_ssize_t)sizeof(int64_t) * 4 * q);
    if (o[0]) {
        int64_t *ids = scratch ? scratch : (int64_t *)PyByteArray_AS_STRING(o[0]);
        m = q ? map_combine(Q(a[0]), Q(a[1]), row_of, p, k, sorted, pos, n, ids) : 0;
        /* written in place (the kept quads' ids, points and complex points), then cut to the quads with a frame:
         * no copy of megabytes a tile */
        o[1] = PyByteArray_FromStringAndSize(NULL, (Py_ssize_t)sizeof(double) * dim * m);
        o[2] = PyByteArray_FromStringAndSize(NULL, a[2].held ? (Py_ssize_t)sizeof(double) * 8 * m : 0);
        if (o[1] && o[2] && a[2].held) {
            m = map_points(ids, m, D(a[2]), Q(a[3]), n_labels, gap, weight, (int)dim,
                           (double *)PyByteArray_AS_STRING(o[1]), (double *)PyByteArray_AS_STRING(o[2]));
        }
    }
    if (o[0] && o[1] && o[2] && PyByteArray_Resize(o[0], scratch ? 0 : (Py_ssize_t)sizeof(int64_t) * 4 * m) == 0
        && PyByteArray_Resize(o[1], (Py_ssize_t)sizeof(double) * dim * m) == 0
        && PyByteArray_Resize(o[2], a[2].held ? (Py_ssize_t)sizeof(double) * 8 * m : 0) == 0) {
        out = PyTuple_Pack(3, o[0], o[1], o[2]);
    }
    for (int x = 0; x < 3; x++) {
        Py_XDECREF(o[x]);
    }
    return out;
}

static PyObject *map_quads(PyObject *self, PyObject *args)
{
    PyObject *onn, *oanchor, *oz, *olabel;
    Py_ssize_t n, n_labels;
    int sorted, positions, want_ids = 1;
    double gap, weight;
    Arr a[4] = {{{0}}};
    if (!PyArg_ParseTuple(args, "OOnpOOnpdd|p:map_quads", &onn, &oanchor, &n, &sorted, &oz, &olabel, &n_labels,
                          &positions, &gap, &weight, &want_ids)) {
        return NULL;
    }
    if (arr_take(onn, &a[0], "nn", 'q', 2, 0, 0) || arr_take(oanchor, &a[1], "anchors", 'q', 1, 0, 0)
        || arr_take(oz, &a[2], "z", 'Z', 1, 0, 1) || arr_take(olabel, &a[3], "label", 'q', 1, 0, 1)
        || arr_check_shape(&a[1], "anchors", arr_dim(&a[0], 0), 0) || arr_check_shape(&a[2], "z", n, 0)
        || arr_check_shape(&a[3], "label", n, 0)) {
        arr_release(a, 4);
        return NULL;
    }
    Py_ssize_t p = arr_dim(&a[0], 0), k = arr_dim(&a[0], 1), nn = n > 0 ? n : 0;
    Py_ssize_t q = want_ids || k < 3 || k > 64 ? 0 : p * (k * (k - 1) * (k - 2) / 6);
    /* one block: each id's anchor row (n int64), the quads when not wanted (q rows of 4 int64), each id's place in a
     * row (n bytes) */
    int64_t *row_of = quads_scratch_claim(&map_scratch, sizeof(int64_t) * (size_t)(nn + 4 * q) + (size_t)nn);
    if (!row_of) {
        arr_release(a, 4);
        return PyErr_NoMemory();
    }
    if (a[2].held != a[3].held) {
        PyErr_SetString(PyExc_ValueError, "need z with label");
    }
    PyObject *out = NULL;
    if (!PyErr_Occurred() && !map_check(Q(a[0]), Q(a[1]), a[3].held ? Q(a[3]) : NULL, p, k, n, row_of)) {
        out = map_build(a, row_of, (signed char *)(row_of + nn + 4 * q), want_ids ? NULL : row_of + nn, n, p, k,
                        sorted, n_labels, positions, gap, weight);
    }
    quads_scratch_release(&map_scratch, row_of);
    arr_release(a, 4);
    return out;
}

static PyObject *map_canonical(PyObject *self, PyObject *args)
{
    PyObject *ozq, *oorder, *oinv, *oab;
    Arr a[4] = {{{0}}};
    if (!PyArg_ParseTuple(args, "OOOO:map_canonical", &ozq, &oorder, &oinv, &oab)) {
        return NULL;
    }
    if (arr_take(ozq, &a[0], "zq", 'Z', 2, 0, 0) || arr_take(oorder, &a[1], "order", 'q', 2, 1, 0)
        || arr_take(oinv, &a[2], "invariants", 'd', 2, 1, 0) || arr_take(oab, &a[3], "ab", 'd', 1, 1, 0)
        || arr_check_shape(&a[0], "zq", arr_dim(&a[0], 0), 4) || arr_check_shape(&a[1], "order", arr_dim(&a[0], 0), 4)
        || arr_check_shape(&a[2], "invariants", arr_dim(&a[0], 0), 4)
        || arr_check_shape(&a[3], "ab", arr_dim(&a[0], 0), 0)) {
        arr_release(a, 4);
        return NULL;
    }
    for (Py_ssize_t i = 0; i < arr_dim(&a[0], 0); i++) {
        int order[4];
        map_canonical_row(D(a[0]) + 8 * i, order, D(a[2]) + 4 * i, D(a[3]) + i);
        for (int x = 0; x < 4; x++) {
            Q(a[1])[4 * i + x] = order[x];
        }
    }
    arr_release(a, 4);
    Py_RETURN_NONE;
}

PyMethodDef map_quads_methods[] = {
    {"map_quads", map_quads, METH_VARARGS,
     "map_quads(nn, anchors, n, sorted, z, label, n_labels, positions, gap, weight): the distinct quads of anchors "
     "with their k nearest (neighbour_quads), and, given z and label, QuadIndex's: the quads with a frame in "
     "canonical order, their tree points and complex points; three bytearrays; with an 11th "
     "argument ids false (default true), the first empty (the ids not copied out)."},
    {"map_canonical", map_canonical, METH_VARARGS,
     "map_canonical(zq, order, invariants, ab): canonical_quads into the arrays given."},
    {NULL, NULL, 0, NULL},
};
