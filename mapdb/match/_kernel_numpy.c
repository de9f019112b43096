/* numpy's arithmetic and sorts in C, with numpy's order of operations (see _kernel.c's head comment). */
#include "_kernel.h"

#include <math.h>
#include <float.h>
#include <stdlib.h>
#include <string.h>

/* ------------------------------------------------------------------ numpy's arithmetic */

/* numpy's pairwise summation of n doubles (DOUBLE_pairwise_sum), as add.reduce runs it: 0.0 + the sum. */
static double pw_rec(const double *a, Py_ssize_t n)
{
    if (n < 8) {
        double res = -0.0;
        for (Py_ssize_t i = 0; i < n; i++) {
            res += a[i];
        }
        return res;
    }
    if (n <= 128) {
        double r[8];
        Py_ssize_t i;
        for (int j = 0; j < 8; j++) {
            r[j] = a[j];
        }
        for (i = 8; i < n - (n % 8); i += 8) {
            for (int j = 0; j < 8; j++) {
                r[j] += a[i + j];
            }
        }
        double res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]));
        for (; i < n; i++) {
            res += a[i];
        }
        return res;
    }
    Py_ssize_t n2 = n / 2;
    n2 -= n2 % 8;
    return pw_rec(a, n2) + pw_rec(a + n2, n - n2);
}

double pw_sum(const double *a, Py_ssize_t n)
{
    return 0.0 + pw_rec(a, n);
}

/* numpy's pairwise summation of complex numbers (CDOUBLE_pairwise_sum): ``a`` holds n interleaved (re, im)
 * pairs; numpy counts doubles, so its blocks of 8 are 4 complex numbers. */
static void cpw_rec(const double *a, Py_ssize_t n, double *rr, double *ri)
{
    Py_ssize_t m = 2 * n;  /* numpy's n: doubles */
    if (m < 8) {
        *rr = -0.0;
        *ri = -0.0;
        for (Py_ssize_t i = 0; i < m; i += 2) {
            *rr += a[i];
            *ri += a[i + 1];
        }
        return;
    }
    if (m <= 128) {
        double r[8];
        Py_ssize_t i;
        for (int j = 0; j < 8; j++) {
            r[j] = a[j];
        }
        for (i = 8; i < m - (m % 8); i += 8) {
            for (int j = 0; j < 8; j++) {
                r[j] += a[i + j];
            }
        }
        *rr = ((r[0] + r[2]) + (r[4] + r[6]));
        *ri = ((r[1] + r[3]) + (r[5] + r[7]));
        for (; i < m; i += 2) {
            *rr += a[i];
            *ri += a[i + 1];
        }
        return;
    }
    Py_ssize_t m2 = m / 2;
    m2 -= m2 % 8;
    double rr1, ri1, rr2, ri2;
    cpw_rec(a, m2 / 2, &rr1, &ri1);
    cpw_rec(a + m2, n - m2 / 2, &rr2, &ri2);
    *rr = rr1 + rr2;
    *ri = ri1 + ri2;
}

void cpw_sum(const double *a, Py_ssize_t n, double *rr, double *ri)
{
    cpw_rec(a, n, rr, ri);
    *rr = 0.0 + *rr;
    *ri = 0.0 + *ri;
}

/* numpy's complex product as its SIMD loops form it (x86-64 with AVX2 or AVX-512: one fused multiply-add a
 * component, ``fmaddsub``), and its quotient (Smith's algorithm, numpy's special cases).  fma() is correctly
 * rounded on every machine, so the kernel's products are the same everywhere. */
void cmul(double ar, double ai, double br, double bi, double *cr, double *ci)
{
    *cr = fma(ar, br, -(ai * bi));
    *ci = fma(ar, bi, ai * br);
}

void cdiv(double ar, double ai, double br, double bi, double *cr, double *ci)
{
    CDivisor d;
    cdiv_by(br, bi, &d);
    cdiv_apply(&d, ar, ai, cr, ci);
}

/* numpy's absolute value of a complex number as its SIMD loops compute it (x86-64 with AVX2 or AVX-512):
 * larger * sqrt(1 + (smaller / larger)^2) with one fused multiply-add, infinities and NaNs first. */
double cabs_np(double re, double im)
{
    re = fabs(re);
    im = fabs(im);
    if (re == INFINITY || im == INFINITY) {
        return INFINITY;
    }
    if (isnan(re) || isnan(im)) {
        return NAN;
    }
    double larger = re > im ? re : im, smaller = re > im ? im : re;
    double ratio = larger == 0.0 ? 0.0 : smaller / larger;
    return sqrt(fma(ratio, ratio, 1.0)) * larger;
}

/* ------------------------------------------------------------------ sorting */


static int keyed_cmp(const void *pa, const void *pb)
{
    const Keyed *a = pa, *b = pb;
    if (np_less(a->v, b->v)) {
        return -1;
    }
    if (np_less(b->v, a->v)) {
        return 1;
    }
    return (a->i > b->i) - (a->i < b->i);
}

/* Sort by value (NaN last), ties by index: a stable argsort. */
void sort_keyed(Keyed *k, Py_ssize_t n)
{
    if (n > 48) {
        qsort(k, (size_t)n, sizeof(Keyed), keyed_cmp);
        return;
    }
    for (Py_ssize_t i = 1; i < n; i++) {
        Keyed x = k[i];
        Py_ssize_t j = i;
        while (j > 0 && keyed_cmp(&x, &k[j - 1]) < 0) {
            k[j] = k[j - 1];
            j--;
        }
        k[j] = x;
    }
}

static int double_cmp(const void *pa, const void *pb)
{
    double a = *(const double *)pa, b = *(const double *)pb;
    return np_less(a, b) ? -1 : (np_less(b, a) ? 1 : 0);
}

void sort_values(double *x, Py_ssize_t n)
{
    if (n > 48) {
        qsort(x, (size_t)n, sizeof(double), double_cmp);
        return;
    }
    for (Py_ssize_t i = 1; i < n; i++) {
        double v = x[i];
        Py_ssize_t j = i;
        while (j > 0 && np_less(v, x[j - 1])) {
            x[j] = x[j - 1];
            j--;
        }
        x[j] = v;
    }
}
