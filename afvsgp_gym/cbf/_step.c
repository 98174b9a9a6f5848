/* The safety controller's per-step arithmetic on the learners' predictions, compiled.
 *
 * The compiled core of afvsgp_gym.cbf.controller.cone_matrices and
 * afvsgp_gym.cbf.exploration.exploration_scale (their docstrings state the formulas): for
 * each barrier predicted, the cone matrix G = beta U of paper eq. 05 from the eq. 51
 * covariance (U'U = (Sigma + Sigma')/2, Cholesky), and the online exploration's gate and
 * scale; and the step's glue: the barriers in the cone program, the learned terms added to
 * the constraints, the eq. 48 samples, the residual observer (the same digits as their numpy
 * versions). Small and dense (m + 1 <= MAXC), row-major float64; the numpy versions are the
 * reference and take over when a factorisation fails or a term is not finite.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <string.h>

#include "../_cbuf.h"

#define MAXC 17 /* m + 1: the action dimension plus one */

/* out = beta U with U'U = (S + S')/2 (U upper triangular, zeros below) for the (c, c) S;
 * 0, or -1 when a pivot is not positive (or NaN) */
static int cone_factor(const double *S, int c, double beta, double *out)
{
    double U[MAXC][MAXC];
    for (int i = 0; i < c; i++) {
        double d = S[i * c + i];
        for (int k = 0; k < i; k++)
            d -= U[k][i] * U[k][i];
        if (!(d > 0.0))
            return -1;
        const double p = sqrt(d);
        U[i][i] = p;
        for (int j = i + 1; j < c; j++) {
            double x = 0.5 * (S[i * c + j] + S[j * c + i]);
            for (int k = 0; k < i; k++)
                x -= U[k][i] * U[k][j];
            U[i][j] = x / p;
        }
    }
    for (int i = 0; i < c; i++)
        for (int j = 0; j < c; j++)
            out[i * c + j] = j < i ? 0.0 : beta * U[i][j];
    return 0;
}

static PyObject *py_cone_factors(PyObject *self, PyObject *args)
{
    PyObject *o[2];
    Py_buffer b[2];
    int n, c;
    double beta;
    if (!PyArg_ParseTuple(args, "iiOdO", &n, &c, &o[0], &beta, &o[1]))
        return NULL;
    if (n < 0 || c < 1 || c > MAXC) {
        PyErr_Format(PyExc_ValueError, "sigma must be (n, c, c) with 1 <= c <= %d", MAXC);
        return NULL;
    }
    static const Spec spec[2] = {{"sigma", 'd', 0}, {"out", 'd', 1}};
    const Py_ssize_t size[2] = {(Py_ssize_t)n * c * c, (Py_ssize_t)n * c * c};
    if (take_all(o, b, spec, size, 2) < 0)
        return NULL;
    int rc = 0;
    for (int r = 0; r < n && rc == 0; r++)
        rc = cone_factor((const double *)b[0].buf + (size_t)r * c * c, c, beta,
                         (double *)b[1].buf + (size_t)r * c * c);
    release_all(b, 2);
    return PyLong_FromLong(rc);
}

/* The online exploration's scale (exploration.exploration_scale): with u = clip(u_nom) and
 * ubar = [1, u], barrier k is gated when std_k = sqrt(max(ubar' Sigma_k ubar, 0)) >
 * threshold noise_std_k and a0_k + a_k u < reach std_k; the answer is the largest rho_k =
 * sqrt(max(sum_i h_i^2 Sigma_k[1+i, 1+i], 0)) / ||h * a_k|| over the gated barriers (inf
 * for a zero gain, NaN if one is NaN), -1 when none is gated. */
static PyObject *py_exploration_scale(PyObject *self, PyObject *args)
{
    enum { SIG, A0, A, U, LOW, HIGH, NOISE, HALF, N };
    static const Spec spec[N] = {{"sigma", 'd', 0}, {"a0", 'd', 0},   {"a", 'd', 0},
                                 {"u_nom", 'd', 0}, {"low", 'd', 0},  {"high", 'd', 0},
                                 {"noise_std", 'd', 0}, {"half_range", 'd', 0}};
    PyObject *o[N];
    Py_buffer b[N];
    int n, m;
    double threshold, reach;
    if (!PyArg_ParseTuple(args, "iiOOOOOOOOdd", &n, &m, &o[0], &o[1], &o[2], &o[3], &o[4],
                          &o[5], &o[6], &o[7], &threshold, &reach))
        return NULL;
    if (n < 0 || m < 1 || m + 1 > MAXC) {
        PyErr_Format(PyExc_ValueError, "the action dimension must be in [1, %d]", MAXC - 1);
        return NULL;
    }
    const Py_ssize_t c = m + 1;
    const Py_ssize_t size[N] = {n * c * c, n, (Py_ssize_t)n * m, m, m, m, n, m};
    if (take_all(o, b, spec, size, N) < 0)
        return NULL;
    const double *sig = b[SIG].buf, *a0 = b[A0].buf, *a = b[A].buf, *un = b[U].buf;
    const double *low = b[LOW].buf, *high = b[HIGH].buf, *noise = b[NOISE].buf;
    const double *h = b[HALF].buf;
    double ub[MAXC];
    ub[0] = 1.0;
    for (int j = 0; j < m; j++)
        ub[j + 1] = fmin(fmax(un[j], low[j]), high[j]);
    double best = -1.0;
    int nan = 0;
    for (int k = 0; k < n; k++) {
        const double *S = sig + (size_t)k * c * c, *ak = a + (size_t)k * m;
        double q = 0.0;
        for (int i = 0; i < c; i++) {
            double x = 0.0;
            for (int j = 0; j < c; j++)
                x += S[i * c + j] * ub[j];
            q += x * ub[i];
        }
        const double std = sqrt(q < 0.0 ? 0.0 : q); /* NaN stays NaN */
        double mean = a0[k];
        for (int j = 0; j < m; j++)
            mean += ak[j] * ub[j + 1];
        if (!(std > threshold * noise[k] && mean < reach * std))
            continue;
        double var = 0.0, g2 = 0.0;
        for (int i = 0; i < m; i++) {
            var += S[(i + 1) * c + i + 1] * (h[i] * h[i]);
            const double g = ak[i] * h[i];
            g2 += g * g;
        }
        const double rho = sqrt(var < 0.0 ? 0.0 : var) / sqrt(g2);
        if (isnan(rho))
            nan = 1;
        else if (rho > best)
            best = rho;
    }
    release_all(b, N);
    return PyFloat_FromDouble(nan ? NAN : best);
}

/* ------------------------------------------------------------------ the step's glue
 * Elementwise arithmetic only, in the numpy expressions' order (each operation rounds once,
 * as numpy's does): the controller's results are the same digits with or without these. The
 * products by matrices (BLAS in numpy) stay in numpy. */

/* whether all n doubles at x are finite */
static int all_finite(const double *x, Py_ssize_t n)
{
    for (Py_ssize_t i = 0; i < n; i++)
        if (!isfinite(x[i]))
            return 0;
    return 1;
}

/* The barriers in the cone program (controller.SafetyController._active_rows) when every
 * term is finite: with h = derivs[:, 0], near = min(h, h + derivs[:, 1] / gain) (r > 1) or h,
 * the k with near < activation, ascending, into rows; their number, or -1 (nothing written)
 * when c0, c, derivs or xi holds a value that is not finite. */
static PyObject *py_active_rows(PyObject *self, PyObject *args)
{
    enum { C0, C, D, XI, ROWS, N };
    static const Spec spec[N] = {{"c0", 'd', 0}, {"c", 'd', 0}, {"derivatives", 'd', 0},
                                 {"xi", 'd', 0}, {"rows", 'q', 1}};
    PyObject *o[N];
    Py_buffer b[N];
    int K, m, r, nb;
    double gain, activation;
    if (!PyArg_ParseTuple(args, "iiiiOOOOddO", &K, &m, &r, &nb, &o[C0], &o[C], &o[D], &o[XI],
                          &gain, &activation, &o[ROWS]))
        return NULL;
    if (K < 1 || m < 1 || r < 1 || nb < 0) {
        PyErr_SetString(PyExc_ValueError, "K, m and r must be positive, nb >= 0");
        return NULL;
    }
    const Py_ssize_t size[N] = {K, (Py_ssize_t)K * m, (Py_ssize_t)K * r, (Py_ssize_t)K * nb, K};
    if (take_all(o, b, spec, size, N) < 0)
        return NULL;
    const double *d = b[D].buf;
    long long *rows = b[ROWS].buf;
    int n = -1;
    if (all_finite(b[C0].buf, size[C0]) && all_finite(b[C].buf, size[C]) &&
        all_finite(d, size[D]) && all_finite(b[XI].buf, size[XI])) {
        n = 0;
        for (int k = 0; k < K; k++) {
            const double h = d[(size_t)k * r];
            double near = h;
            if (r > 1) {
                const double ahead = h + d[(size_t)k * r + 1] / gain;
                near = ahead < h ? ahead : h;
            }
            if (near < activation)
                rows[n++] = k;
        }
    }
    release_all(b, N);
    return PyLong_FromLong(n);
}

/* The learned terms of the n predicted barriers of the program (controller.filter): a0[j] +=
 * bvec[j, 0] + bias[rows[j]], a[j] += bvec[j, 1:], and with beta > 0 the cone matrices G[j] =
 * beta U_j (cone_factor of sigma[j]); 0, or -1 when a factor fails (G then partly written,
 * a0 and a updated). */
static PyObject *py_learned_terms(PyObject *self, PyObject *args)
{
    enum { A0, A, BV, BIAS, ROWS, SIG, G, N };
    static const Spec spec[N] = {{"a0", 'd', 1},   {"a", 'd', 1},     {"bvec", 'd', 0},
                                 {"bias", 'd', 0}, {"rows", 'q', 0},  {"sigma", 'd', 0},
                                 {"G", 'd', 1}};
    PyObject *o[N];
    Py_buffer b[N];
    int n, m, K;
    double beta;
    if (!PyArg_ParseTuple(args, "iiiOOOOOOdO", &n, &m, &K, &o[A0], &o[A], &o[BV], &o[BIAS],
                          &o[ROWS], &o[SIG], &beta, &o[G]))
        return NULL;
    if (n < 0 || m < 1 || m + 1 > MAXC || K < 1) {
        PyErr_Format(PyExc_ValueError, "n >= 0, K >= 1 and the action dimension in [1, %d]",
                     MAXC - 1);
        return NULL;
    }
    const Py_ssize_t c = m + 1;
    const Py_ssize_t size[N] = {n, (Py_ssize_t)n * m, n * c, K, n, n * c * c, n * c * c};
    /* G (None without cones) taken only with beta > 0 */
    const int nt = beta > 0.0 ? N : N - 1;
    if (take_all(o, b, spec, size, nt) < 0)
        return NULL;
    double *a0 = b[A0].buf, *a = b[A].buf;
    const double *bv = b[BV].buf, *bias = b[BIAS].buf, *sig = b[SIG].buf;
    const long long *rows = b[ROWS].buf;
    for (int j = 0; j < n; j++) {
        if (rows[j] < 0 || rows[j] >= K) {
            release_all(b, nt);
            PyErr_Format(PyExc_ValueError, "rows must lie in [0, %d)", K);
            return NULL;
        }
    }
    for (int j = 0; j < n; j++) {
        a0[j] += bv[j * c] + bias[rows[j]];
        for (int i = 0; i < m; i++)
            a[(size_t)j * m + i] += bv[j * c + 1 + i];
    }
    int rc = 0;
    if (beta > 0.0)
        for (int j = 0; j < n && rc == 0; j++)
            rc = cone_factor(sig + (size_t)j * c * c, (int)c, beta,
                             (double *)b[G].buf + (size_t)j * c * c);
    release_all(b, nt);
    return PyLong_FromLong(rc);
}

/* The eq. 48 samples of K barriers (measurement.measure_all), given lgu_b = lg_before u and
 * lgu_a = lg_after u: z = (d_a[:, r-1] - d_b[:, r-1]) / dt - 0.5 ((lf_b + lgu_b) + (lf_a +
 * lgu_a)), xi = 0.5 (xi_b + xi_a); returns the number of samples whose z or xi is not
 * finite. */
static PyObject *py_measure(PyObject *self, PyObject *args)
{
    enum { LFB, LGUB, DB, XIB, LFA, LGUA, DA, XIA, XI, Z, N };
    static const Spec spec[N] = {
        {"lf_before", 'd', 0}, {"lgu_before", 'd', 0}, {"derivatives_before", 'd', 0},
        {"xi_before", 'd', 0}, {"lf_after", 'd', 0},   {"lgu_after", 'd', 0},
        {"derivatives_after", 'd', 0}, {"xi_after", 'd', 0}, {"xi_out", 'd', 1},
        {"z_out", 'd', 1}};
    PyObject *o[N];
    Py_buffer b[N];
    int K, r, nb;
    double dt;
    if (!PyArg_ParseTuple(args, "iiidOOOOOOOOOO", &K, &r, &nb, &dt, &o[0], &o[1], &o[2], &o[3],
                          &o[4], &o[5], &o[6], &o[7], &o[8], &o[9]))
        return NULL;
    if (K < 1 || r < 1 || nb < 0) {
        PyErr_SetString(PyExc_ValueError, "K and r must be positive, nb >= 0");
        return NULL;
    }
    const Py_ssize_t Kr = (Py_ssize_t)K * r, Kb = (Py_ssize_t)K * nb;
    const Py_ssize_t size[N] = {K, K, Kr, Kb, K, K, Kr, Kb, Kb, K};
    if (take_all(o, b, spec, size, N) < 0)
        return NULL;
    const double *lfb = b[LFB].buf, *gub = b[LGUB].buf, *db = b[DB].buf, *xb = b[XIB].buf;
    const double *lfa = b[LFA].buf, *gua = b[LGUA].buf, *da = b[DA].buf, *xa = b[XIA].buf;
    double *xi = b[XI].buf, *z = b[Z].buf;
    int bad = 0;
    for (int k = 0; k < K; k++) {
        const double fd = (da[(size_t)k * r + r - 1] - db[(size_t)k * r + r - 1]) / dt;
        const double nominal = 0.5 * ((lfb[k] + gub[k]) + (lfa[k] + gua[k]));
        z[k] = fd - nominal;
        int finite = isfinite(z[k]);
        for (int j = 0; j < nb; j++) {
            const size_t i = (size_t)k * nb + j;
            xi[i] = 0.5 * (xb[i] + xa[i]);
            finite &= isfinite(xi[i]) != 0;
        }
        bad += !finite;
    }
    release_all(b, N);
    return PyLong_FromLong(bad);
}

/* The residual observer's step (residuals.ResidualObserver.update): for the n barriers rows
 * (distinct), e = z[rows[j]] - predicted[j] and, where e is finite, bias[rows[j]] += weight
 * (e - bias[rows[j]]) (weight > 0); every other barrier's bias <- 0. */
static PyObject *py_residual_update(PyObject *self, PyObject *args)
{
    enum { BIAS, ROWS, PRED, Z, N };
    static const Spec spec[N] = {{"bias", 'd', 1}, {"rows", 'q', 0}, {"predicted", 'd', 0},
                                 {"z", 'd', 0}};
    PyObject *o[N];
    Py_buffer b[N];
    int K, n;
    double weight;
    if (!PyArg_ParseTuple(args, "iiOOOOd", &K, &n, &o[0], &o[1], &o[2], &o[3], &weight))
        return NULL;
    if (K < 1 || n < 0 || n > K) {
        PyErr_SetString(PyExc_ValueError, "K must be positive and 0 <= n <= K");
        return NULL;
    }
    const Py_ssize_t size[N] = {K, n, n, K};
    if (take_all(o, b, spec, size, N) < 0)
        return NULL;
    double *bias = b[BIAS].buf;
    const long long *rows = b[ROWS].buf;
    const double *pred = b[PRED].buf, *z = b[Z].buf;
    char keep[4096];
    char *kp = K <= (int)sizeof keep ? keep : PyMem_Malloc((size_t)K);
    if (kp == NULL) {
        release_all(b, N);
        return PyErr_NoMemory();
    }
    memset(kp, 0, (size_t)K);
    for (int j = 0; j < n; j++) {
        if (rows[j] < 0 || rows[j] >= K || kp[rows[j]]) {
            if (kp != keep)
                PyMem_Free(kp);
            release_all(b, N);
            PyErr_Format(PyExc_ValueError, "rows must be distinct and lie in [0, %d)", K);
            return NULL;
        }
        kp[rows[j]] = 1;
    }
    if (weight > 0.0)
        for (int j = 0; j < n; j++) {
            const double e = z[rows[j]] - pred[j];
            if (isfinite(e))
                bias[rows[j]] += weight * (e - bias[rows[j]]);
        }
    for (int k = 0; k < K; k++)
        if (!kp[k])
            bias[k] = 0.0;
    if (kp != keep)
        PyMem_Free(kp);
    release_all(b, N);
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"cone_factors", py_cone_factors, METH_VARARGS,
     "cone_factors(n, c, sigma, beta, out) -> int: out[r] = beta U_r with U_r'U_r = "
     "(sigma[r] + sigma[r]')/2 (upper triangular) for the (n, c, c) stacks; 0, or -1 when "
     "one is not numerically positive definite (out then partly written)."},
    {"exploration_scale", py_exploration_scale, METH_VARARGS,
     "exploration_scale(n, m, sigma, a0, a, u_nom, low, high, noise_std, half_range, "
     "threshold, reach) -> float: the largest relative gain uncertainty among the gated "
     "barriers, -1.0 when none is gated (NaN if one is NaN)."},
    {"active_rows", py_active_rows, METH_VARARGS,
     "active_rows(K, m, r, nb, c0, c, derivatives, xi, gain, activation, rows) -> int: the "
     "barriers in the cone program into rows, their number; -1 when a term is not finite."},
    {"learned_terms", py_learned_terms, METH_VARARGS,
     "learned_terms(n, m, K, a0, a, bvec, bias, rows, sigma, beta, G) -> int: the learned "
     "mean and bias added to the constraints, the cone matrices (beta > 0) into G; 0, or -1 "
     "when a factor fails."},
    {"measure", py_measure, METH_VARARGS,
     "measure(K, r, nb, dt, lf_before, lgu_before, derivatives_before, xi_before, lf_after, "
     "lgu_after, derivatives_after, xi_after, xi_out, z_out) -> int: the eq. 48 samples, and "
     "the number of them that are not finite."},
    {"residual_update", py_residual_update, METH_VARARGS,
     "residual_update(K, n, bias, rows, predicted, z, weight) -> None: the residual "
     "observer's step in place."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_step",
                                    "Compiled core of the safety controller's per-step "
                                    "arithmetic on the learners' predictions.", -1, methods};

PyMODINIT_FUNC PyInit__step(void) { return PyModule_Create(&module); }
