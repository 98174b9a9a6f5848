/* The per-step arithmetic of a bank of AFVSGP learners (paper eqs. 20-30), compiled.
 *
 * The compiled core of afvsgp_gym.gp.afvsgp_bank.AFVSGPBank (its docstring states the method
 * and the state's layout): one call streams a sample into every learner (update), one
 * predicts the learners of some barriers (predict), one scores a new sample as an inducing
 * point (candidate). The numpy methods' formulas (the posterior in whitened form), the
 * kernel's exponent from the differences to the inducing points (not the numpy methods'
 * expansion: it reads ~8x less memory and cannot overflow), the Cholesky factorisations and
 * the eq. 28 product by the LAPACK and BLAS that scipy ships (scipy.linalg.cython_lapack /
 * cython_blas), the prediction's triangular solves by forward substitution here (at these
 * sizes, tens of right-hand sides of order Mp, BLAS's dtrsm spends its time on packing), the
 * exponentials by vexp here (numpy.exp runs libm's scalar exp on a CPU without AVX-512, at
 * 5-11 ns each). The bank's arrays are taken once, into a State (state()), which the entry
 * points take in place of them; every array is C-ordered float64 (int64 for indices, bool
 * for flags) with the bank's shapes; a return code other than 0 leaves the call to the numpy
 * methods, and when it does the bank was left unchanged (update) or its posterior cache only
 * refreshed (predict).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <string.h>

typedef void (*gemm_t)(char *, char *, int *, int *, int *, double *, double *, int *,
                       double *, int *, double *, double *, int *);
typedef void (*potrf_t)(char *, int *, double *, int *, int *);

static gemm_t dgemm_;
static potrf_t dpotrf_;

/* return codes */
#define OVERFLOW -1   /* a kernel exponent is NaN: the numpy methods take over */
#define NOT_PD -2     /* a Cholesky factorisation failed: the numpy methods jitter */
#define NO_MEMORY -3

#define MAXW 4096 /* columns of the whitening workspace: Mp + c + 1 */
#define MAXB 1024 /* input dimension */
#define TOO_MANY_ROWS -5 /* more predicted rows than the scratch array holds */
#define NOT_FINITE -6    /* a sample is not finite: the numpy method skips it */

#include "../_cbuf.h"

/* ------------------------------------------------------------------ kernel rows */

typedef struct {
    int K, b, c, mp, P; /* learners, input and ubar dimensions, inducing slots, window */
} Dims;

/* The hot loops, one copy per instruction set (_bank_simd.h), chosen when the module loads:
 * every copy does the same arithmetic in the same order, so the choice changes the speed,
 * never a digit. */
typedef struct {
    const char *name;
    void (*weighted_row_sums)(const double *, size_t, const double *, int, int, double *);
    void (*symv)(const double *restrict, const double *restrict, int, double *restrict);
    void (*gram_rows)(const double *restrict, int, int, int, double *restrict);
    void (*lower_solve_rows)(const double *restrict, int, double *restrict, int, int, double);
    int (*exponents)(const Dims *, const double *, const double *, const double *, int,
                     const double *, double *restrict, double *restrict);
    void (*window_exponents)(double *restrict, const double *restrict, double,
                             const double *restrict, const double *restrict, int, int, int);
    void (*add_scaled_product)(double *restrict, double, const double *restrict,
                               const double *restrict, int);
    void (*kernel_row)(double *restrict, const double *restrict, const double *restrict, int,
                       int, double *restrict);
    double (*window_step)(double *restrict, const double *restrict, double *restrict, double,
                          double, int, double, double, const double *restrict, int);
    void (*whitened_step)(double *restrict, const double *restrict, const double *restrict,
                          double, int, double, int);
    void (*vexp)(double *restrict, Py_ssize_t);
} Simd;

/* exp(x) = 2^k exp(r): k = rint(x / ln2) by adding 1.5 2^52 (its low bits then hold k), r = (x -
 * k ln2_hi) - k ln2_lo (Cody and Waite: ln2_hi has 32 significant bits, so k ln2_hi and the
 * first difference are exact), exp(r) = 1 + (r + r^2 P(r)) with P Taylor's 1/2! .. 1/13!
 * (|r| <= 0.3466: truncation below 6e-18 relative) in Estrin's scheme, 2^k added to the
 * exponent bits; outside [EXP_LO, EXP_HI] (a subnormal or infinite result) by ldexp, NaN
 * kept. No FMA, and the same expression for scalars and vectors: every step rounds once, the
 * same in every copy and on every machine (numpy.exp's rounding depends on the CPU). */
#define EXP_INV_LN2 1.4426950408889634
#define EXP_SHIFT 6755399441055744.0          /* 1.5 2^52 */
#define EXP_LN2_HI 6.93147180369123816490e-01 /* 0x3fe62e42fee00000 */
#define EXP_LN2_LO 1.90821492927058770002e-10
#define EXP_LO -708.0
#define EXP_HI 709.0
#define EXP_PAIR(a, b, r) ((1.0 / (a)) + (1.0 / (b)) * (r))
/* exp(r) from r, r^2, r^4 (scalars or vectors alike) */
#define EXP_REDUCED(r, r2, r4)                                                               \
    (1.0 + ((r) + (r2) * ((EXP_PAIR(2.0, 6.0, r) + (r2) * EXP_PAIR(24.0, 120.0, r)) +        \
                          (r4) * ((EXP_PAIR(720.0, 5040.0, r) +                               \
                                   (r2) * EXP_PAIR(40320.0, 362880.0, r)) +                   \
                                  (r4) * (EXP_PAIR(3628800.0, 39916800.0, r) +                \
                                          (r2) * EXP_PAIR(479001600.0, 6227020800.0, r))))))

static double vexp_one(double x)
{
    if (isnan(x))
        return x;
    if (x < -746.0)
        return 0.0;
    if (x > 710.0)
        return HUGE_VAL;
    const double t = x * EXP_INV_LN2 + EXP_SHIFT, k = t - EXP_SHIFT;
    const double r = (x - k * EXP_LN2_HI) - k * EXP_LN2_LO, r2 = r * r, r4 = r2 * r2;
    double p = EXP_REDUCED(r, r2, r4);
    if (x < EXP_LO || x > EXP_HI)
        return ldexp(p, (int)k);
    unsigned long long pb, tb;
    memcpy(&pb, &p, sizeof pb);
    memcpy(&tb, &t, sizeof tb);
    pb += tb << 52;
    memcpy(&p, &pb, sizeof p);
    return p;
}

#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__)
#define SIMD_X86 1
#pragma GCC push_options
#pragma GCC target("avx512f")
#define VL 8
#define SIMD(name) name##_avx512f
#define SIMD_NAME "avx512f"
#include "_bank_simd.h"
#undef VL
#undef SIMD
#undef SIMD_NAME
#pragma GCC pop_options
#pragma GCC push_options
#pragma GCC target("avx2")
#define VL 4
#define SIMD(name) name##_avx2
#define SIMD_NAME "avx2"
#include "_bank_simd.h"
#undef VL
#undef SIMD
#undef SIMD_NAME
#pragma GCC pop_options
#endif
#define VL 2 /* x86-64's SSE2, aarch64's NEON */
#define SIMD(name) name##_base
#define SIMD_NAME "base"
#include "_bank_simd.h"
#undef VL
#undef SIMD
#undef SIMD_NAME

/* every copy, widest first */
static const Simd *const simd_tables[] = {
#ifdef SIMD_X86
    &table_avx512f, &table_avx2,
#endif
    &table_base};
#define N_SIMD ((int)(sizeof simd_tables / sizeof simd_tables[0]))

static const Simd *simd = &table_base; /* the copy in use */

/* whether this CPU runs copy t */
static int simd_runs(const Simd *t)
{
#ifdef SIMD_X86
    __builtin_cpu_init();
    if (t == &table_avx512f)
        return __builtin_cpu_supports("avx512f");
    if (t == &table_avx2)
        return __builtin_cpu_supports("avx2");
#endif
    return t == &table_base;
}

/* prefetch bytes from p into the caches (for writing when write) */
static inline void prefetch(const void *p, size_t bytes, int write)
{
    const char *c = p;
    for (size_t o = 0; o < bytes; o += 64) {
        if (write)
            __builtin_prefetch(c + o, 1, 3);
        else
            __builtin_prefetch(c + o, 0, 3);
    }
}

/* Elements of the scratch array "work": the exponents of every learner's kernel rows, or of
 * one learner's window column. */
static Py_ssize_t work_size(const Dims *D)
{
    const Py_ssize_t a = (Py_ssize_t)D->K * D->c * D->mp, b = (Py_ssize_t)D->c * D->P;
    return a > b ? a : b;
}

static const double *Ki_(const double *kinv, int k, Py_ssize_t mp)
{
    return kinv + (size_t)k * mp * mp;
}

/* ------------------------------------------------------------------ update */

/* x <- L^-1 x and, with two, y <- L^-1 y, by forward substitution (L (n, n) lower triangular,
 * row-major): x_p <- (x_p - sum_{q<p} L_pq x_q) / L_pp, the arithmetic of lower_solve_rows
 * with one right-hand side, the two solves interleaved (two independent chains) */
static void lower_solve_two(const double *restrict L, int n, double *restrict x,
                            double *restrict y, int two)
{
    for (int p = 0; p < n; p++) {
        const double *lp = L + (size_t)p * n;
        double ax = x[p], ay = two ? y[p] : 0.0;
        for (int q = 0; q < p; q++) {
            ax -= lp[q] * x[q];
            ay -= lp[q] * y[q];
        }
        x[p] = ax / lp[p];
        if (two)
            y[p] = ay / lp[p];
    }
}

/* Prefetch what the window step of learner k reads and writes (its K_oo^-1, [r, S], the
 * slot's kernel row and its column of the window's inputs): the 21 learners' state, ~0.5 MB,
 * is out of the caches between control steps, and the hardware prefetchers do not run ahead
 * across these many short arrays. */
static inline void prefetch_learner(const Dims *D, int k, int slot, const double *kinv,
                                    const double *stats, const double *wk, const double *wxt,
                                    const double *wubt)
{
    const size_t mp = (size_t)D->mp, b = (size_t)D->b, c = (size_t)D->c, P = (size_t)D->P;
    prefetch(kinv + k * mp * mp, sizeof(double) * mp * mp, 0);
    prefetch(stats + k * mp * (mp + 1), sizeof(double) * mp * (mp + 1), 1);
    prefetch(wk + (k * P + (size_t)slot) * mp, sizeof(double) * mp, 1);
    for (size_t d = 0; d < b; d++)
        __builtin_prefetch(wxt + (k * b + d) * P + (size_t)slot, 1, 3);
    for (size_t i = 0; i < c; i++)
        __builtin_prefetch(wubt + (k * c + i) * P + (size_t)slot, 1, 3);
}

/* ------------------------------------------------------------------ the bank's state */

/* The arrays of an AFVSGPBank the entry points read and write (its attributes, see
 * AFVSGPBank._core_state), taken once: the State holds their buffers while it lives, their
 * sizes checked against the dims when it is made, and the bank's constant settings. update,
 * predict, candidate and install take it in place of the arrays; the bank makes a new one
 * whenever it allocates new arrays (never in a step). */
enum { S_INDXT, S_LOGVAR, S_IL2, S_UBT, S_VAR, S_KOOINV, S_STATS, S_SCALE, S_WK, S_WZ, S_WXT,
       S_WUBT, S_KNEW, S_KSS, S_RESID, S_WORK, S_HEAD, S_COUNT, S_SEEN, S_FRESH, S_SINCE,
       S_NOISE, S_LOO, S_LSL, S_WHITE, S_LD, S_CVEC, S_INDUB, S_KOO, S_NADD, S_NREM, S_POWREV,
       S_N };

static const Spec state_spec[S_N] = {
    {"ind_xit", 'd', 1},  {"log_var", 'd', 0},   {"inv_ls2", 'd', 0}, {"ubt", 'd', 1},
    {"var", 'd', 0},      {"koo_inv", 'd', 1},   {"stats", 'd', 1},   {"scale", 'd', 1},
    {"wk", 'd', 1},       {"wz", 'd', 1},        {"wxt", 'd', 1},     {"wubt", 'd', 1},
    {"k_new", 'd', 1},    {"kss", 'd', 1},       {"resid", 'd', 1},   {"work", 'd', 1},
    {"head", 'q', 1},     {"count", 'q', 1},     {"n_seen", 'q', 1},  {"fresh", '?', 1},
    {"since", 'q', 1},    {"noise_variance", 'd', 0}, {"l_oo", 'd', 1}, {"lsl", 'd', 1},
    {"white", '?', 1},    {"l_d", 'd', 1},       {"cvec", 'd', 1},    {"ind_ub", 'd', 1},
    {"koo", 'd', 1},      {"n_added", 'q', 1},   {"n_removed", 'q', 1}, {"pow_rev", 'd', 0}};

typedef struct {
    PyObject_HEAD
    Dims D;
    double inv_phi, phi_p, add_floor, swap_margin; /* 1/phi, phi^P, eq. 27's floor, eq. 28 */
    long long refresh_every;
    int held; /* the buffers are taken */
    Py_buffer bf[S_N];
} State;

static void state_dealloc(State *st)
{
    if (st->held)
        release_all(st->bf, S_N);
    Py_TYPE(st)->tp_free((PyObject *)st);
}

static PyTypeObject StateType = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "afvsgp_gym.gp._bank.State",
    .tp_basicsize = sizeof(State),
    .tp_dealloc = (destructor)state_dealloc,
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "An AFVSGPBank's arrays and settings, taken once (made by state())."};

/* state(dims, arrays, (inv_phi, phi_p, add_floor, swap_margin, refresh_every)) -> State:
 * arrays maps the names of state_spec to the bank's arrays (each C-contiguous, of its dtype
 * and size; ValueError naming the first that is not, or a name missing or unknown). */
static PyObject *py_state(PyObject *self, PyObject *args)
{
    Dims D;
    PyObject *arrays;
    double inv_phi, phi_p, add_floor, swap_margin;
    long long refresh_every;
    if (!PyArg_ParseTuple(args, "(iiiii)O!(ddddL)", &D.K, &D.b, &D.c, &D.mp, &D.P, &PyDict_Type,
                          &arrays, &inv_phi, &phi_p, &add_floor, &swap_margin, &refresh_every))
        return NULL;
    const Py_ssize_t K = D.K, b = D.b, c = D.c, mp = D.mp, P = D.P;
    if (K < 1 || b < 1 || b > MAXB || c < 1 || mp < 1 || mp + c + 1 > MAXW || P < 1) {
        PyErr_SetString(PyExc_ValueError, "dims must be positive (b <= 1024, Mp + c < 4096)");
        return NULL;
    }
    if (PyDict_Size(arrays) != S_N) {
        PyErr_Format(PyExc_ValueError, "arrays must hold the %d arrays of the bank's state. "
                     "Got: %zd", S_N, PyDict_Size(arrays));
        return NULL;
    }
    const Py_ssize_t size[S_N] = {
        K * b * mp, K * c, K * c * b, K * c * mp, K * c, K * mp * mp, K * mp * (mp + 1), K,
        K * P * mp, K * P, K * b * P, K * c * P, K * mp, K, K, work_size(&D), K, K, K, K, K,
        K, K * mp * mp, K * mp * mp, K, K * mp * mp, K * mp, K * mp * c, K * mp * mp, K, K, P};
    PyObject *o[S_N];
    for (int i = 0; i < S_N; i++) {
        o[i] = PyDict_GetItemString(arrays, state_spec[i].name); /* borrowed */
        if (o[i] == NULL) {
            PyErr_Format(PyExc_ValueError, "arrays has no %s", state_spec[i].name);
            return NULL;
        }
    }
    State *st = PyObject_New(State, &StateType);
    if (st == NULL)
        return NULL;
    st->held = 0;
    if (take_all(o, st->bf, state_spec, size, S_N) < 0) {
        Py_DECREF(st);
        return NULL;
    }
    st->held = 1;
    st->D = D;
    st->inv_phi = inv_phi;
    st->phi_p = phi_p;
    st->add_floor = add_floor;
    st->swap_margin = swap_margin;
    st->refresh_every = refresh_every;
    return (PyObject *)st;
}

/* The window step of every learner, all at one ring position (eqs. 24-26), for finite
 * samples: with kt of the new sample, k_new = ubar' Kt, k_ss = s . ubar^2; scale <- scale /
 * phi; [r, S] += scale (k_new [z, k_new'] - phi^P k_old [z_old, k_old']) (k_old, z_old the
 * slot's sample when the window is full); the slot <- the new sample; head, count, n_seen,
 * since advance; the whitened statistics A = L^-1 S L^-T (lsl) of a learner predicted since
 * its last update (white and fresh) follow, A += scale (l l' - phi^P l_old l_old') with l =
 * L^-1 k_new, l_old = L^-1 k_old, and white is cleared for the others; fresh is cleared;
 * resid = k_ss - k_new' K_oo^-1 k_new (eq. 27). Returns
 * (code, candidates, best, refresh due, renormalisation due): the number of learners whose
 * resid exceeds max(add_floor k_ss, s2), the one of them with the largest resid / k_ss (the
 * first if tied; -1 for none), whether some since reached refresh_every, some scale 1e100.
 * Code NOT_FINITE or OVERFLOW: nothing changed. */
static PyObject *py_update(PyObject *self, PyObject *args)
{
    enum { XI, UB, Z, N };
    static const Spec spec[N] = {{"xi", 'd', 0}, {"ub", 'd', 0}, {"z", 'd', 0}};
    PyObject *o[N];
    Py_buffer bf[N];
    State *state;
    if (!PyArg_ParseTuple(args, "O!OOO", &StateType, &state, &o[0], &o[1], &o[2]))
        return NULL;
    const Dims D = state->D;
    const Py_ssize_t K = D.K, b = D.b, c = D.c, mp = D.mp, P = D.P;
    const double inv_phi = state->inv_phi, phi_p = state->phi_p, add_floor = state->add_floor;
    const long long refresh_every = state->refresh_every;
    const Py_ssize_t size[N] = {K * b, c, K};
    if (take_all(o, bf, spec, size, N) < 0)
        return NULL;
    Py_buffer *sb = state->bf;
    const double *oxt = sb[S_INDXT].buf, *lvar = sb[S_LOGVAR].buf, *il2 = sb[S_IL2].buf;
    const double *ubt = sb[S_UBT].buf, *var = sb[S_VAR].buf, *kinv = sb[S_KOOINV].buf;
    const double *loo = sb[S_LOO].buf;
    double *lsl = sb[S_LSL].buf;
    char *white = sb[S_WHITE].buf;
    const double *xi = bf[XI].buf;
    const double *ub = bf[UB].buf, *z = bf[Z].buf;
    double *stats = sb[S_STATS].buf, *scale = sb[S_SCALE].buf, *wk = sb[S_WK].buf;
    double *wz = sb[S_WZ].buf, *wxt = sb[S_WXT].buf, *wubt = sb[S_WUBT].buf;
    double *knew = sb[S_KNEW].buf, *kss = sb[S_KSS].buf, *resid = sb[S_RESID].buf;
    double *E = sb[S_WORK].buf;
    long long *head = sb[S_HEAD].buf, *count = sb[S_COUNT].buf, *seen = sb[S_SEEN].buf;
    long long *since = sb[S_SINCE].buf;
    char *fresh = sb[S_FRESH].buf;
    const double *noise = sb[S_NOISE].buf;
    int rc = 0, n_cand = 0, best = -1, refresh_due = 0, renorm_due = 0;
    double total = 0.0, best_rel = 0.0;
    for (Py_ssize_t i = 0; i < K * b; i++)
        total += xi[i];
    for (Py_ssize_t i = 0; i < K; i++)
        total += z[i];
    for (Py_ssize_t i = 0; i < c; i++)
        total += ub[i];
    const int full = count[0] == P;
    const int slot = full ? (int)((head[0] + 1) % P) : (int)count[0];
    if (!isfinite(total))
        rc = NOT_FINITE;
    else if (slot < 0 || slot >= P)
        rc = NOT_FINITE; /* a corrupted ring: leave it to the numpy method */
    /* first every k_new (nothing changes if an exponent overflows) */
    double *sq = PyMem_Malloc(sizeof(double) * (size_t)(b * mp));
    if (sq == NULL) {
        release_all(bf, N);
        return PyErr_NoMemory();
    }
    for (int k = 0; k < D.K && rc == 0; k++) {
        if (k + 1 < D.K)
            prefetch(oxt + (k + 1) * mp * b, sizeof(double) * (size_t)(mp * b), 0);
        rc = simd->exponents(&D, oxt, lvar, il2, k, xi + k * b, E + k * c * mp, sq);
        if (rc == 0)
            simd->vexp(E + k * c * mp, c * mp);
    }
    PyMem_Free(sq);
    for (int k = 0; k < D.K && rc == 0; k++) {
        if (k + 1 < D.K)
            prefetch(ubt + (k + 1) * c * mp, sizeof(double) * (size_t)(c * mp), 0);
        simd->kernel_row(E + k * c * mp, ubt + k * c * mp, ub, (int)c, (int)mp, knew + k * mp);
        double s = 0.0;
        for (int i = 0; i < c; i++)
            s += var[k * c + i] * (ub[i] * ub[i]);
        kss[k] = s;
    }
    for (int k = 0; k < D.K && rc == 0; k++) {
        if (k + 1 < D.K)
            prefetch_learner(&D, k + 1, slot, kinv, stats, wk, wxt, wubt);
        const double s = scale[k] * inv_phi;
        double *ko = wk + (k * P + slot) * mp;
        scale[k] = s;
        const double f = full ? -phi_p * s : 0.0, zo = full ? wz[k * P + slot] * f : 0.0;
        double lk[MAXW], lo[MAXW]; /* L^-1 k_new, L^-1 k_old: the whitened step's vectors */
        const int whiten = white[k] && fresh[k];
        white[k] = (char)whiten;
        if (whiten) {
            const double *Lk = loo + (size_t)k * mp * mp;
            memcpy(lk, knew + k * mp, sizeof(double) * (size_t)mp);
            if (full)
                memcpy(lo, ko, sizeof(double) * (size_t)mp);
            else
                memset(lo, 0, sizeof(double) * (size_t)mp);
            lower_solve_two(Lk, (int)mp, lk, lo, full);
        }
        const double q = simd->window_step(stats + k * mp * (mp + 1), knew + k * mp, ko, s,
                                           z[k] * s, full, f, zo, Ki_(kinv, k, mp), (int)mp);
        if (whiten)
            simd->whitened_step(lsl + (size_t)k * mp * mp, lk, lo, s, full, f, (int)mp);
        wz[k * P + slot] = z[k];
        for (int d = 0; d < b; d++)
            wxt[(k * b + d) * P + slot] = xi[k * b + d];
        for (int i = 0; i < c; i++)
            wubt[(k * c + i) * P + slot] = ub[i];
        resid[k] = kss[k] - q;
        const double floor_ = add_floor * kss[k];
        if (resid[k] > (floor_ > noise[k] ? floor_ : noise[k])) {
            n_cand++;
            if (best < 0 || resid[k] / kss[k] > best_rel) {
                best = k;
                best_rel = resid[k] / kss[k];
            }
        }
        head[k] = slot;
        count[k] += !full;
        seen[k] += 1;
        fresh[k] = 0;
        since[k] += 1;
        refresh_due |= since[k] >= refresh_every;
        renorm_due |= s > 1e100;
    }
    release_all(bf, N);
    return Py_BuildValue("iiiii", rc, n_cand, best, refresh_due, renorm_due);
}

/* ------------------------------------------------------------------ predict */

/* b (n, c) and Sigma (n, c, c) of learners rows at xi (n, b) (eq. 20, whitened): with L =
 * chol(K_oo) (l_oo, lower), G = L^-1 Kt', w = L^-1 r / s2' (s2' = s2 scale); unless fresh,
 * L_D = chol(I + A / s2') is stored (l_d, lower) and fresh set, A = L^-1 S L^-T the whitened
 * statistics (lsl) as update kept them (white), else computed here (two triangular solves of
 * order Mp with Mp right-hand sides), stored and white set; H = L_D^-1 G, cv = L_D^-1 w
 * (stored in cvec); b = H' cv, Sigma = diag(s) - G'G + H'H. */
static PyObject *py_predict(PyObject *self, PyObject *args)
{
    enum { ROWS, XI, BOUT, SOUT, N };
    static const Spec spec[N] = {
        {"rows", 'q', 0}, {"xi", 'd', 0}, {"b_out", 'd', 1}, {"sigma_out", 'd', 1}};
    PyObject *o[N];
    Py_buffer bf[N];
    State *state;
    Py_ssize_t n;
    if (!PyArg_ParseTuple(args, "O!nOOOO", &StateType, &state, &n, &o[0], &o[1], &o[2], &o[3]))
        return NULL;
    const Dims D = state->D;
    const Py_ssize_t K = D.K, b = D.b, c = D.c, mp = D.mp;
    if (n < 0) {
        PyErr_SetString(PyExc_ValueError, "n must be >= 0");
        return NULL;
    }
    const Py_ssize_t size[N] = {n, n * b, n * c, n * c * c};
    if (n * c * mp > work_size(&D))
        return PyLong_FromLong(TOO_MANY_ROWS);
    if (take_all(o, bf, spec, size, N) < 0)
        return NULL;
    Py_buffer *sb = state->bf;
    const double *oxt = sb[S_INDXT].buf, *lvar = sb[S_LOGVAR].buf, *il2 = sb[S_IL2].buf;
    const double *ubt = sb[S_UBT].buf, *var = sb[S_VAR].buf, *loo = sb[S_LOO].buf;
    const double *stats = sb[S_STATS].buf;
    const double *scale = sb[S_SCALE].buf, *noise = sb[S_NOISE].buf, *xi = bf[XI].buf;
    const long long *rows = bf[ROWS].buf;
    double *ld = sb[S_LD].buf, *cvec = sb[S_CVEC].buf, *bout = bf[BOUT].buf;
    double *sout = bf[SOUT].buf;
    char *fresh = sb[S_FRESH].buf, *white = sb[S_WHITE].buf;
    double *lsl = sb[S_LSL].buf;
    for (Py_ssize_t j = 0; j < n; j++) {
        if (rows[j] < 0 || rows[j] >= K) {
            release_all(bf, N);
            PyErr_Format(PyExc_ValueError, "rows must lie in [0, %zd)", K);
            return NULL;
        }
    }
    const int ncol = (int)(mp + c + 1);
    double *work = PyMem_Malloc(
        sizeof(double) * (size_t)(mp * ncol + mp * mp + c * c + (c + 1) * (c + 1) + b * mp));
    if (work == NULL) {
        release_all(bf, N);
        return PyErr_NoMemory();
    }
    double *gg = work + mp * ncol + mp * mp, *E = sb[S_WORK].buf;
    double *sq = gg + c * c + (c + 1) * (c + 1);
    int m_ = (int)mp, info = 0, rc = 0;
    char L = 'L';
    for (Py_ssize_t j = 0; j < n && rc == 0; j++) {
        rc = simd->exponents(&D, oxt, lvar, il2, (int)rows[j], xi + j * b, E + j * c * mp, sq);
        if (rc == 0)
            simd->vexp(E + j * c * mp, c * mp);
    }
    for (Py_ssize_t j = 0; j < n && rc == 0; j++) {
        const int k = (int)rows[j];
        double *kt = E + j * c * mp;
        const double *Uo = ubt + (size_t)k * c * mp;
        for (int r = 0; r < c * mp; r++)
            kt[r] *= Uo[r];
        const double *st = stats + (size_t)k * mp * (mp + 1);
        double *Lk = (double *)loo + (size_t)k * mp * mp, *LDk = ld + (size_t)k * mp * mp;
        double inv = 1.0 / (noise[k] * scale[k]);
        const int refresh = !fresh[k], whiten = refresh && !white[k];
        /* work (mp, ldb), row-major: row p = [S_p, Kt'_p, r_p / s2'], S only to compute A */
        const int off = whiten ? (int)mp : 0, ldb = off + (int)c + 1;
        double *Bm = work, *X = work + off;
        for (int p = 0; p < mp; p++) {
            double *row = Bm + (size_t)p * ldb;
            if (whiten)
                memcpy(row, st + p * (mp + 1) + 1, sizeof(double) * (size_t)mp);
            for (int i = 0; i < c; i++)
                row[off + i] = kt[i * mp + p];
            row[off + c] = st[p * (mp + 1)] * inv;
        }
        /* L^-1 [S, Kt', r / s2'] (Lk: the row-major lower factor of K_oo) */
        simd->lower_solve_rows(Lk, m_, Bm, ldb, ldb, 1.0);
        if (refresh) {
            /* A = L^-1 S L^-T (the transpose of (L^-1 S)' solved again) unless kept; the
             * Cholesky factor of inv A + I (LAPACK, column-major lower: the buffer read as
             * its transpose) */
            double *Ak = lsl + (size_t)k * mp * mp, *A = work + mp * ncol;
            if (whiten) {
                for (int p = 0; p < mp; p++)
                    for (int q = 0; q < mp; q++)
                        Ak[q * mp + p] = Bm[(size_t)p * ldb + q];
                simd->lower_solve_rows(Lk, m_, Ak, m_, m_, 1.0);
                white[k] = 1;
            }
            for (int p = 0; p < mp * mp; p++)
                A[p] = Ak[p] * inv;
            for (int p = 0; p < mp; p++)
                A[p + p * mp] += 1.0;
            dpotrf_(&L, &m_, A, &m_, &info);
            if (info != 0) {
                rc = NOT_PD;
                break;
            }
            for (int p = 0; p < mp; p++)
                for (int q = 0; q < mp; q++)
                    LDk[p * mp + q] = q <= p ? A[p + q * mp] : 0.0;
            fresh[k] = 1;
        }
        /* G'G before G becomes H */
        simd->gram_rows(X, m_, ldb, (int)c, gg);
        simd->lower_solve_rows(LDk, m_, X, ldb, (int)c + 1, 1.0);
        for (int p = 0; p < mp; p++)
            cvec[(size_t)k * mp + p] = X[(size_t)p * ldb + c];
        double *bj = bout + j * c, *sj = sout + j * c * c;
        /* [H, cv]'[H, cv]: H'H and H'cv (the last column) */
        double *hh = gg + c * c;
        simd->gram_rows(X, m_, ldb, (int)c + 1, hh);
        for (int i = 0; i < c; i++) {
            bj[i] = hh[i * (c + 1) + c];
            for (int l = i; l < c; l++) {
                const double v = hh[i * (c + 1) + l] - gg[i * c + l] +
                                 (i == l ? var[k * c + i] : 0.0);
                sj[i * c + l] = sj[l * c + i] = v;
            }
        }
    }
    PyMem_Free(work);
    release_all(bf, N);
    return PyLong_FromLong(rc);
}

/* ------------------------------------------------------------------ inducing candidate */

/* Learner k's newest sample (x, ubar, k_ss, k_new) as an inducing point (eqs. 27-30), the
 * decision only: lvec = L^-1 k_new[:m], d = k_ss - |lvec|^2; if d <= 1e-6 k_ss, 0. Else the
 * statistics are renormalised (scale 1), col = k(x, window) (slot order), lc = phi^age col,
 * srow = lc' wk[:, :m], s_dd = lc . col, r_new = lc . wz; with a full set (m = Mp), the eq.
 * 28 score of the enlarged set (K_e^-1 by the bordered inverse) names the point to drop,
 * and 0 when the new point does not beat it by swap_margin k_ss. Returns (code, drop, dd,
 * s_dd, r_new): code 1 append, 2 replace point drop, 0 no change; dd = d + jitter. */
static PyObject *py_candidate(PyObject *self, PyObject *args)
{
    enum { XI, UB, KNEW, LVEC, COL, SROW, N };
    static const Spec spec[N] = {{"xi", 'd', 0},   {"ub", 'd', 0},  {"k_new", 'd', 0},
                                 {"lvec", 'd', 1}, {"col", 'd', 1}, {"srow", 'd', 1}};
    PyObject *o[N];
    Py_buffer bf[N];
    State *state;
    int k, m, head, cnt;
    double kss, jitter;
    if (!PyArg_ParseTuple(args, "O!iiiiddOOOOOO", &StateType, &state, &k, &m, &head, &cnt, &kss,
                          &jitter, &o[0], &o[1], &o[2], &o[3], &o[4], &o[5]))
        return NULL;
    const Dims D = state->D;
    const Py_ssize_t K = D.K, b = D.b, c = D.c, mp = D.mp, P = D.P;
    const double swap_margin = state->swap_margin;
    if (k < 0 || k >= K || m < 1 || m > mp || cnt < 1 || cnt > P || head < 0 || head >= cnt) {
        PyErr_SetString(PyExc_ValueError, "k, m, head or count out of range");
        return NULL;
    }
    const Py_ssize_t size[N] = {b, c, mp, mp, P, mp};
    if (take_all(o, bf, spec, size, N) < 0)
        return NULL;
    Py_buffer *sb = state->bf;
    const double *Lk = (const double *)sb[S_LOO].buf + (size_t)k * mp * mp;
    const double *Ki = (const double *)sb[S_KOOINV].buf + (size_t)k * mp * mp;
    double *st = (double *)sb[S_STATS].buf + (size_t)k * mp * (mp + 1);
    double *scale = (double *)sb[S_SCALE].buf + k;
    const double *wk = (const double *)sb[S_WK].buf + (size_t)k * P * mp;
    const double *wz = (const double *)sb[S_WZ].buf + (size_t)k * P;
    const double *wxt = (const double *)sb[S_WXT].buf + (size_t)k * b * P;
    const double *wubt = (const double *)sb[S_WUBT].buf + (size_t)k * c * P;
    const double *L2 = (const double *)sb[S_IL2].buf + (size_t)k * c * b;
    const double *lv = (const double *)sb[S_LOGVAR].buf + (size_t)k * c;
    const double *rev = sb[S_POWREV].buf, *x = bf[XI].buf, *ub = bf[UB].buf;
    const double *kn = bf[KNEW].buf;
    double *lvec = bf[LVEC].buf, *col = bf[COL].buf, *srow = bf[SROW].buf;
    int code = 0, drop = -1;
    double d = 0.0, dd = 0.0, sdd = 0.0, rnew = 0.0;
    double *tmp = NULL;
    /* eq. 27 residual from the factor */
    for (int i = 0; i < m; i++) {
        double s = kn[i];
        for (int j = 0; j < i; j++)
            s -= Lk[i * mp + j] * lvec[j];
        lvec[i] = s / Lk[i * mp + i];
    }
    for (int i = 0; i < m; i++)
        d += lvec[i] * lvec[i];
    d = kss - d;
    if (!(d > 1e-6 * kss))
        goto done;
    if (*scale != 1.0) {
        const double f = 1.0 / *scale;
        for (Py_ssize_t i = 0; i < mp * (mp + 1); i++)
            st[i] *= f;
        *scale = 1.0;
    }
    tmp = PyMem_Malloc(sizeof(double) * (size_t)(3 * (m + 1) * (m + 1) + (m + 1) + cnt));
    if (tmp == NULL) {
        code = NO_MEMORY;
        goto done;
    }
    /* the window column k(x, (xi_t, ub_t)) from the differences: exponents (c, cnt) */
    double *E = sb[S_WORK].buf;
    for (int i = 0; i < c; i++)
        simd->window_exponents(E + (size_t)i * cnt, L2 + i * b, lv[i], x, wxt, (int)b, (int)P,
                               cnt);
    simd->vexp(E, c * cnt);
    for (int t = 0; t < cnt; t++)
        col[t] = 0.0;
    for (int i = 0; i < c; i++)
        simd->add_scaled_product(col, ub[i], E + (size_t)i * cnt, wubt + i * P, cnt);
    /* weights phi^age (age (head - t) mod P), the new row of [r, S] (eq. 30) */
    double *lcs = tmp + 3 * (m + 1) * (m + 1) + (m + 1);
    for (int t = 0; t < cnt; t++) {
        const int age = t <= head ? head - t : head - t + (int)P;
        const double lc = rev[P - 1 - age] * col[t];
        lcs[t] = lc;
        sdd += lc * col[t];
        rnew += lc * wz[t];
    }
    simd->weighted_row_sums(wk, (size_t)mp, lcs, cnt, m, srow);
    dd = d + jitter;
    if (m + 1 > mp) {
        /* eq. 28 on the enlarged set: K_e^-1 = [[K^-1 + w w'/dd, -w/dd], [-w'/dd, 1/dd]] */
        const int n1 = m + 1;
        double *kinv = tmp, *se = kinv + n1 * n1, *prod = se + n1 * n1, *w = prod + n1 * n1;
        simd->symv(Ki, kn, m, w); /* m = Mp here */
        for (int i = 0; i < m; i++) {
            for (int l = 0; l < m; l++) {
                kinv[i * n1 + l] = w[i] * (w[l] / dd) + Ki[i * mp + l];
                se[i * n1 + l] = st[i * (mp + 1) + 1 + l];
            }
            kinv[i * n1 + m] = kinv[m * n1 + i] = -w[i] / dd;
            se[i * n1 + m] = se[m * n1 + i] = srow[i];
        }
        kinv[m * n1 + m] = 1.0 / dd;
        se[m * n1 + m] = sdd;
        /* column-major se' kinv' = (kinv se)': read row-major, prod = kinv se */
        int n1_ = n1;
        double one = 1.0, zero = 0.0;
        char Nn = 'N';
        dgemm_(&Nn, &Nn, &n1_, &n1_, &n1_, &one, se, &n1_, kinv, &n1_, &zero, prod, &n1_);
        double best = 0.0, last = 0.0;
        for (int i = 0; i < n1; i++) {
            double s = 0.0;
            for (int l = 0; l < n1; l++)
                s += prod[i * n1 + l] * kinv[i * n1 + l];
            s /= kinv[i * n1 + i];
            if (i < m && (drop < 0 || s < best)) {
                best = s;
                drop = i;
            }
            if (i == m)
                last = s;
        }
        if (!(last - best > swap_margin * kss)) {
            drop = -1;
            goto done;
        }
        code = 2;
    } else {
        code = 1;
    }
done:
    PyMem_Free(tmp);
    release_all(bf, N);
    if (code == NO_MEMORY)
        return PyErr_NoMemory();
    return Py_BuildValue("iiddd", code, drop, dd, sdd, rnew);
}

/* ------------------------------------------------------------------ inducing set */

/* K_oo^-1 of learner k after an inducing-set change (eqs. 29-30): with refactor, L =
 * chol(K_oo[:m, :m]) (LAPACK) into l_oo first (else l_oo holds it already, e.g. the bordered
 * factor); then K_oo^-1 = L^-T L^-1 into koo_inv[:m, :m] (L^-1 by forward substitution) and
 * fresh[k] cleared. NOT_PD (nothing changed) when the factorisation fails. */
/* factor_inverse on learner k's blocks of the stacked koo, l_oo, koo_inv (mp x mp each);
 * 0, NOT_PD (nothing changed) or NO_MEMORY */
static int factor_inverse_k(Py_ssize_t mp, int k, int m, int refactor, const double *koo_all,
                            double *lo_all, double *kinv_all, char *fresh)
{
    const double *koo = koo_all + (size_t)k * mp * mp;
    double *lo = lo_all + (size_t)k * mp * mp;
    double *kinv = kinv_all + (size_t)k * mp * mp;
    double *L = PyMem_Malloc(sizeof(double) * 3 * (size_t)m * m);
    if (L == NULL)
        return NO_MEMORY;
    double *X = L + (size_t)m * m, *g = X + (size_t)m * m;
    int rc = 0;
    for (int i = 0; i < m; i++)
        for (int j = 0; j < m; j++)
            L[i * m + j] = refactor ? koo[i * mp + j] : (j <= i ? lo[i * mp + j] : 0.0);
    if (refactor) {
        /* the row-major block read as column-major is the same symmetric matrix: its "U"
         * factor, read row-major, is the lower L */
        char uplo = 'U';
        int n = m, info = 0;
        dpotrf_(&uplo, &n, L, &n, &info);
        if (info != 0)
            rc = NOT_PD;
        for (int i = 0; i < m && rc == 0; i++)
            for (int j = i + 1; j < m; j++)
                L[i * m + j] = 0.0;
    }
    if (rc == 0) {
        for (int i = 0; i < m * m; i++)
            X[i] = 0.0;
        for (int i = 0; i < m; i++)
            X[i * m + i] = 1.0;
        simd->lower_solve_rows(L, m, X, m, m, 1.0); /* X = L^-1 */
        simd->gram_rows(X, m, m, m, g);             /* g = X' X */
        for (int i = 0; i < m; i++) {
            memcpy(kinv + (size_t)i * mp, g + (size_t)i * m, sizeof(double) * (size_t)m);
            if (refactor)
                memcpy(lo + (size_t)i * mp, L + (size_t)i * m, sizeof(double) * (size_t)m);
        }
        fresh[k] = 0;
    }
    PyMem_Free(L);
    return rc;
}

static PyObject *py_factor_inverse(PyObject *self, PyObject *args)
{
    enum { KOO, LOO, KINV, FRESH, N };
    static const Spec spec[N] = {{"koo", 'd', 0}, {"l_oo", 'd', 1}, {"koo_inv", 'd', 1},
                                 {"fresh", '?', 1}};
    PyObject *o[N];
    Py_buffer bf[N];
    Dims D;
    int k, m, refactor;
    if (!PyArg_ParseTuple(args, "(iiiii)iipOOOO", &D.K, &D.b, &D.c, &D.mp, &D.P, &k, &m,
                          &refactor, &o[0], &o[1], &o[2], &o[3]))
        return NULL;
    if (D.K < 1 || D.mp < 1 || D.mp > MAXW || k < 0 || k >= D.K || m < 1 || m > D.mp) {
        PyErr_SetString(PyExc_ValueError, "k and m must index the bank");
        return NULL;
    }
    const Py_ssize_t mp = D.mp, K = D.K;
    const Py_ssize_t size[N] = {K * mp * mp, K * mp * mp, K * mp * mp, K};
    if (take_all(o, bf, spec, size, N) < 0)
        return NULL;
    const int rc = factor_inverse_k(mp, k, m, refactor, bf[KOO].buf, bf[LOO].buf,
                                    bf[KINV].buf, bf[FRESH].buf);
    release_all(bf, N);
    if (rc == NO_MEMORY)
        return PyErr_NoMemory();
    return PyLong_FromLong(rc);
}

/* Learner k's newest sample installed as inducing point pos (eqs. 29-30;
 * AFVSGPBank._install, whose numpy statements these are, copies only): with m points before
 * and mm after (append: pos = m, mm = m + 1; replace: pos < m, mm = m), krow = k_new[:m] with
 * kss_jit at pos, srow[:m] with s_dd at pos; ind_xit[k, :, pos] = xi, ind_ub[k, pos] = ub,
 * ubt[k, :, pos] = ub, K_oo's row and column pos <- krow, [r, S]'s row pos <- [r_new, srow]
 * and column pos + 1 <- srow, wk[k, :count, pos] = col, with append the bordered factor's row
 * pos <- [lvec, sqrt(dd)]; n_added[k] (and with replace n_removed[k]) + 1; then
 * factor_inverse (refactor with replace). Returns 0, or NOT_PD (the copies made, the factor
 * and inverse unchanged: the caller refactors with jitter). */
static PyObject *py_install(PyObject *self, PyObject *args)
{
    enum { XI, UB, KNEW, SROW, COL, LVEC, N };
    static const Spec spec[N] = {{"xi", 'd', 0},   {"ub", 'd', 0},  {"k_new", 'd', 0},
                                 {"srow", 'd', 0}, {"col", 'd', 0}, {"lvec", 'd', 0}};
    PyObject *o[N];
    Py_buffer bf[N];
    State *state;
    int k, m, pos, replace, cnt;
    double kss_jit, sdd, rnew, dd;
    if (!PyArg_ParseTuple(args, "O!iiipiddddOOOOOO", &StateType, &state, &k, &m, &pos,
                          &replace, &cnt, &kss_jit, &sdd, &rnew, &dd, &o[0], &o[1], &o[2],
                          &o[3], &o[4], &o[5]))
        return NULL;
    const Dims D = state->D;
    const Py_ssize_t K = D.K, b = D.b, c = D.c, mp = D.mp, P = D.P;
    if (k < 0 || k >= K || m < 0 || m > mp || cnt < 1 || cnt > P ||
        (replace ? pos < 0 || pos >= m : pos != m || m >= mp)) {
        PyErr_SetString(PyExc_ValueError, "k, m, pos or count out of range");
        return NULL;
    }
    const int mm = replace ? m : m + 1;
    const Py_ssize_t size[N] = {b, c, mp, m, cnt, m};
    if (take_all(o, bf, spec, size, N) < 0)
        return NULL;
    Py_buffer *sb = state->bf;
    const double *xi = bf[XI].buf, *ub = bf[UB].buf, *kn = bf[KNEW].buf, *srow = bf[SROW].buf;
    const double *col = bf[COL].buf, *lvec = bf[LVEC].buf;
    double *xt = (double *)sb[S_INDXT].buf + (size_t)k * b * mp;
    double *iu = (double *)sb[S_INDUB].buf + (size_t)k * mp * c;
    double *U = (double *)sb[S_UBT].buf + (size_t)k * c * mp;
    double *koo = (double *)sb[S_KOO].buf + (size_t)k * mp * mp;
    double *st = (double *)sb[S_STATS].buf + (size_t)k * mp * (mp + 1);
    double *wk = (double *)sb[S_WK].buf + (size_t)k * P * mp;
    double *lo = (double *)sb[S_LOO].buf + (size_t)k * mp * mp;
    long long *nadd = sb[S_NADD].buf, *nrem = sb[S_NREM].buf;
    nadd[k] += 1;
    if (replace)
        nrem[k] += 1;
    for (Py_ssize_t d = 0; d < b; d++)
        xt[d * mp + pos] = xi[d];
    for (Py_ssize_t i = 0; i < c; i++) {
        iu[(size_t)pos * c + i] = ub[i];
        U[i * mp + pos] = ub[i];
    }
    for (int q = 0; q < mm; q++) {
        const double kq = q == pos ? kss_jit : kn[q], sq = q == pos ? sdd : srow[q];
        koo[(size_t)pos * mp + q] = kq;
        koo[(size_t)q * mp + pos] = kq;
        st[(size_t)pos * (mp + 1) + 1 + q] = sq;
        st[(size_t)q * (mp + 1) + pos + 1] = sq;
    }
    st[(size_t)pos * (mp + 1)] = rnew;
    for (int t = 0; t < cnt; t++)
        wk[(size_t)t * mp + pos] = col[t];
    if (!replace) {
        for (int q = 0; q < pos; q++)
            lo[(size_t)pos * mp + q] = lvec[q];
        lo[(size_t)pos * mp + pos] = sqrt(dd);
    }
    const int rc = factor_inverse_k(mp, k, mm, replace, koo - (size_t)k * mp * mp,
                                    sb[S_LOO].buf, sb[S_KOOINV].buf, sb[S_FRESH].buf);
    release_all(bf, N);
    if (rc == NO_MEMORY)
        return PyErr_NoMemory();
    return PyLong_FromLong(rc);
}

/* ------------------------------------------------------------------ module */

/* x <- exp(x) in place by the copy in use (for the tests of vexp against high precision). */
static PyObject *py_vexp(PyObject *self, PyObject *args)
{
    PyObject *o;
    Py_buffer bf;
    static const Spec spec = {"x", 'd', 1};
    if (!PyArg_ParseTuple(args, "O", &o) || take(o, &bf, &spec, -1) < 0)
        return NULL;
    simd->vexp(bf.buf, bf.len / (Py_ssize_t)sizeof(double));
    PyBuffer_Release(&bf);
    Py_RETURN_NONE;
}

/* The copies of the hot loops this CPU runs (widest first), and with a name, the one to use. */
static PyObject *py_simd(PyObject *self, PyObject *args)
{
    const char *name = NULL;
    if (!PyArg_ParseTuple(args, "|z", &name))
        return NULL;
    PyObject *names = PyList_New(0);
    if (names == NULL)
        return NULL;
    const Simd *chosen = NULL;
    for (int i = 0; i < N_SIMD; i++) {
        if (!simd_runs(simd_tables[i]))
            continue;
        PyObject *u = PyUnicode_FromString(simd_tables[i]->name);
        if (u == NULL || PyList_Append(names, u) < 0) {
            Py_XDECREF(u);
            Py_DECREF(names);
            return NULL;
        }
        Py_DECREF(u);
        if (name != NULL && strcmp(name, simd_tables[i]->name) == 0)
            chosen = simd_tables[i];
    }
    if (name != NULL && chosen == NULL) {
        PyErr_Format(PyExc_ValueError, "simd: %R is not one of this CPU's copies %R",
                     PyTuple_GetItem(args, 0), names);
        Py_DECREF(names);
        return NULL;
    }
    if (chosen != NULL)
        simd = chosen;
    PyObject *out = Py_BuildValue("(sN)", simd->name, PyList_AsTuple(names));
    Py_DECREF(names);
    return out;
}

static void *capi(const char *module, const char *name)
{
    PyObject *mod = PyImport_ImportModule(module);
    if (mod == NULL)
        return NULL;
    PyObject *table = PyObject_GetAttrString(mod, "__pyx_capi__");
    Py_DECREF(mod);
    if (table == NULL)
        return NULL;
    PyObject *cap = PyDict_GetItemString(table, name); /* borrowed */
    void *fn = NULL;
    if (cap == NULL)
        PyErr_Format(PyExc_ImportError, "%s has no %s", module, name);
    else
        fn = PyCapsule_GetPointer(cap, PyCapsule_GetName(cap));
    Py_DECREF(table);
    return fn;
}

static PyMethodDef methods[] = {
    {"state", py_state, METH_VARARGS,
     "state(dims, arrays, (inv_phi, phi_p, add_floor, swap_margin, refresh_every)) -> State: "
     "the bank's arrays (a dict by name: ind_xit, log_var, inv_ls2, ubt, var, koo_inv, stats, "
     "scale, wk, wz, wxt, wubt, k_new, kss, resid, work, head, count, n_seen, fresh, since, "
     "noise_variance, l_oo, lsl, white, l_d, cvec, ind_ub, koo, n_added, n_removed, pow_rev) "
     "taken once, and its settings."},
    {"update", py_update, METH_VARARGS,
     "update(state, xi, ub, z) -> (code, candidates, best candidate, refresh due, "
     "renormalisation due): the window step of every learner at their shared ring position "
     "(code 0), or a negative code (nothing changed)."},
    {"predict", py_predict, METH_VARARGS,
     "predict(state, n, rows, xi, b_out, sigma_out) -> int: eq. 20 for learners rows (0), or "
     "a negative code (the numpy method takes over)."},
    {"candidate", py_candidate, METH_VARARGS,
     "candidate(state, k, m, head, count, kss, jitter, xi, ub, k_new, lvec, col, srow) -> "
     "(code, drop, dd, s_dd, r_new): the eqs. 27-28 decision on a new inducing point."},
    {"factor_inverse", py_factor_inverse, METH_VARARGS,
     "factor_inverse(dims, k, m, refactor, koo, l_oo, koo_inv, fresh) -> int: L = "
     "chol(K_oo) of learner k into l_oo (with refactor) and K_oo^-1 into koo_inv (0), or "
     "NOT_PD (nothing changed)."},
    {"install", py_install, METH_VARARGS,
     "install(state, k, m, pos, replace, count, kss_jit, s_dd, r_new, dd, xi, ub, k_new, srow, "
     "col, lvec) -> int: learner k's new inducing point in slot pos and K_oo^-1 (0), or "
     "NOT_PD (the copies made, the factor and inverse unchanged)."},
    {"vexp", py_vexp, METH_VARARGS,
     "vexp(x) -> None: x <- exp(x) in place (a C-contiguous, writable float64 array), as the "
     "core computes its kernels' exponentials."},
    {"simd", py_simd, METH_VARARGS,
     "simd([name]) -> (in use, available): the copy of the hot loops in use ('avx512f', "
     "'avx2' or 'base') and the ones this CPU runs, widest first; with a name, use that one "
     "(the same arithmetic in each: it changes the speed only)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_bank",
                                    "Compiled core of afvsgp_gym.gp.afvsgp_bank.", -1, methods};

PyMODINIT_FUNC PyInit__bank(void)
{
    dgemm_ = (gemm_t)capi("scipy.linalg.cython_blas", "dgemm");
    if (dgemm_ == NULL)
        return NULL;
    dpotrf_ = (potrf_t)capi("scipy.linalg.cython_lapack", "dpotrf");
    if (dpotrf_ == NULL)
        return NULL;
    for (int i = N_SIMD - 1; i >= 0; i--)
        if (simd_runs(simd_tables[i]))
            simd = simd_tables[i];
    if (PyType_Ready(&StateType) < 0)
        return NULL;
    PyObject *m = PyModule_Create(&module);
    if (m == NULL)
        return NULL;
    Py_INCREF(&StateType);
    if (PyModule_AddObject(m, "State", (PyObject *)&StateType) < 0) {
        Py_DECREF(&StateType);
        Py_DECREF(m);
        return NULL;
    }
    /* how update and predict take the inducing inputs: (K, b, Mp), by dimension */
    if (m != NULL && PyModule_AddStringConstant(m, "INDUCING_INPUTS", "by dimension") < 0) {
        Py_DECREF(m);
        return NULL;
    }
    /* update and predict keep the whitened statistics (the state's lsl, white) */
    if (m != NULL && PyModule_AddIntConstant(m, "WHITENED_STATISTICS", 1) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    /* the calling convention afvsgp_gym._compiled expects: 2, the bank's arrays in a State */
    if (PyModule_AddIntConstant(m, "ABI", 2) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
