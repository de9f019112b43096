/* The compiled kernel's shared parts: arrays taken through the buffer protocol (_kernel_buffers.c).
 *
 * The kernel is one extension module, mapdb.match._kernel, built from several C files (setup.py lists them), one
 * concept a file; _kernel.c holds the module and adds each file's functions by its method table.
 */
#ifndef MAPDB_KERNEL_H
#define MAPDB_KERNEL_H

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

/* A buffer taken from a Python object (``held`` when it must be released). */
typedef struct {
    Py_buffer view;
    int held;
} Arr;

/* Release the held buffers of ``a[0 .. count)``. */
void arr_release(Arr *a, int count);
/* Take a C-contiguous buffer of format ``kind`` ('d' float64, 'Z' complex128, '?' bool, 'q' int64, 'Q' uint64,
 * 'i' int32, 'I' uint32, 'B' uint8) and ``ndim`` dimensions from ``obj`` (None allowed when ``optional``: then
 * nothing is held).  Returns 0, or -1 with TypeError / ValueError set. */
int arr_take(PyObject *obj, Arr *a, const char *name, char kind, int ndim, int writable, int optional);
/* The length of axis ``axis`` (-1 when nothing is held). */
Py_ssize_t arr_dim(const Arr *a, int axis);
/* 0 when ``a`` (if held) has ``rows`` rows (and ``cols`` columns when 2-D), else -1 with ValueError set. */
int arr_check_shape(const Arr *a, const char *name, Py_ssize_t rows, Py_ssize_t cols);

/* numpy's arithmetic and sorts, reproduced (_kernel_numpy.c): the same inputs give numpy's bits. */
typedef struct {
    double v;
    Py_ssize_t i;
} Keyed;
double pw_sum(const double *a, Py_ssize_t n);
void cpw_sum(const double *a, Py_ssize_t n, double *rr, double *ri);
void cmul(double ar, double ai, double br, double bi, double *cr, double *ci);
void cdiv(double ar, double ai, double br, double bi, double *cr, double *ci);
/* cdiv in two steps, for several numerators over one denominator (a quad's two points in its frame, a centroid's
 * division by 4): its ratio and scale made once (cdiv_by), then each quotient (cdiv_apply), the same bits. */
typedef struct {
    double rat, scl, zero;  /* zero: |Re b| when b is 0 (numpy divides by it) */
    int by_re;  /* |Re b| >= |Im b| (not when either is NaN) */
    int is_zero;
} CDivisor;
static inline void cdiv_by(double br, double bi, CDivisor *d)
{
    double babs_r = fabs(br), babs_i = fabs(bi);
    d->by_re = babs_r >= babs_i;
    d->is_zero = d->by_re && babs_r == 0 && babs_i == 0;
    d->zero = babs_r;
    d->rat = d->is_zero ? 0.0 : d->by_re ? bi / br : br / bi;
    d->scl = d->is_zero ? 0.0 : d->by_re ? 1.0 / (br + bi * d->rat) : 1.0 / (bi + br * d->rat);
}
/* ``c`` ? a : b, by their bits: no branch to mispredict where c is a coin toss (which side of a quad is longer). */
static inline double select_d(int c, double a, double b)
{
    uint64_t ua, ub, m = (uint64_t)0 - (uint64_t)(c != 0);
    memcpy(&ua, &a, sizeof(ua));
    memcpy(&ub, &b, sizeof(ub));
    ua = (ua & m) | (ub & ~m);
    memcpy(&a, &ua, sizeof(a));
    return a;
}
static inline void cdiv_apply(const CDivisor *d, double ar, double ai, double *cr, double *ci)
{
    if (d->is_zero) {
        *cr = ar / d->zero;
        *ci = ai / d->zero;
        return;
    }
    /* both of Smith's forms, the one numpy takes kept (the same operations in the same order) */
    *cr = select_d(d->by_re, ar + ai * d->rat, ar * d->rat + ai) * d->scl;
    *ci = select_d(d->by_re, ai - ar * d->rat, ai * d->rat - ar) * d->scl;
}
double cabs_np(double re, double im);
/* numpy's order for floats: ascending, NaN last (inline: sorts and nearest-neighbour loops call it per compare). */
static inline int np_less(double a, double b)
{
    return isnan(b) ? !isnan(a) : a < b;
}
void sort_keyed(Keyed *k, Py_ssize_t n);
void sort_values(double *x, Py_ssize_t n);

/* A map objects' KD-tree per label as the kernel reads it (_kernel_objects.c describes the arrays). */
typedef struct {
    const double *pts;
    const int64_t *pid;
    const double *box;
    const int64_t *node;
    const int64_t *root;
    Py_ssize_t n, m, n_labels;
    int bad;  /* set when a node read names a position or child outside the arrays (arrays changed by hand) */
} ObjectsTree;
/* The tree's five arrays from Python objects o[0 .. 5) into a[0 .. 5); 0, or -1 with an error set. */
int objects_take_tree(PyObject **o, Arr *a, ObjectsTree *t);
/* None, or NULL with ValueError when a walk met a node outside the arrays. */
PyObject *objects_checked(const ObjectsTree *t);
/* The nearest object of label l within squared distance bound2 (strictly; ties: lower index), -1 if none. */
int64_t objects_nearest1(ObjectsTree *t, int64_t l, double qx, double qy, double bound2, double *d2);
/* log10_nfa_curve's minimum over k and its index for h rows of n (_kernel_nfa.c); 0, or -1 with MemoryError set. */
int nfa_rows(const double *u, const double *shape, const unsigned char *sample, Py_ssize_t h, Py_ssize_t n,
             Py_ssize_t ns, double offset, double floor_, double *nfa, int64_t *best);
/* The nearest of each query's k neighbours within its reach, not at its row's excluded points (_kernel.c). */
void first_allowed_rows(const double *d, const int64_t *idx, const double *reach, const double *z,
                        Py_ssize_t nz, const double *ex, Py_ssize_t ne, Py_ssize_t repeat,
                        const unsigned char *allowed, Py_ssize_t m, Py_ssize_t k, double *od, int64_t *oi);
/* One hypothesis's tolerance shapes and sample mask from its quad's image points (_kernel.c; buf: 2 q doubles). */
void quad_row(const double *z, Py_ssize_t n, const int64_t *ids, Py_ssize_t q, double *buf, double *shape,
              unsigned char *sample);
/* One row's refinement inliers (x: n doubles, keep: n bytes of room) and one weighted similarity fit (buf: 3 k
 * doubles; out: a, b as re, im pairs), numpy's arithmetic (_kernel.c). */
void row_inliers(const double *u, const double *dist, const int64_t *mid, int64_t k_best, double gate,
                 Py_ssize_t n, double *x, unsigned char *keep, unsigned char *inlier);
void fit_row(const double *src, const double *dst, const double *w, Py_ssize_t k, double *buf, double *out);

/* Each concept's method table, added to the module by PyInit__kernel. */
extern PyMethodDef nfa_methods[];  /* _kernel_nfa.c: the NFA curve and the binomial tail */
extern PyMethodDef objects_methods[];  /* _kernel_objects.c: the map objects' KD-trees per label */
extern PyMethodDef object_discs_methods[];  /* _kernel_object_discs.c: their discs and densities */
extern PyMethodDef verify_methods[];  /* _kernel_verify.c: the verification's fused chains */
extern PyMethodDef verify_refine_methods[];  /* _kernel_verify_refine.c: the refinement, fused */
extern PyMethodDef places_methods[];  /* _kernel_places.c: a round's steps between its verification calls */
/* Quad lookups (_kernel_quads.c). */
extern PyMethodDef quads_methods[];
extern PyMethodDef quad_tree_methods[];  /* _kernel_quad_tree.c */
extern PyMethodDef image_quads_methods[];  /* _kernel_image_quads.c */
extern PyMethodDef map_quads_methods[];  /* _kernel_map_quads.c: a map tile's quads and tree points */
extern PyMethodDef stored_methods[];  /* _kernel_stored.c: the stored quad index's lookup */
extern PyMethodDef hits_methods[];  /* _kernel_hits.c: an image's lookups made hypotheses in few calls */
extern PyMethodDef qdecode_methods[];  /* _kernel_qdecode.c: the stored index's packed blocks decoded */
extern PyMethodDef qcheck_methods[];  /* _kernel_qcheck.c: the stored index's blocks checked (CRC-32) */
extern PyMethodDef screen_methods[];  /* _kernel_screen.c: the screen's neighbours of image objects */

#define D(a) ((double *)(a).view.buf)
#define B(a) ((unsigned char *)(a).view.buf)
#define Q(a) ((int64_t *)(a).view.buf)

#endif
