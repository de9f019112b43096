/* A round's places (screen._screened_fused): the steps between its kernel calls, one call each, and the distinct
 * places among its hypotheses (refine.distinct).
 *
 * places_shortlist: the screen's best hypotheses (a stable argsort of its NFA, NaN last, the first ``shortlist``),
 * their rows, and their projections a z + b (numpy's complex product, then the sum) with their labels, flat, as
 * the neighbours' query reads them.  places_chosen: the decision's distinct places (a stable argsort of its NFA,
 * each hypothesis's separation |a| diag_px fraction, then distinct's loop), their rows, their neighbours' rows and
 * the radius of their density discs (factor |a| diag_px / 2).  The numpy calls they replace (argsort, abs,
 * products, row takes, repeat, reshape) cost 50-60 microseconds a round on an analysis image, for a few hundred
 * floating point operations; each value is computed as numpy computed it (cabs_np, cmul), in the same order.
 *
 * places_reach: each label's search reach under a round's places' densities (ObjectIndex.label_reach of an (H, L)
 * density): sqrt(u_max / (pi min_r density[r, l])), numpy's column minimum (a NaN kept) and its operations in order.
 *
 * places_pairs: refine.candidates' rows (a finite pose and three inliers at least) and their (image, map) pairs in
 * row order, one call for the nine numpy calls that found them.
 *
 * Distinct places:
 *
 * The hypotheses are read in the order given (best first); one is kept when its place b lies farther than the
 * larger of the two separations from every place kept before it, until ``limit`` are kept.  The Python loop it
 * replaces compared Python complex numbers: |b_i - b_j| is their abs (the C library's hypot of the difference's
 * parts, inf when either part is infinite, NaN when either is NaN and none is infinite), and the larger separation
 * is Python's max(s_i, s_j) (s_j when s_j > s_i, else s_i: a NaN first stays, a NaN second is passed over), so the
 * same places are kept for any input.  A round's screen called that loop with 16 hypotheses and 4 places to keep:
 * 30 microseconds of Python calls an image for a few hundred floating point operations.
 */
#include "_kernel.h"

/* |z| of a Python complex z (complex_abs: hypot, with infinities before NaNs). */
static double places_abs(double re, double im)
{
    if (isinf(re) || isinf(im)) {
        return INFINITY;
    }
    if (isnan(re) || isnan(im)) {
        return NAN;
    }
    return hypot(re, im);
}

/* The kept rows of ``order`` (m of them, each in 0 .. h) written to out; how many.  As the loop did, the limit is
 * looked at once a row is kept: a limit below 1 keeps the first row (out holds min(m, max(limit, 1))). */
static Py_ssize_t places_keep(const double *b, const double *sep, const int64_t *order, Py_ssize_t m,
                              Py_ssize_t limit, int64_t *out)
{
    Py_ssize_t kept = 0;
    for (Py_ssize_t p = 0; p < m; p++) {
        int64_t i = order[p];
        int apart = 1;
        for (Py_ssize_t q = 0; q < kept && apart; q++) {
            int64_t j = out[q];
            double wider = sep[j] > sep[i] ? sep[j] : sep[i];  /* Python's max(sep[i], sep[j]) */
            apart = places_abs(b[2 * i] - b[2 * j], b[2 * i + 1] - b[2 * j + 1]) > wider;
        }
        if (apart) {
            out[kept++] = i;
            if (kept >= limit) {
                break;
            }
        }
    }
    return kept;
}

/* How many rows places_keep may keep of m. */
static Py_ssize_t places_room(Py_ssize_t m, Py_ssize_t limit)
{
    Py_ssize_t cap = limit < 1 ? 1 : limit;
    return m < cap ? m : cap;
}

static PyObject *places_distinct(PyObject *self, PyObject *args)
{
    PyObject *ob, *oorder, *osep, *oout;
    Py_ssize_t limit;
    Arr a[4] = {{{0}}};
    if (!PyArg_ParseTuple(args, "OOOnO:places_distinct", &ob, &oorder, &osep, &limit, &oout)) {
        return NULL;
    }
    if (arr_take(ob, &a[0], "b", 'Z', 1, 0, 0) || arr_take(oorder, &a[1], "order", 'q', 1, 0, 0)
        || arr_take(osep, &a[2], "separation", 'd', 1, 0, 0) || arr_take(oout, &a[3], "out", 'q', 1, 1, 0)) {
        arr_release(a, 4);
        return NULL;
    }
    Py_ssize_t h = arr_dim(&a[0], 0), m = arr_dim(&a[1], 0);
    if (arr_check_shape(&a[2], "separation", h, 0)) {
        arr_release(a, 4);
        return NULL;
    }
    if (arr_dim(&a[3], 0) < places_room(m, limit)) {
        PyErr_Format(PyExc_ValueError, "out must hold min(max(limit, 1), %zd) rows", m);
        arr_release(a, 4);
        return NULL;
    }
    for (Py_ssize_t p = 0; p < m; p++) {
        if (Q(a[1])[p] < 0 || Q(a[1])[p] >= h) {
            PyErr_Format(PyExc_ValueError, "order must hold indices in 0 .. %zd", h - 1);
            arr_release(a, 4);
            return NULL;
        }
    }
    Py_ssize_t kept = places_keep(D(a[0]), D(a[2]), Q(a[1]), m, limit, Q(a[3]));
    arr_release(a, 4);
    return PyLong_FromSsize_t(kept);
}

/* A stable argsort of x[0 .. h) (NaN last, ties by index) into order; 0, or -1 with MemoryError set. */
static int places_argsort(const double *x, Py_ssize_t h, int64_t *order)
{
    Keyed *k = PyMem_Malloc(sizeof(Keyed) * (size_t)(h + 1));
    if (k == NULL) {
        PyErr_NoMemory();
        return -1;
    }
    for (Py_ssize_t i = 0; i < h; i++) {
        k[i].v = x[i];
        k[i].i = i;
    }
    sort_keyed(k, h);
    for (Py_ssize_t i = 0; i < h; i++) {
        order[i] = (int64_t)k[i].i;
    }
    PyMem_Free(k);
    return 0;
}

/* Rows rows[0 .. m) of a, b (complex), ids (q int64 a row) and map_z (q complex a row) into the outputs. */
static void places_rows(const int64_t *rows, Py_ssize_t m, Py_ssize_t q, const Arr *in, Arr *out)
{
    for (Py_ssize_t p = 0; p < m; p++) {
        int64_t r = rows[p];
        memcpy(D(out[0]) + 2 * p, D(in[0]) + 2 * r, 2 * sizeof(double));
        memcpy(D(out[1]) + 2 * p, D(in[1]) + 2 * r, 2 * sizeof(double));
        memcpy(Q(out[2]) + p * q, Q(in[2]) + r * q, (size_t)q * sizeof(int64_t));
        memcpy(D(out[3]) + 2 * p * q, D(in[3]) + 2 * r * q, 2 * (size_t)q * sizeof(double));
    }
}

/* Take the hypotheses' arrays a, b (h complex), ids (h, q int64), map_z (h, q complex) from o[0 .. 4) into in and
 * their outputs (m rows each, writable) from o[4 .. 8) into out; 0, or -1 with an error set (all released). */
static int places_take_rows(PyObject **o, Arr *in, Arr *out, Py_ssize_t h, Py_ssize_t m, Py_ssize_t *q)
{
    static const char kinds[4] = {'Z', 'Z', 'q', 'Z'};
    static const char *names[8] = {"a", "b", "ids", "map_z", "out_a", "out_b", "out_ids", "out_map_z"};
    for (int j = 0; j < 8; j++) {
        if (arr_take(o[j], j < 4 ? &in[j] : &out[j - 4], names[j], kinds[j % 4], j % 4 < 2 ? 1 : 2, j >= 4, 0)) {
            arr_release(in, 4);
            arr_release(out, 4);
            return -1;
        }
    }
    *q = arr_dim(&in[2], 1);
    for (int j = 0; j < 4; j++) {
        Py_ssize_t cols = j < 2 ? 0 : *q;
        if (arr_check_shape(&in[j], names[j], h, cols) || arr_check_shape(&out[j], names[j + 4], m, cols)) {
            arr_release(in, 4);
            arr_release(out, 4);
            return -1;
        }
    }
    return 0;
}

static PyObject *places_shortlist(PyObject *self, PyObject *args)
{
    PyObject *o[8], *onfa, *oz, *olab, *ow, *olabels;
    Py_ssize_t shortlist, q;
    Arr in[4] = {{{0}}}, out[4] = {{{0}}}, a[5] = {{{0}}};
    if (!PyArg_ParseTuple(args, "OOOOOOOnOOOOOO:places_shortlist", &onfa, &o[0], &o[1], &o[2], &o[3], &oz, &olab,
                          &shortlist, &o[4], &o[5], &o[6], &o[7], &ow, &olabels)) {
        return NULL;
    }
    if (arr_take(onfa, &a[0], "nfa", 'd', 1, 0, 0) || arr_take(oz, &a[1], "z", 'Z', 1, 0, 0)
        || arr_take(olab, &a[2], "img_label", 'q', 1, 0, 0) || arr_take(ow, &a[3], "out_w", 'Z', 1, 1, 0)
        || arr_take(olabels, &a[4], "out_labels", 'q', 1, 1, 0)) {
        arr_release(a, 5);
        return NULL;
    }
    Py_ssize_t h = arr_dim(&a[0], 0), n = arr_dim(&a[1], 0), m = shortlist < h ? shortlist : h;
    if (shortlist < 0 || arr_check_shape(&a[2], "img_label", n, 0) || arr_check_shape(&a[3], "out_w", m * n, 0)
        || arr_check_shape(&a[4], "out_labels", m * n, 0) || places_take_rows(o, in, out, h, m, &q)) {
        if (!PyErr_Occurred()) {
            PyErr_SetString(PyExc_ValueError, "shortlist must be at least 0");
        }
        arr_release(a, 5);
        return NULL;
    }
    int64_t *order = PyMem_Malloc(sizeof(int64_t) * (size_t)(h + 1));
    if (order == NULL || places_argsort(D(a[0]), h, order)) {
        PyMem_Free(order);
        arr_release(a, 5);
        arr_release(in, 4);
        arr_release(out, 4);
        return order == NULL ? PyErr_NoMemory() : NULL;
    }
    places_rows(order, m, q, in, out);
    const double *z = D(a[1]);
    for (Py_ssize_t p = 0; p < m; p++) {  /* a z + b: numpy's product, then its sum */
        const double *ar = D(out[0]) + 2 * p, *br = D(out[1]) + 2 * p;
        for (Py_ssize_t i = 0; i < n; i++) {
            double *w = D(a[3]) + 2 * (p * n + i);
            cmul(ar[0], ar[1], z[2 * i], z[2 * i + 1], &w[0], &w[1]);
            w[0] += br[0];
            w[1] += br[1];
            Q(a[4])[p * n + i] = Q(a[2])[i];
        }
    }
    PyMem_Free(order);
    arr_release(a, 5);
    arr_release(in, 4);
    arr_release(out, 4);
    return PyLong_FromSsize_t(m);
}

/* The distinct places' rows (chosen[0 .. c)) of the neighbours (n k a hypothesis) and their discs' radii. */
static void places_near_rows(const int64_t *chosen, Py_ssize_t c, Py_ssize_t nk, const Arr *near, Arr *out,
                             const double *a, double factor, double diag_px, double *radius)
{
    for (Py_ssize_t p = 0; p < c; p++) {
        int64_t r = chosen[p];
        memcpy(D(out[0]) + p * nk, D(near[0]) + r * nk, (size_t)nk * sizeof(double));
        memcpy(Q(out[1]) + p * nk, Q(near[1]) + r * nk, (size_t)nk * sizeof(int64_t));
        radius[p] = ((factor * cabs_np(a[2 * r], a[2 * r + 1])) * diag_px) / 2.0;
    }
}

/* The distinct places of h hypotheses by their nfa (sep: room for h doubles, order: for h, chosen: for limit). */
static Py_ssize_t places_choose(const double *nfa, const double *a, const double *b, Py_ssize_t h, double diag_px,
                                double fraction, Py_ssize_t limit, double *sep, int64_t *order, int64_t *chosen)
{
    if (places_argsort(nfa, h, order)) {
        return -1;
    }
    for (Py_ssize_t i = 0; i < h; i++) {
        sep[i] = (cabs_np(a[2 * i], a[2 * i + 1]) * diag_px) * fraction;  /* np.abs(a) * diag_px * fraction */
    }
    return places_keep(b, sep, order, h, limit, chosen);
}

static PyObject *places_chosen(PyObject *self, PyObject *args)
{
    PyObject *o[8], *onfa, *ond, *oni, *ood, *ooi, *orad;
    Py_ssize_t n, limit, q;
    double diag_px, fraction, factor;
    Arr in[4] = {{{0}}}, out[4] = {{{0}}}, a[6] = {{{0}}};
    if (!PyArg_ParseTuple(args, "OOOOOOOndddnOOOOOOO:places_chosen", &onfa, &o[0], &o[1], &o[2], &o[3], &ond, &oni,
                          &n, &diag_px, &fraction, &factor, &limit, &o[4], &o[5], &o[6], &o[7], &ood, &ooi, &orad)) {
        return NULL;
    }
    if (arr_take(onfa, &a[0], "nfa", 'd', 1, 0, 0) || arr_take(ond, &a[1], "near_d", 'd', 2, 0, 0)
        || arr_take(oni, &a[2], "near_i", 'q', 2, 0, 0) || arr_take(ood, &a[3], "out_near_d", 'd', 2, 1, 0)
        || arr_take(ooi, &a[4], "out_near_i", 'q', 2, 1, 0) || arr_take(orad, &a[5], "out_radius", 'd', 1, 1, 0)) {
        arr_release(a, 6);
        return NULL;
    }
    Py_ssize_t h = arr_dim(&a[0], 0), k = arr_dim(&a[1], 1), m = places_room(h, limit);
    if (n < 0 || arr_check_shape(&a[1], "near_d", h * n, k) || arr_check_shape(&a[2], "near_i", h * n, k)
        || arr_check_shape(&a[3], "out_near_d", m * n, k) || arr_check_shape(&a[4], "out_near_i", m * n, k)
        || arr_check_shape(&a[5], "out_radius", m, 0) || places_take_rows(o, in, out, h, m, &q)) {
        if (!PyErr_Occurred()) {
            PyErr_SetString(PyExc_ValueError, "n must be at least 0");
        }
        arr_release(a, 6);
        return NULL;
    }
    double *sep = PyMem_Malloc(sizeof(double) * (size_t)(h + 1));
    int64_t *order = PyMem_Malloc(sizeof(int64_t) * (size_t)(h + m + 1)), *chosen = order + h;
    Py_ssize_t c = sep == NULL || order == NULL ? -2
                   : places_choose(D(a[0]), D(in[0]), D(in[1]), h, diag_px, fraction, limit, sep, order, chosen);
    if (c >= 0) {
        places_rows(chosen, c, q, in, out);
        places_near_rows(chosen, c, n * k, &a[1], &a[3], D(in[0]), factor, diag_px, D(a[5]));
    }
    PyMem_Free(sep);
    PyMem_Free(order);
    arr_release(a, 6);
    arr_release(in, 4);
    arr_release(out, 4);
    if (c == -2) {
        return PyErr_NoMemory();
    }
    return c < 0 ? NULL : PyLong_FromSsize_t(c);
}

/* The kept rows of h poses (a: re, im pairs) over n objects: written to keep, each one's end in pairs to ends and
 * its pairs (image index, mid) to pairs; how many rows were kept. */
static Py_ssize_t places_pairs_rows(const double *a, const unsigned char *inlier, const int64_t *mid, Py_ssize_t h,
                                    Py_ssize_t n, int64_t *keep, int64_t *ends, int64_t *pairs)
{
    Py_ssize_t kept = 0, end = 0;
    for (Py_ssize_t r = 0; r < h; r++) {
        Py_ssize_t count = 0;
        for (Py_ssize_t i = 0; i < n; i++) {
            count += inlier[r * n + i] != 0;
        }
        if (!(isfinite(a[2 * r]) && isfinite(a[2 * r + 1])) || count < 3) {
            continue;
        }
        for (Py_ssize_t i = 0; i < n; i++) {
            if (inlier[r * n + i]) {
                pairs[2 * end] = i;
                pairs[2 * end + 1] = mid[r * n + i];
                end++;
            }
        }
        keep[kept] = r;
        ends[kept++] = end;
    }
    return kept;
}

static PyObject *places_pairs(PyObject *self, PyObject *args)
{
    static const char *names[6] = {"a", "inlier", "mid", "out_keep", "out_ends", "out_pairs"};
    static const char kinds[6] = {'Z', '?', 'q', 'q', 'q', 'q'};
    static const int dims[6] = {1, 2, 2, 1, 1, 2};
    PyObject *o[6];
    Arr a[6] = {{{0}}};
    if (!PyArg_ParseTuple(args, "OOOOOO:places_pairs", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5])) {
        return NULL;
    }
    for (int j = 0; j < 6; j++) {
        if (arr_take(o[j], &a[j], names[j], kinds[j], dims[j], j >= 3, 0)) {
            arr_release(a, 6);
            return NULL;
        }
    }
    Py_ssize_t h = arr_dim(&a[0], 0), n = arr_dim(&a[1], 1);
    if (arr_check_shape(&a[1], "inlier", h, n) || arr_check_shape(&a[2], "mid", h, n)
        || arr_check_shape(&a[3], "out_keep", h, 0) || arr_check_shape(&a[4], "out_ends", h, 0)
        || arr_check_shape(&a[5], "out_pairs", h * n, 2)) {
        arr_release(a, 6);
        return NULL;
    }
    Py_ssize_t kept = places_pairs_rows(D(a[0]), B(a[1]), Q(a[2]), h, n, Q(a[3]), Q(a[4]), Q(a[5]));
    arr_release(a, 6);
    return PyLong_FromSsize_t(kept);
}

static PyObject *places_reach(PyObject *self, PyObject *args)
{
    PyObject *od, *oout;
    double u_max;
    Arr a[2] = {{{0}}};
    if (!PyArg_ParseTuple(args, "OdO:places_reach", &od, &u_max, &oout)) {
        return NULL;
    }
    if (arr_take(od, &a[0], "density", 'd', 2, 0, 0) || arr_take(oout, &a[1], "out", 'd', 1, 1, 0)) {
        arr_release(a, 2);
        return NULL;
    }
    Py_ssize_t h = arr_dim(&a[0], 0), nl = arr_dim(&a[0], 1);
    if (arr_check_shape(&a[1], "out", nl, 0)) {
        arr_release(a, 2);
        return NULL;
    }
    if (h < 1 && nl > 0) {  /* numpy's min of no rows */
        arr_release(a, 2);
        PyErr_SetString(PyExc_ValueError, "density has no rows: no minimum");
        return NULL;
    }
    const double *d = D(a[0]);
    for (Py_ssize_t l = 0; l < nl; l++) {
        double m = d[l];
        for (Py_ssize_t r = 1; r < h; r++) {
            double x = d[r * nl + l];
            m = (m <= x || isnan(m)) ? m : x;  /* np.minimum: a NaN on either side is kept */
        }
        D(a[1])[l] = sqrt(u_max / (M_PI * m));
    }
    arr_release(a, 2);
    Py_RETURN_NONE;
}

PyMethodDef places_methods[] = {
    {"places_reach", places_reach, METH_VARARGS,
     "places_reach(density, u_max, out): each label's reach sqrt(u_max / (pi min over rows of density)) (density: "
     "(H, L), H >= 1)."},
    {"places_pairs", places_pairs, METH_VARARGS,
     "places_pairs(a, inlier, mid, out_keep, out_ends, out_pairs) -> kept: the rows with a finite a and three "
     "inliers at least, each one's end in out_pairs and its (image index, mid) pairs, in row order."},
    {"places_chosen", places_chosen, METH_VARARGS,
     "places_chosen(nfa, a, b, ids, map_z, near_d, near_i, n, diag_px, fraction, factor, limit, out_a, out_b, "
     "out_ids, out_map_z, out_near_d, out_near_i, out_radius) -> c: the c distinct places (outputs of "
     "min(max(limit, 1), h) rows) (distinct of the stable "
     "argsort of nfa, separations |a| diag_px fraction), their rows, their neighbours' rows (n a hypothesis) and "
     "their density discs' radii factor |a| diag_px / 2."},
    {"places_shortlist", places_shortlist, METH_VARARGS,
     "places_shortlist(nfa, a, b, ids, map_z, z, img_label, shortlist, out_a, out_b, out_ids, out_map_z, out_w, "
     "out_labels) -> m: the m = min(shortlist, h) best rows by nfa (stable, NaN last), their projections a z + b "
     "and labels (m n, flat)."},
    {"places_distinct", places_distinct, METH_VARARGS,
     "places_distinct(b, order, separation, limit, out) -> kept: the rows of order (best first) whose place b lies "
     "farther than the larger separation from every row kept before, at most max(limit, 1), written to out."},
    {NULL, NULL, 0, NULL},
};
