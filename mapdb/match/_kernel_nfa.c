/* The a contrario decision's number of false alarms (mapdb.match.nfa.log10_nfa_curve): each row's trial chances
 * (sorted normalised residuals, with and without tolerance shapes) and the binomial tail's log10, its minimum
 * over the number of inliers.  numpy's arithmetic as _kernel.c's head comment says. */
#include "_kernel.h"

#include <float.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

/* ------------------------------------------------------------------ trial chances */

/* One row without shapes: the trial objects' sorted u, as chances 1 - exp(-u) (1 where u is not finite). */
static void chances_plain(const double *u, const unsigned char *sample, Py_ssize_t n, Py_ssize_t ns, double *x,
                          double *p)
{
    for (Py_ssize_t i = 0; i < n; i++) {
        x[i] = (sample && sample[i]) ? -1.0 : u[i];
    }
    sort_values(x, n);
    for (Py_ssize_t j = ns; j < n; j++) {
        double v = x[j];
        p[j - ns] = isfinite(v) ? -expm1(-v) : 1.0;
    }
}

/* One row with shapes: thresholds the trial objects' sorted u / shape; the chance of a threshold the mean over
 * trial objects of 1 - exp(-tau shape_i) (``fallback``: numpy's second form, for degenerate shapes). */
static void chances_shaped(const double *u, const double *shape, const unsigned char *sample, Py_ssize_t n,
                           Py_ssize_t ns, Keyed *k, double *rest, double *term, int fallback, double *p)
{
    Py_ssize_t t = n - ns;
    for (Py_ssize_t i = 0; i < n; i++) {
        k[i].v = ((sample && sample[i]) ? -1.0 : u[i]) / shape[i];
        k[i].i = i;
    }
    sort_keyed(k, n);
    int positive = 1;  /* every trial object's shape > 0: an infinite threshold's chances are then all 1 */
    for (Py_ssize_t i = 0; i < t; i++) {
        rest[i] = shape[k[ns + i].i];
        positive &= rest[i] > 0.0;
    }
    for (Py_ssize_t j = 0; j < t; j++) {
        double tau = k[ns + j].v;
        if (positive && tau == INFINITY) {  /* each term expm1(-inf) = -1, their sum -t exactly: p = 1 exactly */
            p[j] = 1.0;
            continue;
        }
        if (!fallback) {
            for (Py_ssize_t i = 0; i < t; i++) {
                term[i] = expm1(-tau * rest[i]);
            }
            p[j] = -(pw_sum(term, t) / (double)t);
            continue;
        }
        for (Py_ssize_t i = 0; i < t; i++) {
            double c = isfinite(tau) ? -expm1(-tau * rest[i]) : 1.0;
            term[i] = isnan(c) ? 1.0 : (c == INFINITY ? DBL_MAX : (c == -INFINITY ? -DBL_MAX : c));
        }
        p[j] = pw_sum(term, t) / (double)t;
    }
}

static void chances_rows(const double *u, const double *shape, const unsigned char *sample, Py_ssize_t h,
                         Py_ssize_t n, Py_ssize_t ns, Keyed *k, double *x, double *term, double *p)
{
    Py_ssize_t t = n - ns;
    int any_nan = 0;
    for (Py_ssize_t r = 0; r < h; r++) {
        const unsigned char *s = sample ? sample + r * n : NULL;
        if (shape == NULL) {
            chances_plain(u + r * n, s, n, ns, x, p + r * t);
        } else {
            chances_shaped(u + r * n, shape + r * n, s, n, ns, k, x, term, 0, p + r * t);
        }
    }
    for (Py_ssize_t j = 0; shape != NULL && j < h * t; j++) {
        any_nan |= isnan(p[j]);
    }
    for (Py_ssize_t r = 0; any_nan && r < h; r++) {
        chances_shaped(u + r * n, shape + r * n, sample ? sample + r * n : NULL, n, ns, k, x, term, 1, p + r * t);
    }
    for (Py_ssize_t j = 0; j < h * t; j++) {  /* clipped to [0, 1], NaN kept (numpy's maximum and minimum) */
        double q = (p[j] >= 0.0 || isnan(p[j])) ? p[j] : 0.0;
        p[j] = (q <= 1.0 || isnan(q)) ? q : 1.0;
    }
}

/* ------------------------------------------------------------------ the binomial tail */

/* ln of the sum of C(n, j) p^j (1-p)^(n-j) from j = from, stepping by ``step`` (+1 or -1) while the terms fall (the
 * first is the largest): each term from its neighbour by their ratio, so nothing overflows and sums far below the
 * double range keep their logarithm.  ``lf[i]`` = ln i!. */
static double log_terms(Py_ssize_t n, Py_ssize_t from, Py_ssize_t step, double p, const double *lf)
{
    double ratio = p / (1.0 - p);
    double head = lf[n] - lf[from] - lf[n - from] + (double)from * log(p) + (double)(n - from) * log1p(-p);
    double sum = 1.0, t = 1.0;
    for (Py_ssize_t j = from + step; j >= 0 && j <= n; j += step) {
        t *= step > 0 ? ratio * (double)(n - j + 1) / (double)j : (double)(j + 1) / ((double)(n - j) * ratio);
        sum += t;
        if (t < sum * 1e-17) {  /* the rest cannot change the sum */
            break;
        }
    }
    return head + log(sum);
}

/* log10 P(Binomial(n, p) >= k) for 1 <= k <= n, as log10(betainc(k, n - k + 1, p)) rounds it: below the mode the
 * upper tail's terms summed from k up; from the mode on, the lower tail's from k - 1 down, and the tail
 * 1 - lower rounded to a double first (a tail of 1.0 is 1.0 as betainc gives it: the curve's ties stay ties).
 * Agrees with scipy's betainc to 1.4e-13 in log10 down to tails of 1e-275, below which betainc underflows early,
 * and with exact rational arithmetic to 1e-12 (tests/test_kernel.py). */
static double log10_tail(Py_ssize_t n, Py_ssize_t k, double p, const double *lf)
{
    if (isnan(p)) {
        return NAN;
    }
    if (p <= 0.0) {
        return -INFINITY;
    }
    if (p >= 1.0) {
        return 0.0;
    }
    if (k > (Py_ssize_t)floor((double)(n + 1) * p)) {
        return log_terms(n, k, 1, p, lf) / M_LN10;
    }
    return log10(1.0 - exp(log_terms(n, k - 1, -1, p, lf)));
}

static PyObject *tail_log10(PyObject *self, PyObject *args)
{
    Py_ssize_t n, k;
    double p;
    if (!PyArg_ParseTuple(args, "nnd:tail_log10", &n, &k, &p)) {
        return NULL;
    }
    if (k < 1 || k > n || n > 100000) {
        PyErr_Format(PyExc_ValueError, "need 1 <= k <= n <= 100000, got n = %zd, k = %zd", n, k);
        return NULL;
    }
    double *lf = PyMem_Malloc(sizeof(double) * (size_t)(n + 1));
    if (lf == NULL) {
        return PyErr_NoMemory();
    }
    for (Py_ssize_t i = 0; i <= n; i++) {
        lf[i] = lgamma((double)i + 1.0);
    }
    double out = log10_tail(n, k, p, lf);
    PyMem_Free(lf);
    return PyFloat_FromDouble(out);
}

/* Each row's minimum over k of offset + max(log10 tail, floor), and where it is (numpy's argmin: the first
 * minimum, the first NaN if any). */
static void curve_rows(const double *p, Py_ssize_t h, Py_ssize_t t, double offset, double floor_, const double *lf,
                       double *nfa, int64_t *best)
{
    for (Py_ssize_t r = 0; r < h; r++) {
        Py_ssize_t arg = 0;
        double low = 0.0;
        for (Py_ssize_t j = 0; j < t; j++) {
            double l = log10_tail(t, j + 1, p[r * t + j], lf);
            double c = offset + ((l >= floor_ || isnan(l)) ? l : floor_);
            if (j == 0 || (!isnan(low) && (c < low || isnan(c)))) {
                low = c;
                arg = j;
            }
        }
        nfa[r] = low;
        best[r] = (int64_t)arg;
    }
}

/* ------------------------------------------------------------------ shaped rows, thresholds skipped exactly */

/* Whether threshold k's curve value c = offset + max(log10 tail, floor) is surely above ``low`` when its chance is
 * at least ``lo`` (0 < lo < 1): the tail P(X >= k) is at least its tail at lo, which is at least its term P(X = k);
 * the tail as computed is within 1e-12 in log10 of the true one (tests/test_kernel.py), and the margin (1e-6, and
 * 1e-9 of the terms' size) is far wider than that and than the rounding here. */
static int nfa_above(Py_ssize_t t, Py_ssize_t k, double lo, const double *lf, double offset, double floor_,
                     double low)
{
    double kl = (double)k * log(lo), rl = (double)(t - k) * log1p(-lo);
    double lb = (lf[t] - lf[k] - lf[t - k] + kl + rl) / M_LN10;
    double err = 1e-6 + 1e-9 * (lf[t] + lf[k] + lf[t - k] + fabs(kl) + fabs(rl));
    double m = lb - err;
    return offset + (m >= floor_ ? m : floor_) > low;
}

/* A lower bound of a threshold tau's chance, the mean over i of 1 - exp(-tau r_i) (0 <= tau < inf, every r_i finite
 * and > 0): each term is at least 1 - exp(-tau r_min), and, 1 - exp(-x) being concave and 0 at 0, at least
 * (r_i / r_max)(1 - exp(-tau r_max)), whose mean is ``share`` (mean r / r_max) times that.  Less 1e-9 of it: far
 * more than the rounding of these few operations and of the chance's own mean of t <= 100000 terms. */
static double nfa_chance_below(double tau, double rmin, double rmax, double share)
{
    double a = -expm1(-tau * rmin), b = share * -expm1(-tau * rmax);
    return (a > b ? a : b) * (1.0 - 1e-9);
}

/* Threshold j's curve value, its chance as chances_shaped forms it (numpy's first form) and its tail as
 * curve_rows reads it; NaN when its chance is NaN. */
static double nfa_threshold(double tau, const double *rest, double *term, Py_ssize_t t, int positive, Py_ssize_t j,
                            const double *lf, double offset, double floor_)
{
    double p = 1.0;
    if (!(positive && tau == INFINITY)) {  /* else each term expm1(-inf) = -1: p = 1 exactly */
        for (Py_ssize_t i = 0; i < t; i++) {
            term[i] = expm1(-tau * rest[i]);
        }
        p = -(pw_sum(term, t) / (double)t);
    }
    if (isnan(p)) {
        return NAN;
    }
    p = p >= 0.0 ? (p <= 1.0 ? p : 1.0) : 0.0;
    double l = log10_tail(t, j + 1, p, lf);
    return offset + ((l >= floor_ || isnan(l)) ? l : floor_);
}

/* One shaped row's curve, chances_shaped and curve_rows for one row (the same operations), with thresholds that
 * cannot be its minimum skipped: their chances (t expm1 each) are never formed.  Walked from the last threshold
 * down (the minimum is mostly near the end: most objects are inliers), a tie kept at the lower threshold (numpy's
 * argmin), a threshold skipped when its curve value is surely above the lowest so far (nfa_above on
 * nfa_chance_below).  Skipping needs every trial shape finite and > 0 and no NaN threshold (then no chance of the
 * row is NaN, formed or not) and offset not NaN; else every threshold in order.  Returns 1 when a chance formed
 * is NaN: the caller then forms the whole array numpy's way (its second form for every row). */
static int nfa_shaped_row(const double *u, const double *shape, const unsigned char *sample, Py_ssize_t n,
                          Py_ssize_t ns, Keyed *k, double *rest, double *term, const double *lf, double offset,
                          double floor_, double *nfa, int64_t *best)
{
    Py_ssize_t t = n - ns, arg = 0;
    for (Py_ssize_t i = 0; i < n; i++) {
        k[i].v = ((sample && sample[i]) ? -1.0 : u[i]) / shape[i];
        k[i].i = i;
    }
    sort_keyed(k, n);
    int positive = 1, skip = !isnan(k[n - 1].v) && !isnan(offset) && t <= 100000;
    double rmin = INFINITY, rmax = 0.0, rsum = 0.0, low = 0.0;
    for (Py_ssize_t i = 0; i < t; i++) {
        rest[i] = shape[k[ns + i].i];
        positive &= rest[i] > 0.0;
        skip &= isfinite(rest[i]);
        rmin = rest[i] < rmin ? rest[i] : rmin;
        rmax = rest[i] > rmax ? rest[i] : rmax;
        rsum += rest[i];
    }
    skip &= positive;
    double share = skip ? (rsum / (double)t) / rmax : 0.0;
    for (Py_ssize_t s = 0; s < t; s++) {
        Py_ssize_t j = skip ? t - 1 - s : s;
        double tau = k[ns + j].v;
        if (skip && s > 0 && tau >= 0.0 && tau < INFINITY) {
            double lo = nfa_chance_below(tau, rmin, rmax, share);
            if (lo > 0.0 && lo < 1.0 && nfa_above(t, j + 1, lo, lf, offset, floor_, low)) {
                continue;
            }
        }
        double c = nfa_threshold(tau, rest, term, t, positive, j, lf, offset, floor_);
        if (isnan(c) && (skip || !isnan(offset))) {
            return 1;  /* a NaN chance (offset is not NaN) */
        }
        if (skip ? (s == 0 || c <= low) : (j == 0 || (!isnan(low) && (c < low || isnan(c))))) {
            low = c;
            arg = j;
        }
    }
    *nfa = low;
    *best = (int64_t)arg;
    return 0;
}

static PyObject *nfa_curve(PyObject *self, PyObject *args)
{
    PyObject *ou, *oshape, *osample, *onfa, *obest;
    Py_ssize_t ns;
    double offset, floor_;
    Arr a[5] = {{{0}}};
    if (!PyArg_ParseTuple(args, "OOOnddOO:nfa_curve", &ou, &oshape, &osample, &ns, &offset, &floor_, &onfa,
                          &obest)) {
        return NULL;
    }
    if (arr_take(ou, &a[0], "u", 'd', 2, 0, 0) || arr_take(oshape, &a[1], "shape", 'd', 2, 0, 1)
        || arr_take(osample, &a[2], "sample", '?', 2, 0, 1) || arr_take(onfa, &a[3], "nfa", 'd', 1, 1, 0)
        || arr_take(obest, &a[4], "best", 'q', 1, 1, 0)) {
        arr_release(a, 5);
        return NULL;
    }
    Py_ssize_t h = arr_dim(&a[0], 0), n = arr_dim(&a[0], 1);
    if (ns < 0 || ns >= n) {
        PyErr_Format(PyExc_ValueError, "n_sample must be in 0..%zd, got %zd", n - 1, ns);
    } else if (!arr_check_shape(&a[1], "shape", h, n) && !arr_check_shape(&a[2], "sample", h, n)
               && !arr_check_shape(&a[3], "nfa", h, 0)) {
        arr_check_shape(&a[4], "best", h, 0);
    }
    if (PyErr_Occurred()) {
        arr_release(a, 5);
        return NULL;
    }
    int failed = nfa_rows(D(a[0]), a[1].held ? D(a[1]) : NULL, a[2].held ? B(a[2]) : NULL, h, n, ns, offset, floor_,
                          D(a[3]), Q(a[4]));
    arr_release(a, 5);
    if (failed) {
        return NULL;
    }
    Py_RETURN_NONE;
}

/* ln i! for i <= NFA_LF_CACHED, made once (the first call holds the GIL): every call's curve reads the same. */
#define NFA_LF_CACHED 4096
static double nfa_lf[NFA_LF_CACHED + 1];
static int nfa_lf_made = 0;

static const double *nfa_lf_table(Py_ssize_t t, double *own)
{
    if (t > NFA_LF_CACHED) {
        for (Py_ssize_t i = 0; i <= t; i++) {
            own[i] = lgamma((double)i + 1.0);
        }
        return own;
    }
    if (!nfa_lf_made) {
        for (Py_ssize_t i = 0; i <= NFA_LF_CACHED; i++) {
            nfa_lf[i] = lgamma((double)i + 1.0);
        }
        nfa_lf_made = 1;
    }
    return nfa_lf;
}

int nfa_rows(const double *u, const double *shape, const unsigned char *sample, Py_ssize_t h, Py_ssize_t n,
             Py_ssize_t ns, double offset, double floor_, double *nfa, int64_t *best)
{
    Py_ssize_t t = n - ns;
    Keyed *k = PyMem_Malloc(sizeof(Keyed) * (size_t)(n + 1));
    double *x = PyMem_Malloc(sizeof(double) * (size_t)(2 * n + 2 + t + 1 + h * t));
    if (k == NULL || x == NULL) {
        PyMem_Free(k);
        PyMem_Free(x);
        PyErr_NoMemory();
        return -1;
    }
    const double *lf = nfa_lf_table(t, x + 2 * n + 2);
    double *p = x + 2 * n + 2 + t + 1;
    Py_BEGIN_ALLOW_THREADS
    int any_nan = 0;
    for (Py_ssize_t r = 0; shape != NULL && !any_nan && r < h; r++) {
        any_nan = nfa_shaped_row(u + r * n, shape + r * n, sample ? sample + r * n : NULL, n, ns, k, x, x + n + 1,
                                 lf, offset, floor_, nfa + r, best + r);
    }
    if (shape == NULL || any_nan) {  /* numpy's way: every chance, then the curves */
        chances_rows(u, shape, sample, h, n, ns, k, x, x + n + 1, p);
        curve_rows(p, h, t, offset, floor_, lf, nfa, best);
    }
    Py_END_ALLOW_THREADS
    PyMem_Free(k);
    PyMem_Free(x);
    return 0;
}

PyMethodDef nfa_methods[] = {
    {"nfa_curve", nfa_curve, METH_VARARGS,
     "nfa_curve(u, shape, sample, n_sample, offset, floor, nfa, best): log10_nfa_curve's minimum over k, the "
     "binomial tail included, and its index."},
    {"tail_log10", tail_log10, METH_VARARGS,
     "tail_log10(n, k, p): log10 P(Binomial(n, p) >= k), the kernel's binomial tail (for tests)."},
    {NULL, NULL, 0, NULL},
};
