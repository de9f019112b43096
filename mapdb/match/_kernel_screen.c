/* The matcher's cheap screens, each one call: the screen's neighbours of image objects (screen.screen_neighbours:
 * each image object's k nearest image objects) and the rivals' quick count (ObjectIndex.near_counts: how many
 * image objects each place puts near a map object of their label).
 *
 * Neighbours of image objects:
 *
 * An image holds a few dozen objects (at most FastOptions.max_objects, 256): they are sorted by x once and each
 * one's k nearest found by walking out from it in x until the x distance alone rules the rest out, the k smallest
 * kept by insertion: no tree to build.  Building scipy's cKDTree over them and querying it cost 0.14 ms an image
 * (its Python-side checks and arrays); this call costs a few microseconds.  Distances compare as scipy's do,
 * (dx dx) + (dy dy) in that order; equal distances rank the lower index first (scipy's order there was its
 * heap's); non-finite points are refused with ValueError, as scipy's tree refused them.
 */
#include "_kernel.h"

/* The k best (squared distance, index) pairs so far, ascending (ties: the lower index first): (d2, j) offered. */
static void screen_offer(double d2, Py_ssize_t j, Py_ssize_t k, Py_ssize_t *kept, double *best, int64_t *out)
{
    if (*kept == k && (d2 > best[k - 1] || (d2 == best[k - 1] && j > out[k - 1]))) {
        return;
    }
    Py_ssize_t at = *kept < k ? (*kept)++ : k - 1;
    while (at > 0 && (d2 < best[at - 1] || (d2 == best[at - 1] && j < out[at - 1]))) {
        best[at] = best[at - 1];
        out[at] = out[at - 1];
        at--;
    }
    best[at] = d2;
    out[at] = j;
}

/* Each point's k nearest: the points in order of x (``by_x``: Keyed of x, index, sorted), each row walking right
 * then left from its own place until dx dx alone passes its k-th squared distance (dx dx + dy dy rounds to no
 * less: every point further along in x is further away, and none of them ties).  The same k as every pair read,
 * at a fraction of the pairs in an image of many objects. */
static void screen_knn_rows(const double *z, Py_ssize_t n, Py_ssize_t k, const Keyed *by_x, double *best,
                            int64_t *out)
{
    for (Py_ssize_t p = 0; p < n; p++) {
        Py_ssize_t i = by_x[p].i, kept = 0;
        double xi = z[2 * i], yi = z[2 * i + 1];
        int64_t *row = out + i * k;
        for (Py_ssize_t step = 1; step >= -1; step -= 2) {
            for (Py_ssize_t q = step > 0 ? p : p - 1; q >= 0 && q < n; q += step) {
                Py_ssize_t j = by_x[q].i;
                double dx = z[2 * j] - xi, dy = z[2 * j + 1] - yi, dx2 = dx * dx;
                if (kept == k && dx2 > best[k - 1]) {
                    break;
                }
                screen_offer(dx2 + dy * dy, j, k, &kept, best, row);
            }
        }
    }
}

static PyObject *screen_knn(PyObject *self, PyObject *args)
{
    PyObject *oz, *oout;
    Arr a[2] = {{{0}}};
    if (!PyArg_ParseTuple(args, "OO:screen_knn", &oz, &oout)) {
        return NULL;
    }
    if (arr_take(oz, &a[0], "z", 'Z', 1, 0, 0) || arr_take(oout, &a[1], "out", 'q', 2, 1, 0)) {
        arr_release(a, 2);
        return NULL;
    }
    Py_ssize_t n = arr_dim(&a[0], 0), k = arr_dim(&a[1], 1);
    if (k < 1 || k > n) {
        PyErr_Format(PyExc_ValueError, "out must have between 1 and %zd columns, got %zd", n, k);
    } else if (!arr_check_shape(&a[1], "out", n, k)) {
        for (Py_ssize_t j = 0; j < 2 * n; j++) {
            if (!isfinite(D(a[0])[j])) {  /* as scipy's tree refused them: no order among NaNs to answer */
                PyErr_SetString(PyExc_ValueError, "z must be finite");
                break;
            }
        }
    }
    if (PyErr_Occurred()) {
        arr_release(a, 2);
        return NULL;
    }
    double *best = PyMem_Malloc(sizeof(double) * (size_t)k);
    Keyed *by_x = PyMem_Malloc(sizeof(Keyed) * (size_t)n);
    if (best == NULL || by_x == NULL) {
        PyMem_Free(best);
        PyMem_Free(by_x);
        arr_release(a, 2);
        return PyErr_NoMemory();
    }
    for (Py_ssize_t i = 0; i < n; i++) {
        by_x[i].v = D(a[0])[2 * i];
        by_x[i].i = i;
    }
    sort_keyed(by_x, n);
    screen_knn_rows(D(a[0]), n, k, by_x, best, Q(a[1]));
    PyMem_Free(best);
    PyMem_Free(by_x);
    arr_release(a, 2);
    Py_RETURN_NONE;
}

/* ------------------------------------------------------------------ the rivals' quick count */

/* Of each pose r (a, b as re, im pairs), how many of the n image objects land closer than sqrt(bound2) to a map
 * object of their label: a z + b as numpy computes it (its complex product, then the sum), each point's nearest
 * under the bound (objects_knn's k = 1 query: a squared distance below bound2; a label outside the tree's, a
 * non-finite point or a NaN bound finds none, as there).  Counts below ``need`` may stop short (still below it). */
static void screen_count_rows(ObjectsTree *t, const double *a, const double *b, const double *z, const int64_t *lab,
                              Py_ssize_t h, Py_ssize_t n, double bound2, int64_t need, int64_t *out)
{
    for (Py_ssize_t r = 0; r < h; r++) {
        int64_t count = 0;
        /* a place that can no longer reach ``need`` stops: its count, below need, is all the caller reads of it */
        for (Py_ssize_t i = 0; i < n && count + (n - i) >= need; i++) {
            double wr, wi, d2;
            cmul(a[2 * r], a[2 * r + 1], z[2 * i], z[2 * i + 1], &wr, &wi);
            wr += b[2 * r];
            wi += b[2 * r + 1];
            count += objects_nearest1(t, lab[i], wr, wi, bound2, &d2) >= 0;
        }
        out[r] = count;
    }
}

static PyObject *screen_near_counts(PyObject *self, PyObject *args)
{
    PyObject *o[5], *oa, *ob, *oz, *olab, *oout;
    double bound;
    long long need;
    Arr a[10] = {{{0}}};
    ObjectsTree t;
    if (!PyArg_ParseTuple(args, "OOOOOOOOOdLO:screen_near_counts", &o[0], &o[1], &o[2], &o[3], &o[4], &oa, &ob, &oz,
                          &olab, &bound, &need, &oout)) {
        return NULL;
    }
    if (objects_take_tree(o, a, &t) < 0 || arr_take(oa, &a[5], "a", 'Z', 1, 0, 0)
        || arr_take(ob, &a[6], "b", 'Z', 1, 0, 0) || arr_take(oz, &a[7], "z", 'Z', 1, 0, 0)
        || arr_take(olab, &a[8], "img_label", 'q', 1, 0, 0) || arr_take(oout, &a[9], "out", 'q', 1, 1, 0)) {
        arr_release(a, 10);
        return NULL;
    }
    Py_ssize_t h = arr_dim(&a[5], 0), n = arr_dim(&a[7], 0);
    if (arr_check_shape(&a[6], "b", h, 0) || arr_check_shape(&a[8], "img_label", n, 0)
        || arr_check_shape(&a[9], "out", h, 0)) {
        arr_release(a, 10);
        return NULL;
    }
    screen_count_rows(&t, D(a[5]), D(a[6]), D(a[7]), Q(a[8]), h, n, bound * bound, (int64_t)need, Q(a[9]));
    arr_release(a, 10);
    return objects_checked(&t);
}

PyMethodDef screen_methods[] = {
    {"screen_near_counts", screen_near_counts, METH_VARARGS,
     "screen_near_counts(pts, pid, box, node, root, a, b, z, img_label, bound, need, out): each pose's image "
     "objects closer than bound to a map object of their label (counts below need may stop short)."},
    {"screen_knn", screen_knn, METH_VARARGS,
     "screen_knn(z, out): each of the n image objects' k nearest (out: (n, k) int64; ties: lower index first)."},
    {NULL, NULL, 0, NULL},
};
