/* The stored quad index's lookup in the kernel (StoredQuadIndex.lookup's per-query work; see _kernel_stored.h).
 *
 * For each query row (invariants q, radius r clamped to its combination's cell side, label key lk): the cells its
 * ball reaches (at most 3 per invariant, those whose box comes within r of q, numpy's arithmetic of the former
 * lookup.query_cells), each found in the directory (the fence names the page, a binary search in the page the cell);
 * then the cells' quads in pieces of at most about ``limit`` candidates (the former lookup.pieces), each piece's
 * candidates bounded from their positions inside their cells (float32 lower bounds within the radius, then the k-th
 * smallest upper bound of a row's candidates: the former bound_candidates, whose margins keep every candidate that
 * can be among the k nearest), the kept ones and 16 spread over the piece resolved and checked to be filed where
 * their invariants put them, and the kept ones within the radius kept k a row, nearest first, ties in the order
 * met (the former lookup.Best).
 */
#include "_kernel_stored.h"

#include <stdlib.h>
#include <string.h>

#define STORED_MARGIN 0.05  /* lookup._BOUND_MARGIN: in positions inside a cell */
#define STORED_SLACK 1e-6   /* lookup._CELL_SLACK: in cells */
#define STORED_AUDITED 16   /* stored.AUDITED */

typedef struct {
    int64_t row, start, count;
    uint64_t key;
    float rel[4];
} StoredCell;

typedef struct {
    StoredCell *v;
    Py_ssize_t n, cap;
} StoredCells;

typedef struct {
    int64_t row, ids[4];
    double dist;
} StoredHit;

typedef struct {
    StoredHit *buf, *out;
    Py_ssize_t n, cap, n_out, cap_out, k;
    int64_t row;
} StoredBest;

static void *stored_grow(void *p, Py_ssize_t *cap, Py_ssize_t need, size_t size)
{
    if (need <= *cap) {
        return p;
    }
    Py_ssize_t c = *cap ? *cap : 16;
    while (c < need) {
        c *= 2;
    }
    void *q = realloc(p, (size_t)c * size);
    if (q == NULL) {
        PyErr_NoMemory();
        return NULL;
    }
    *cap = c;
    return q;
}

static int stored_flush(StoredBest *b)
{
    if (b->n == 0) {
        return 0;
    }
    StoredHit *o = stored_grow(b->out, &b->cap_out, b->n_out + b->n, sizeof(StoredHit));
    if (o == NULL) {
        return -1;
    }
    b->out = o;
    memcpy(b->out + b->n_out, b->buf, (size_t)b->n * sizeof(StoredHit));
    b->n_out += b->n;
    b->n = 0;
    return 0;
}

/* Offer a hit (rows come ascending): kept among its row's k nearest, after the hits of equal distance. */
static int stored_offer(StoredBest *b, const StoredHit *h)
{
    if (h->row != b->row && stored_flush(b)) {
        return -1;
    }
    b->row = h->row;
    Py_ssize_t lo = 0, hi = b->n;
    while (lo < hi) {
        Py_ssize_t mid = lo + (hi - lo) / 2;
        if (b->buf[mid].dist <= h->dist) {
            lo = mid + 1;
        } else {
            hi = mid;
        }
    }
    if (lo >= b->k) {
        return 0;
    }
    if (b->n == b->k) {
        b->n--;
    }
    StoredHit *nb = stored_grow(b->buf, &b->cap, b->n + 1, sizeof(StoredHit));
    if (nb == NULL) {
        return -1;
    }
    b->buf = nb;
    memmove(b->buf + lo + 1, b->buf + lo, (size_t)(b->n - lo) * sizeof(StoredHit));
    b->buf[lo] = *h;
    b->n++;
    return 0;
}

/* The page that can hold ``key`` (the last whose first key is at most key; -1 if none).  A row's cells come in key
 * order: the search gallops from the previous key's page ``*hint`` (-1: a binary search of the whole fence). */
static Py_ssize_t stored_page(const StoredTables *t, uint64_t key, Py_ssize_t *hint)
{
    Py_ssize_t lo = 0, hi = t->n_pages;
    if (*hint >= 0 && t->fence_key[*hint] <= key) {
        lo = *hint;
        Py_ssize_t step = 1;
        while (lo + step < t->n_pages && t->fence_key[lo + step] <= key) {
            lo += step;
            step *= 2;
        }
        hi = lo + step < t->n_pages ? lo + step : t->n_pages;
        lo++;
    }
    while (lo < hi) {  /* the first page whose first key is above key */
        Py_ssize_t mid = lo + (hi - lo) / 2;
        if (t->fence_key[mid] <= key) {
            lo = mid + 1;
        } else {
            hi = mid;
        }
    }
    *hint = lo - 1;
    return lo - 1;
}

/* The directory's cell of ``key`` (-1 absent), or -2 when its page is not decoded yet (then asked for once). */
static int64_t stored_find(const StoredTables *t, uint64_t key, StoredNeeds *nd, uint8_t *asked, int *err,
                           Py_ssize_t *hint)
{
    Py_ssize_t page = stored_page(t, key, hint);
    if (page < 0) {
        return -1;
    }
    if (!t->decoded[page]) {
        if (!asked[page]) {
            asked[page] = 1;
            *err = stored_push(&nd->pages, page);
        }
        return -2;
    }
    int64_t a = t->first_cell[page], b = t->first_cell[page + 1];
    if (a < 0 || b < a || b > t->n_cells) {
        *err = -(10 + STORED_BAD_RANGE);
        return -1;
    }
    while (a < b) {
        int64_t mid = a + (b - a) / 2;
        if (t->dir_key[mid] < key) {
            a = mid + 1;
        } else {
            b = mid;
        }
    }
    return a < t->first_cell[page + 1] && t->dir_key[a] == key ? a : -1;
}

/* A found cell kept (its quads' blocks asked for when not all checked). */
static int stored_keep_cell(const StoredTables *t, StoredCells *out, StoredCell *c, int64_t at, StoredNeeds *nd)
{
    c->start = t->dir_start[at];
    c->count = t->dir_count[at];
    if (c->start < 0 || c->count < 0 || c->start > t->n_quads - c->count) {
        return -(10 + STORED_BAD_RANGE);
    }
    if (c->count) {  /* its quads' blocks checked by the kernel before any is read (qcheck_quads) */
        for (int64_t blk = (c->start * t->rb) >> STORED_BLOCK_BITS;
             blk <= ((c->start + c->count) * t->rb - 1) >> STORED_BLOCK_BITS; blk++) {
            if (!t->q_checked[blk] && stored_push(&nd->quads, blk)) {
                return -1;
            }
        }
    }
    StoredCell *v = stored_grow(out->v, &out->cap, out->n + 1, sizeof(StoredCell));
    if (v == NULL) {
        return -1;
    }
    out->v = v;
    out->v[out->n++] = *c;
    return 0;
}

/* The cells query row ``i``'s ball reaches, found in the directory (the former query_cells and Directory.find). */
static int stored_row_cells(const StoredTables *t, const StoredAsk *a, Py_ssize_t i, StoredCells *out,
                            StoredNeeds *nd, uint8_t *asked)
{
    double s[4], cell = a->cell[i], sc = (double)(1 << t->sub_bits);
    int64_t base[4], top = ((int64_t)1 << t->bits) - 1;
    for (int j = 0; j < 4; j++) {
        s[j] = (a->q[4 * i + j] + 1.0) / cell;
        double f = floor(s[j]);
        if (!(f < 4.0e18)) {
            return 0;  /* every cell of it out of the keys' range */
        }
        base[j] = f > 0 ? (int64_t)f : 0;
    }
    double reach = (a->r[i] / cell) * (1.0 + STORED_SLACK) + STORED_SLACK, g2[4][3];
    int in[4][3];
    for (int j = 0; j < 4; j++) {  /* each invariant's squared gap to its 3 cells, and whether they are keys' */
        for (int d = 0; d < 3; d++) {
            int64_t c = base[j] + d - 1;
            double x = (double)c - s[j], y = s[j] - (double)(c + 1), g = x > y ? x : y;
            g = g > 0.0 ? g : 0.0;
            g2[j][d] = g * g;
            in[j][d] = c >= 0 && c <= top;
        }
    }
    Py_ssize_t hint = -1;
    for (int step = 0; step < 81; step++) {
        int d0 = step / 27, d1 = (step / 9) % 3, d2 = (step / 3) % 3, d3 = step % 3;
        /* (gap * gap).sum(axis=2), numpy's order */
        double sum = ((g2[0][d0] + g2[1][d1]) + g2[2][d2]) + g2[3][d3];
        if (!(in[0][d0] && in[1][d1] && in[2][d2] && in[3][d3]) || !(sum <= reach * reach)) {
            continue;
        }
        int64_t cand[4] = {base[0] + d0 - 1, base[1] + d1 - 1, base[2] + d2 - 1, base[3] + d3 - 1};
        StoredCell c = {.row = i, .key = (uint64_t)a->lk[i]};
        for (int j = 0; j < 4; j++) {
            c.key = (c.key << t->bits) | (uint64_t)cand[j];
            c.rel[j] = (float)((s[j] - (double)cand[j]) * sc);
        }
        int err = 0;
        int64_t at = stored_find(t, c.key, nd, asked, &err, &hint);
        if (err) {
            return err;
        }
        if (at >= 0 && (err = stored_keep_cell(t, out, &c, at, nd))) {
            return err;
        }
    }
    return 0;
}

/* Lower bound (float32, squared, in positions) of a candidate at ``sub`` from a query at ``rel``. */
static float stored_lower(const uint8_t *sub, const float *rel)
{
    float d[4];
    for (int j = 0; j < 4; j++) {
        d[j] = fabsf((float)sub[j] - (rel[j] - 0.5f)) - 0.5f;
        d[j] = d[j] > 0.0f ? d[j] * d[j] : 0.0f;
    }
    return (d[0] + d[1]) + (d[2] + d[3]);
}

static int64_t stored_upper(const uint8_t *sub, const float *rel)
{
    float d[4];
    for (int j = 0; j < 4; j++) {
        d[j] = fabsf((float)sub[j] - (rel[j] - 0.5f)) + 0.5f;
        d[j] *= d[j];
    }
    return (int64_t)ceilf(sqrtf((d[0] + d[1]) + (d[2] + d[3])) * 16.0f);
}

static int stored_cmp64(const void *x, const void *y)
{
    int64_t a = *(const int64_t *)x, b = *(const int64_t *)y;
    return (a > b) - (a < b);
}

/* A piece's candidates: their cell and position, lower bound and state (1 kept, 2 audited). */
typedef struct {
    Py_ssize_t n, cap;
    int64_t *cell, *pos, *tmp;
    float *lower;
    uint8_t *state;
} StoredPiece;

static int stored_piece_room(StoredPiece *p, Py_ssize_t need)
{
    if (need <= p->cap) {
        return 0;
    }
    Py_ssize_t cap = p->cap ? 2 * p->cap : 256;
    while (cap < need) {
        cap *= 2;
    }
    int64_t *cell = realloc(p->cell, (size_t)cap * 8), *pos = cell ? realloc(p->pos, (size_t)cap * 8) : NULL;
    p->cell = cell ? cell : p->cell;
    p->pos = pos ? pos : p->pos;
    int64_t *tmp = pos ? realloc(p->tmp, (size_t)cap * 8) : NULL;
    p->tmp = tmp ? tmp : p->tmp;
    float *lower = tmp ? realloc(p->lower, (size_t)cap * sizeof(float)) : NULL;
    p->lower = lower ? lower : p->lower;
    uint8_t *state = lower ? realloc(p->state, (size_t)cap) : NULL;
    p->state = state ? state : p->state;
    if (state == NULL) {
        PyErr_NoMemory();
        return -1;
    }
    p->cap = cap;
    return 0;
}

/* A row's kept candidates [i, j) cut to those whose lower bound is within the k-th smallest upper bound. */
static void stored_kth(const StoredTables *t, const StoredCells *cs, StoredPiece *p, Py_ssize_t i, Py_ssize_t j,
                       Py_ssize_t k, float rf)
{
    Py_ssize_t n = 0;
    for (Py_ssize_t x = i; x < j; x++) {
        if (p->state[x]) {
            int64_t an, tr;
            uint8_t sub[4];
            stored_record(t, p->pos[x], &an, &tr, sub);
            p->tmp[n++] = stored_upper(sub, cs->v[p->cell[x]].rel);
        }
    }
    if (n <= k) {
        return;
    }
    qsort(p->tmp, (size_t)n, sizeof(int64_t), stored_cmp64);
    float kth = (float)((double)p->tmp[k - 1] / 16.0 + STORED_MARGIN);
    float lim = fminf(kth, rf);
    for (Py_ssize_t x = i; x < j; x++) {
        p->state[x] = p->state[x] && p->lower[x] <= lim * lim;
    }
}

/* The piece's candidates bounded (state 1: kept), then 16 spread over it audited (state | 2). */
static void stored_bound(const StoredTables *t, const StoredAsk *a, const StoredCells *cs, StoredPiece *p)
{
    double sc = (double)(1 << t->sub_bits);
    for (Py_ssize_t i = 0; i < p->n;) {
        int64_t row = cs->v[p->cell[i]].row;
        float rf = (float)(a->r[row] * (sc / a->cell[row]) + STORED_MARGIN);
        Py_ssize_t j = i;
        for (; j < p->n && cs->v[p->cell[j]].row == row; j++) {
            int64_t an, tr;
            uint8_t sub[4];
            stored_record(t, p->pos[j], &an, &tr, sub);
            p->lower[j] = stored_lower(sub, cs->v[p->cell[j]].rel);
            p->state[j] = p->lower[j] <= rf * rf;
        }
        stored_kth(t, cs, p, i, j, a->k, rf);
        i = j;
    }
    Py_ssize_t num = p->n < STORED_AUDITED ? p->n : STORED_AUDITED;  /* np.linspace(0, n - 1, num), truncated */
    for (Py_ssize_t x = 0; x < num; x++) {
        Py_ssize_t at = x == num - 1 ? p->n - 1 : (Py_ssize_t)((double)x * ((double)(p->n - 1) / (double)(num - 1)));
        p->state[at] |= 2;
    }
}

/* Resolve, check and measure a bounded piece; hits offered to ``b`` (none once something needs checking). */
static int stored_measure(const StoredTables *t, const StoredAsk *a, const StoredCells *cs, StoredPiece *p,
                          StoredNeeds *nd, StoredBest *b, int *incomplete)
{
    for (Py_ssize_t i = 0; i < p->n; i++) {
        if (!p->state[i]) {
            continue;
        }
        const StoredCell *c = &cs->v[p->cell[i]];
        StoredHit h = {.row = c->row};
        int64_t an, tr;
        uint8_t sub[4];
        double inv[4], d2 = 0.0;
        stored_record(t, p->pos[i], &an, &tr, sub);
        int rc = stored_resolve_one(t, an, tr, nd, h.ids, inv);
        if (rc < 0) {
            return rc;
        }
        if (rc == 1) {
            *incomplete = 1;
            continue;
        }
        if (!stored_filed(t, inv, c->key, sub, a->cell[c->row])) {
            return -(10 + STORED_NOT_FILED);
        }
        if (!(p->state[i] & 1) || *incomplete) {
            continue;
        }
        for (int j = 0; j < 4; j++) {
            double d = inv[j] - a->q[4 * c->row + j];
            d2 = j ? d2 + d * d : d * d;
        }
        h.dist = sqrt(d2);
        if (h.dist <= a->r[c->row] && stored_offer(b, &h)) {
            return -1;
        }
    }
    return 0;
}

/* The found cells' candidates in pieces (the former lookup.pieces: ranges cut at ``limit``, a piece the parts whose
 * cumulative end falls in one multiple of ``limit``). */
static int stored_pieces(const StoredTables *t, const StoredAsk *a, const StoredCells *cs, StoredNeeds *nd,
                         StoredBest *b, int *incomplete)
{
    StoredPiece p = {0};
    int64_t group = -1, end = 0, limit = a->limit;
    int rc = 0;
    for (Py_ssize_t c = 0; c < cs->n && !rc; c++) {
        for (int64_t part = 0; part * limit < cs->v[c].count && !rc; part++) {
            int64_t s0 = cs->v[c].start + part * limit, len = cs->v[c].count - part * limit;
            len = len < limit ? len : limit;
            end += len;
            if ((end - 1) / limit != group && p.n) {
                stored_bound(t, a, cs, &p);
                rc = stored_measure(t, a, cs, &p, nd, b, incomplete);
                p.n = 0;
            }
            group = (end - 1) / limit;
            if (!rc && !(rc = stored_piece_room(&p, p.n + len))) {
                for (int64_t x = 0; x < len; x++, p.n++) {
                    p.cell[p.n] = c;
                    p.pos[p.n] = s0 + x;
                }
            }
        }
    }
    if (!rc && p.n) {
        stored_bound(t, a, cs, &p);
        rc = stored_measure(t, a, cs, &p, nd, b, incomplete);
    }
    free(p.cell), free(p.pos), free(p.tmp), free(p.lower), free(p.state);
    return rc;
}

/* (2, code) on corruption; (1, pages, ranges, neighbours' objects, coordinates' objects) when something needs
 * checking first; else (0, rows, ids, distances) as bytes. */
static PyObject *stored_answer(int rc, const StoredNeeds *nd, const StoredBest *b, const int64_t *row_of)
{
    if (rc == -1) {
        return NULL;
    }
    if (rc < -1) {
        return Py_BuildValue("(ii)", 2, -rc - 10);
    }
    if (stored_needs_any(nd)) {
        return Py_BuildValue("(iNNNN)", 1, stored_vec_bytes(&nd->pages), stored_vec_bytes(&nd->ranges),
                             stored_vec_bytes(&nd->nb), stored_vec_bytes(&nd->co));
    }
    PyObject *rows = PyBytes_FromStringAndSize(NULL, b->n_out * 8), *ids = PyBytes_FromStringAndSize(NULL, b->n_out * 32);
    PyObject *dist = PyBytes_FromStringAndSize(NULL, b->n_out * 8);
    if (rows == NULL || ids == NULL || dist == NULL) {
        Py_XDECREF(rows), Py_XDECREF(ids), Py_XDECREF(dist);
        return NULL;
    }
    for (Py_ssize_t i = 0; i < b->n_out; i++) {
        ((int64_t *)PyBytes_AS_STRING(rows))[i] = row_of ? row_of[b->out[i].row] : b->out[i].row;
        memcpy(PyBytes_AS_STRING(ids) + 32 * i, b->out[i].ids, 32);
        ((double *)PyBytes_AS_STRING(dist))[i] = b->out[i].dist;
    }
    return Py_BuildValue("(iNNN)", 0, rows, ids, dist);
}

static int stored_take_ask(PyObject **o, Arr *a, StoredAsk *ask)
{
    if (arr_take(o[0], &a[0], "invariants", 'd', 2, 0, 0) || arr_take(o[1], &a[1], "radius", 'd', 1, 0, 0)
        || arr_take(o[2], &a[2], "cell", 'd', 1, 0, 0) || arr_take(o[3], &a[3], "label keys", 'q', 1, 0, 0)) {
        return -1;
    }
    ask->m = arr_dim(&a[0], 0);
    if (arr_check_shape(&a[0], "invariants", ask->m, 4) || arr_check_shape(&a[1], "radius", ask->m, 0)
        || arr_check_shape(&a[2], "cell", ask->m, 0) || arr_check_shape(&a[3], "label keys", ask->m, 0)) {
        return -1;
    }
    if (ask->k < 1 || ask->limit < 1) {
        PyErr_SetString(PyExc_ValueError, "k and limit must be at least 1");
        return -1;
    }
    ask->q = D(a[0]), ask->r = D(a[1]), ask->cell = D(a[2]), ask->lk = Q(a[3]);
    return 0;
}

static PyObject *stored_lookup(PyObject *self, PyObject *args)
{
    PyObject *ot, *o[4];
    StoredAsk ask = {0};
    if (!PyArg_ParseTuple(args, "OOOOOnn:stored_lookup", &ot, &o[0], &o[1], &o[2], &o[3], &ask.k, &ask.limit)) {
        return NULL;
    }
    StoredTables t;
    Arr a[4] = {{{0}}};
    PyObject *out = NULL;
    if (!stored_take_tables(ot, &t) && !stored_take_ask(o, a, &ask)) {
        out = stored_run(&t, &ask, NULL);
    }
    arr_release(t.a, STORED_TABLES), arr_release(a, 4);
    return out;
}

/* The lookup of ``ask``'s rows on the tables (_kernel_stored.h); ``row_of`` (or NULL) renames the answer's rows. */
PyObject *stored_run(const StoredTables *t, const StoredAsk *ask, const int64_t *row_of)
{
    StoredNeeds nd = {{0}};
    StoredCells cs = {0};
    StoredBest b = {.k = ask->k, .row = -1};
    uint8_t *asked = calloc((size_t)t->n_pages + 1, 1);
    int rc = asked ? 0 : (PyErr_NoMemory(), -1);
    for (Py_ssize_t i = 0; i < ask->m && !rc; i++) {
        rc = stored_row_cells(t, ask, i, &cs, &nd, asked);
    }
    if (!rc && !nd.pages.n && !nd.ranges.n) {
        int incomplete = 0;
        rc = qcheck_quads(t, &nd.quads);
        rc = rc ? rc : stored_pieces(t, ask, &cs, &nd, &b, &incomplete);
        rc = rc ? rc : stored_flush(&b);
    }
    PyObject *out = stored_answer(rc, &nd, &b, row_of);
    free(asked), free(cs.v), free(b.buf), free(b.out);
    stored_needs_free(&nd);
    return out;
}

/* Object ids (canonical order) and invariants of quads given by anchors and triple numbers. */
static PyObject *stored_resolve(PyObject *self, PyObject *args)
{
    PyObject *ot, *oa, *otr;
    if (!PyArg_ParseTuple(args, "OOO:stored_resolve", &ot, &oa, &otr)) {
        return NULL;
    }
    StoredTables t;
    Arr a[2] = {{{0}}};
    if (stored_take_tables(ot, &t) || arr_take(oa, &a[0], "anchor", 'q', 1, 0, 0)
        || arr_take(otr, &a[1], "triple", 'q', 1, 0, 0) || arr_check_shape(&a[1], "triple", arr_dim(&a[0], 0), 0)) {
        arr_release(t.a, STORED_TABLES), arr_release(a, 2);
        return NULL;
    }
    Py_ssize_t n = arr_dim(&a[0], 0);
    StoredNeeds nd = {{0}};
    PyObject *ids = PyBytes_FromStringAndSize(NULL, n * 32), *inv = PyBytes_FromStringAndSize(NULL, n * 32), *out;
    int rc = ids && inv ? 0 : -1;
    for (Py_ssize_t i = 0; i < n && rc >= 0; i++) {
        int64_t *id = (int64_t *)PyBytes_AS_STRING(ids) + 4 * i;
        double *iv = (double *)PyBytes_AS_STRING(inv) + 4 * i;
        int r = stored_resolve_one(&t, Q(a[0])[i], Q(a[1])[i], &nd, id, iv);
        rc = r < 0 ? r : rc;
    }
    if (rc == -1) {
        out = NULL;
    } else if (rc < -1) {
        out = Py_BuildValue("(ii)", 2, -rc - 10);
    } else if (stored_needs_any(&nd)) {
        out = Py_BuildValue("(iNNNN)", 1, stored_vec_bytes(&nd.pages), stored_vec_bytes(&nd.ranges),
                            stored_vec_bytes(&nd.nb), stored_vec_bytes(&nd.co));
    } else {
        out = Py_BuildValue("(iOO)", 0, ids, inv);
    }
    Py_XDECREF(ids), Py_XDECREF(inv);
    stored_needs_free(&nd);
    arr_release(t.a, STORED_TABLES), arr_release(a, 2);
    return out;
}

PyMethodDef stored_methods[] = {
    {"stored_lookup", stored_lookup, METH_VARARGS,
     "stored_lookup(tables, invariants, radius, cell, label_keys, k, limit): a stored index's lookup of query rows "
     "(their radii already clamped to their cells): (0, rows, ids, distances) as bytes, (1, pages, ranges, "
     "neighbour objects, coordinate objects) to check first, or (2, code) when the file is corrupt."},
    {"stored_resolve", stored_resolve, METH_VARARGS,
     "stored_resolve(tables, anchor, triple): (0, ids, invariants) as bytes of quads given by anchors and triple "
     "numbers, (1, ...) as stored_lookup's needs, or (2, code)."},
    {NULL, NULL, 0, NULL},
};
