/* verify.refine on flat ground, fused into one call (see _kernel_verify.c): each hypothesis's association, NFA
 * curve, inliers and refit, round by round, with numpy's arithmetic. */
#include "_kernel.h"

/* ------------------------------------------------------------------ the refinement, fused */

/* One refinement's inputs (verify.refine on flat ground, an in-memory index). */
typedef struct {
    ObjectsTree *t;
    const double *z, *zmap, *reach, *density, *near_d;
    const int64_t *lab, *near_i;
    Py_ssize_t n, nz, n_labels, k_near, iterations;
    int per_row;
    double bound2, offset, floor_, gate;
} VerifyRefine;

/* Row r's association under z -> (ar + i ai) z + (br + i bi): each object's nearest map object of its label within
 * its reach (ObjectIndex.nearest: from the neighbours of the first projections when ``first`` and given, else the
 * tree bounded per point as verify_screen_u is), and u = (lam pi) (d d). */
static void verify_refine_associate(const VerifyRefine *v, Py_ssize_t r, int first, const double *ab, double *dist,
                                    int64_t *mid, double *u)
{
    for (Py_ssize_t i = 0; i < v->n; i++) {
        int64_t l = v->lab[i], idx;
        double reach_l = v->reach[l], d;
        if (first && v->near_d != NULL) {
            d = v->near_d[(r * v->n + i) * v->k_near];
            idx = v->near_i[(r * v->n + i) * v->k_near];
        } else {
            double wr, wi, d2, prune2 = reach_l * reach_l * (1.0 + 1e-9);
            cmul(ab[0], ab[1], v->z[2 * i], v->z[2 * i + 1], &wr, &wi);
            idx = objects_nearest1(v->t, l, wr + ab[2], wi + ab[3], prune2 < v->bound2 ? prune2 : v->bound2, &d2);
            d = idx >= 0 && d2 < v->bound2 ? sqrt(d2) : INFINITY;
        }
        int ok = d <= reach_l;
        dist[i] = ok ? d : INFINITY;
        mid[i] = ok ? idx : -1;
        u[i] = (v->density[(v->per_row ? r : 0) * v->n_labels + l] * M_PI) * (dist[i] * dist[i]);
    }
}

/* Work room of a row: 9 n + 1 doubles and 3 n + 1 bytes. */
typedef struct {
    double *u, *x, *wts, *target, *buf;
    int64_t *prev_mid;
    unsigned char *keep, *prev_in;
} VerifyRefineWork;

/* verify.refine of row r: associate, decide (the curve's k), the inliers, refit (kept when finite over 3 inliers
 * at least), until the last iteration or an association equal to the previous one (the fit that gave (a, b) was
 * then made from it: every further round would repeat it bit for bit).  ab: a, b as re, im pairs, updated. */
static int verify_refine_row(const VerifyRefine *v, Py_ssize_t r, double *ab, double *nfa, unsigned char *inlier,
                             int64_t *mid, double *dist, VerifyRefineWork *w)
{
    Py_ssize_t n = v->n;
    for (Py_ssize_t it = 0; it <= v->iterations; it++) {
        verify_refine_associate(v, r, it == 0, ab, dist, mid, w->u);
        int64_t best = -5;  /* k_best 0 when there are no trials (log10_nfa_curve's) */
        *nfa = INFINITY;
        if (n > 4 && nfa_rows(w->u, NULL, NULL, 1, n, 4, v->offset, v->floor_, nfa, &best)) {
            return -1;
        }
        row_inliers(w->u, dist, mid, best + 5, v->gate, n, w->x, w->keep, inlier);
        if (it == v->iterations) {
            break;
        }
        if (it > 0 && !memcmp(w->prev_in, inlier, (size_t)n) && !memcmp(w->prev_mid, mid, sizeof(int64_t) * (size_t)n)) {
            break;
        }
        memcpy(w->prev_in, inlier, (size_t)n);
        memcpy(w->prev_mid, mid, sizeof(int64_t) * (size_t)n);
        Py_ssize_t count = 0;
        for (Py_ssize_t i = 0; i < n; i++) {
            int64_t j = mid[i] > 0 ? (mid[i] < v->nz ? mid[i] : v->nz - 1) : 0;  /* indices off the map read its last */
            w->target[2 * i] = v->zmap[2 * j];
            w->target[2 * i + 1] = v->zmap[2 * j + 1];
            w->wts[i] = inlier[i] ? 1.0 : 0.0;
            count += inlier[i] != 0;
        }
        double out[4];
        fit_row(v->z, w->target, w->wts, n, w->buf, out);
        if (isfinite(out[0]) && isfinite(out[1]) && count >= 3) {
            memcpy(ab, out, sizeof(out));
        }
    }
    return 0;
}

static int verify_refine_rows(VerifyRefine *v, Py_ssize_t h, double *a, double *b, double *nfa, unsigned char *inlier,
                              int64_t *mid, double *dist)
{
    Py_ssize_t n = v->n;
    double *room = PyMem_Malloc(sizeof(double) * (size_t)(9 * n + 1));
    unsigned char *bytes = PyMem_Malloc((size_t)(2 * n + 1));
    int64_t *prev_mid = PyMem_Malloc(sizeof(int64_t) * (size_t)(n + 1));
    if (room == NULL || bytes == NULL || prev_mid == NULL) {
        PyMem_Free(room);
        PyMem_Free(bytes);
        PyMem_Free(prev_mid);
        PyErr_NoMemory();
        return -1;
    }
    VerifyRefineWork w = {room, room + n, room + 2 * n, room + 3 * n, room + 5 * n, prev_mid, bytes, bytes + n};
    double rmax = -INFINITY;
    for (Py_ssize_t i = 0; i < n; i++) {
        rmax = v->reach[v->lab[i]] > rmax ? v->reach[v->lab[i]] : rmax;
    }
    double bound = v->bound2 < rmax ? v->bound2 : rmax;  /* bound2 holds half the gap until here */
    v->bound2 = bound * bound;
    int failed = 0;
    for (Py_ssize_t r = 0; r < h && !failed; r++) {
        double ab[4] = {a[2 * r], a[2 * r + 1], b[2 * r], b[2 * r + 1]};
        failed = verify_refine_row(v, r, ab, nfa + r, inlier + r * n, mid + r * n, dist + r * n, &w);
        a[2 * r] = ab[0];
        a[2 * r + 1] = ab[1];
        b[2 * r] = ab[2];
        b[2 * r + 1] = ab[3];
    }
    PyMem_Free(room);
    PyMem_Free(bytes);
    PyMem_Free(prev_mid);
    return failed;
}

static PyObject *verify_refine(PyObject *self, PyObject *args)
{
    static const char *names[14] = {"a", "b", "z", "img_label", "map_z", "reach", "density", "near_d", "near_i", "nfa",
                                    "inlier", "mid", "dist", ""};
    static const char kinds[13] = {'Z', 'Z', 'Z', 'q', 'Z', 'd', 'd', 'd', 'q', 'd', '?', 'q', 'd'};
    static const int dims[13] = {1, 1, 1, 1, 1, 1, 2, 2, 2, 1, 2, 2, 2};
    PyObject *o[18];
    double half_gap, offset, floor_, gate;
    Py_ssize_t iterations;
    Arr a[18] = {{{0}}};
    ObjectsTree t;
    if (!PyArg_ParseTuple(args, "OOOOOOOOOOOOdnOOdddOOOO:verify_refine", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5],
                          &o[6], &o[7], &o[8], &o[9], &o[10], &o[11], &half_gap, &iterations, &o[12], &o[13], &offset,
                          &floor_, &gate, &o[14], &o[15], &o[16], &o[17])) {
        return NULL;
    }
    int failed = objects_take_tree(o, a, &t) < 0;
    for (int j = 0; j < 13 && !failed; j++) {
        failed = arr_take(o[5 + j], &a[5 + j], names[j], kinds[j], dims[j], j < 2 || j > 8, j == 7 || j == 8) < 0;
    }
    Py_ssize_t h = arr_dim(&a[5], 0), n = arr_dim(&a[7], 0), nl = arr_dim(&a[10], 0), k_near = arr_dim(&a[12], 1);
    if (!failed && (arr_check_shape(&a[6], "b", h, 0) || arr_check_shape(&a[8], "img_label", n, 0)
                    || arr_check_shape(&a[11], "density", arr_dim(&a[11], 0), nl)
                    || arr_check_shape(&a[12], "near_d", h * n, k_near) || arr_check_shape(&a[13], "near_i", h * n, k_near)
                    || arr_check_shape(&a[14], "nfa", h, 0) || arr_check_shape(&a[15], "inlier", h, n)
                    || arr_check_shape(&a[16], "mid", h, n) || arr_check_shape(&a[17], "dist", h, n))) {
        failed = 1;
    }
    if (!failed && (n < 1 || iterations < 0 || arr_dim(&a[9], 0) < 1 || a[12].held != a[13].held
                    || (arr_dim(&a[11], 0) != 1 && arr_dim(&a[11], 0) != h) || (a[12].held && k_near < 1))) {
        PyErr_SetString(PyExc_ValueError, "need an object, iterations >= 0, a map object, near_d and near_i alike, "
                                          "and density of one row or a row a hypothesis");
        failed = 1;
    }
    for (Py_ssize_t i = 0; !failed && i < n; i++) {
        if (Q(a[8])[i] < 0 || Q(a[8])[i] >= nl) {
            PyErr_Format(PyExc_ValueError, "img_label holds %lld, outside 0..%zd", (long long)Q(a[8])[i], nl - 1);
            failed = 1;
        }
    }
    for (Py_ssize_t j = 0; !failed && a[13].held && j < h * n * k_near; j++) {
        if (Q(a[13])[j] < 0 || Q(a[13])[j] > arr_dim(&a[9], 0)) {
            PyErr_SetString(PyExc_ValueError, "near_i must hold indices of map objects (or their count: none)");
            failed = 1;
        }
    }
    if (!failed) {
        VerifyRefine v = {&t, D(a[7]), D(a[9]), D(a[10]), D(a[11]), a[12].held ? D(a[12]) : NULL, Q(a[8]),
                          a[13].held ? Q(a[13]) : NULL, n, arr_dim(&a[9], 0), nl, k_near, iterations,
                          arr_dim(&a[11], 0) > 1, half_gap, offset, floor_, gate};
        failed = verify_refine_rows(&v, h, D(a[5]), D(a[6]), D(a[14]), B(a[15]), Q(a[16]), D(a[17]));
    }
    arr_release(a, 18);
    if (failed) {
        return NULL;
    }
    return objects_checked(&t);
}

PyMethodDef verify_refine_methods[] = {
    {"verify_refine", verify_refine, METH_VARARGS,
     "verify_refine(pts, pid, box, node, root, a, b, z, img_label, map_z, reach, density, half_gap, iterations, "
     "near_d, near_i, offset, floor, gate, nfa, inlier, mid, dist): verify.refine on flat ground, fused (a, b "
     "updated in place)."},
    {NULL, NULL, 0, NULL},
};
