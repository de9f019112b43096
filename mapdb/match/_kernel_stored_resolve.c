/* The stored quad index's quads resolved in the kernel (see _kernel_stored.h): a record's anchor and triple number
 * to the quad's object ids in canonical order and its invariants, as StoredQuadIndex._resolve computed them with
 * numpy (neighbours decoded from their packed blocks, packed.neighbour_fields; coordinates from the decoded blocks,
 * x = (x_i + ox) * quantum in float64; the ids sorted, then canonical_quads' row, _kernel_map_quads.c), and the
 * check that a resolved quad is filed where its invariants put it (binding.check_filed's row).
 */
#include "_kernel_stored.h"

#include <stdlib.h>
#include <string.h>

/* canonical_quads' row (_kernel_map_quads.c). */
void map_canonical_row(const double *z, int *order, double *t, double *ab);

int stored_push(StoredVec *s, int64_t x)
{
    if (s->n == s->cap) {
        Py_ssize_t cap = s->cap ? 2 * s->cap : 64;
        int64_t *v = realloc(s->v, (size_t)cap * sizeof(int64_t));
        if (v == NULL) {
            PyErr_NoMemory();
            return -1;
        }
        s->v = v;
        s->cap = cap;
    }
    s->v[s->n++] = x;
    return 0;
}

void stored_needs_free(StoredNeeds *nd)
{
    free(nd->pages.v);
    free(nd->ranges.v);
    free(nd->quads.v);
    free(nd->nb.v);
    free(nd->co.v);
    memset(nd, 0, sizeof(*nd));
}

int stored_needs_any(const StoredNeeds *nd)
{
    return nd->pages.n || nd->ranges.n || nd->nb.n || nd->co.n;
}

PyObject *stored_vec_bytes(const StoredVec *s)
{
    return PyBytes_FromStringAndSize((const char *)s->v, (Py_ssize_t)(s->n * (Py_ssize_t)sizeof(int64_t)));
}

/* The tables' arrays: name, format letters, item size, dimensions (the order of StoredQuadIndex._tables). */
static const struct {
    const char *name;
    char kind;  /* arr_take's: 'B' uint8, '?' bool, 'Q' uint64, 'q' int64, 'i' int32, 'I' uint32 */
    int ndim;
} stored_specs[STORED_TABLES] = {
    {"quads", 'B', 2}, {"quads checked", '?', 1}, {"fence keys", 'Q', 1}, {"first cells", 'q', 1},
    {"pages decoded", '?', 1}, {"cell keys", 'Q', 1}, {"cell starts", 'q', 1}, {"cell counts", 'q', 1},
    {"triples", 'q', 2}, {"nb_start", 'Q', 1}, {"nb_width", 'B', 1}, {"nb_data", 'B', 1},
    {"neighbours checked", '?', 1}, {"coordinates", 'i', 2}, {"coordinates decoded", '?', 1},
    {"quads checksums", 'I', 1},
};

static int stored_bad(const char *what)
{
    PyErr_Format(PyExc_ValueError, "stored index tables: %s", what);
    return -1;
}

/* The tables' sizes checked against each other. */
static int stored_check_sizes(StoredTables *t)
{
    Arr *a = t->a;
    t->n_quads = arr_dim(&a[0], 0);
    t->rb = arr_dim(&a[0], 1);
    t->q_blocks = arr_dim(&a[1], 0);
    t->n_pages = arr_dim(&a[4], 0);
    t->n_cells = arr_dim(&a[5], 0);
    t->n_triples = arr_dim(&a[8], 0);
    t->nb_blocks = arr_dim(&a[10], 0);
    t->nb_bytes = arr_dim(&a[11], 0);
    t->co_blocks = arr_dim(&a[14], 0);
    if (t->rb < 1 || t->rb > 8 || t->q_blocks < (t->n_quads * t->rb + 4095) / 4096 || arr_dim(&a[15], 0) != t->q_blocks) {
        return stored_bad("quads and their blocks disagree");
    }
    if (a[1].view.readonly) {  /* the lookup marks the quads blocks it checks (_kernel_qcheck.c) */
        return stored_bad("quads checked must be writable");
    }
    if (arr_dim(&a[2], 0) != t->n_pages || arr_dim(&a[3], 0) != t->n_pages + 1 || arr_dim(&a[6], 0) != t->n_cells
        || arr_dim(&a[7], 0) != t->n_cells || arr_dim(&a[8], 1) != 3 || arr_dim(&a[9], 0) < t->nb_blocks
        || arr_dim(&a[12], 0) != t->nb_blocks || arr_dim(&a[13], 1) != 2 || arr_dim(&a[13], 0) != t->n_objects
        || t->co_blocks < (t->n_objects + STORED_NB_BLOCK - 1) / STORED_NB_BLOCK) {
        return stored_bad("array sizes disagree");
    }
    if (t->bits < 1 || 4 * t->bits > 63 || t->sub_bits < 1 || t->sub_bits > 8 || t->triple_bits < 1
        || 4 * t->sub_bits + t->triple_bits > 63 || t->k_nb < 0 || t->k_nb > 64 || !isfinite(t->quantum)) {
        return stored_bad("parameters out of range");
    }
    return 0;
}

int stored_take_tables(PyObject *tables, StoredTables *t)
{
    memset(t, 0, sizeof(*t));
    if (!PyTuple_Check(tables) || PyTuple_GET_SIZE(tables) != STORED_TABLES + 1) {
        PyErr_SetString(PyExc_TypeError, "tables must be a tuple of 16 arrays and a tuple of parameters");
        return -1;
    }
    for (int i = 0; i < STORED_TABLES; i++) {
        if (arr_take(PyTuple_GET_ITEM(tables, i), &t->a[i], stored_specs[i].name, stored_specs[i].kind,
                     stored_specs[i].ndim, 0, 0)) {
            return -1;
        }
    }
    long long n, ox, oy;
    if (!PyArg_ParseTuple(PyTuple_GET_ITEM(tables, STORED_TABLES), "iiiiLLLd;tables' parameters", &t->sub_bits,
                          &t->triple_bits, &t->bits, &t->k_nb, &n, &ox, &oy, &t->quantum)) {
        return -1;
    }
    t->n_objects = n;
    t->ox = ox;
    t->oy = oy;
    Arr *a = t->a;
    t->quads = B(a[0]), t->q_checked = B(a[1]), t->fence_key = (const uint64_t *)a[2].view.buf;
    t->first_cell = Q(a[3]), t->decoded = B(a[4]), t->dir_key = (const uint64_t *)a[5].view.buf;
    t->dir_start = Q(a[6]), t->dir_count = Q(a[7]), t->triples = Q(a[8]);
    t->nb_start = (const uint64_t *)a[9].view.buf, t->nb_width = B(a[10]), t->nb_data = B(a[11]);
    t->nb_checked = B(a[12]), t->xy = (const int32_t *)a[13].view.buf, t->co_decoded = B(a[14]);
    t->q_crcs = (const uint32_t *)a[15].view.buf, t->q_mark = (uint8_t *)a[1].view.buf;
    return stored_check_sizes(t);
}

void stored_record(const StoredTables *t, Py_ssize_t at, int64_t *anchor, int64_t *triple, uint8_t *sub)
{
    uint64_t v = 0;
    const uint8_t *row = t->quads + at * t->rb;
    for (Py_ssize_t b = t->rb - 1; b >= 0; b--) {
        v = (v << 8) | row[b];
    }
    uint64_t mask = ((uint64_t)1 << t->sub_bits) - 1;
    for (int j = 0; j < 4; j++) {
        sub[3 - j] = (uint8_t)((v >> (t->sub_bits * j)) & mask);
    }
    v >>= 4 * t->sub_bits;
    *triple = (int64_t)(v & (((uint64_t)1 << t->triple_bits) - 1));
    *anchor = (int64_t)(v >> t->triple_bits);
}

/* The k_nb neighbours of ``anchor`` (its block checked): 0, or a corruption code. */
static int stored_neighbours(const StoredTables *t, int64_t anchor, int64_t *nb)
{
    int64_t block = anchor / STORED_NB_BLOCK;
    int64_t w = t->nb_width[block];
    if (w > PACKED_MAX_WIDTH || t->nb_start[block] > (uint64_t)t->nb_bytes) {
        return STORED_BAD_RANGE;
    }
    int bad = 0;
    for (int j = 0; j < t->k_nb; j++) {
        int64_t at = (int64_t)t->nb_start[block] * 8 + ((anchor % STORED_NB_BLOCK) * t->k_nb + j) * w;
        nb[j] = anchor + packed_unzigzag(packed_field(t->nb_data, t->nb_bytes, at, w, &bad));
        if (bad) {
            return STORED_BAD_RANGE;
        }
        if (nb[j] < 0 || nb[j] >= t->n_objects) {
            return STORED_BAD_ID;
        }
    }
    return 0;
}

static inline void stored_sort4(int64_t *v)
{
    static const int net[5][2] = {{0, 1}, {2, 3}, {0, 2}, {1, 3}, {1, 2}};
    for (int c = 0; c < 5; c++) {
        int64_t a = v[net[c][0]], b = v[net[c][1]];
        v[net[c][0]] = a < b ? a : b;
        v[net[c][1]] = a < b ? b : a;
    }
}

/* Record an object whose block is not checked (not again when the previous one recorded is of the same block). */
static int stored_need(StoredVec *v, int64_t id)
{
    if (v->n && v->v[v->n - 1] / STORED_NB_BLOCK == id / STORED_NB_BLOCK) {
        return 0;
    }
    return stored_push(v, id);
}

int stored_resolve_one(const StoredTables *t, int64_t anchor, int64_t triple, StoredNeeds *nd, int64_t *ids,
                       double *inv)
{
    if (anchor < 0 || anchor >= t->n_objects || triple < 0 || triple >= t->n_triples) {
        return -(10 + STORED_BAD_ID);
    }
    int64_t block = anchor / STORED_NB_BLOCK, nb[64], m[4];
    if (block >= t->nb_blocks) {
        return -(10 + STORED_BAD_ID);
    }
    if (!t->nb_checked[block]) {  /* every such anchor: Python reads their neighbours' coordinates at once */
        return stored_push(&nd->nb, anchor) ? -1 : 1;
    }
    int bad = stored_neighbours(t, anchor, nb);
    if (bad) {
        return -(10 + bad);
    }
    m[0] = anchor;
    for (int c = 0; c < 3; c++) {
        int64_t j = t->triples[3 * triple + c];
        if (j < 0 || j >= t->k_nb) {
            return -(10 + STORED_BAD_RANGE);
        }
        m[1 + c] = nb[j];
    }
    stored_sort4(m);
    int need = 0;
    for (int c = 0; c < 4; c++) {
        if (!t->co_decoded[m[c] / STORED_NB_BLOCK]) {
            need = 1;
            if (stored_need(&nd->co, m[c])) {
                return -1;
            }
        }
    }
    if (need) {
        return 1;
    }
    double z[8];
    for (int c = 0; c < 4; c++) {
        z[2 * c] = (double)((int64_t)t->xy[2 * m[c]] + t->ox) * t->quantum;
        z[2 * c + 1] = (double)((int64_t)t->xy[2 * m[c] + 1] + t->oy) * t->quantum;
    }
    int order[4];
    map_canonical_row(z, order, inv, NULL);
    for (int c = 0; c < 4; c++) {
        ids[c] = m[order[c]];
    }
    return 0;
}

int stored_filed(const StoredTables *t, const double *inv, uint64_t key, const uint8_t *sub, double cell)
{
    double sc = (double)(1 << t->sub_bits);
    uint64_t mine = key >> (4 * t->bits);
    for (int j = 0; j < 4; j++) {
        if (!isfinite(inv[j])) {
            return 0;
        }
        double s = (inv[j] + 1.0) / cell, k = floor(s);
        double f = floor((s - k) * sc);
        f = f < 0 ? 0 : (f > sc - 1 ? sc - 1 : f);
        if (!(s < 9.0e18) || (uint8_t)f != sub[j]) {  /* a cell that far is in no key */
            return 0;
        }
        mine = (mine << t->bits) | (uint64_t)(int64_t)(k > 0 ? k : 0);
    }
    return mine == key;
}
