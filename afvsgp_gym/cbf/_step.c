/* The safety controller's per-step arithmetic on the learners' predictions, compiled.
 *
 * The compiled core of afvsgp_gym.cbf.controller.cone_matrices and
 * afvsgp_gym.cbf.exploration.exploration_scale (their docstrings state the formulas): for
 * each barrier predicted, the cone matrix G = beta U of paper eq. 05 from the eq. 51
 * covariance (U'U = (Sigma + Sigma')/2, Cholesky), and the online exploration's gate and
 * scale. Small and dense (m + 1 <= MAXC), row-major float64; the numpy versions are the
 * reference and take over when a factorisation fails.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>

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

static PyMethodDef methods[] = {
    {"cone_factors", py_cone_factors, METH_VARARGS,
     "cone_factors(n, c, sigma, beta, out) -> int: out[r] = beta U_r with U_r'U_r = "
     "(sigma[r] + sigma[r]')/2 (upper triangular) for the (n, c, c) stacks; 0, or -1 when "
     "one is not numerically positive definite (out then partly written)."},
    {"exploration_scale", py_exploration_scale, METH_VARARGS,
     "exploration_scale(n, m, sigma, a0, a, u_nom, low, high, noise_std, half_range, "
     "threshold, reach) -> float: the largest relative gain uncertainty among the gated "
     "barriers, -1.0 when none is gated (NaN if one is NaN)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_step",
                                    "Compiled core of the safety controller's per-step "
                                    "arithmetic on the learners' predictions.", -1, methods};

PyMODINIT_FUNC PyInit__step(void) { return PyModule_Create(&module); }
