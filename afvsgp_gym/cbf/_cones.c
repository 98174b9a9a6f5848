/* Projection onto a few second-order cones that all bind, and the box (paper eq. 05).
 *
 * The compiled core of afvsgp_gym.cbf.binding_cones (its docstring states the method):
 * Newton's method on the KKT system of
 *
 *     min 1/2 ||u - u_nom||^2  s.t.  c_i(u) = a0_i + a_i u - ||G_i ubar|| = 0 (i < k),
 *                                    u_j on its box face (j fixed),
 *
 * in (u_free, lam), with the Lagrangian's Hessian H = I + sum_i lam_i (B_i'B_i - w_i w_i') /
 * ||v_i|| (B_i = G_i[:, 1:], v_i = G_i ubar, w_i = B_i' v_i / ||v_i||; max(lam_i, 0) in it, so
 * that it stays positive definite) by Cholesky and the k x k Schur complement, inside a
 * primal-dual active set on the box faces (project); and the search of the binding set among
 * a program's cones (solve_set). Dense, small: m <= MAXM actions, k <= MAXK binding cones,
 * K <= MAXC cones in a program. The caller certifies the answer.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <string.h>

#include "../_cbuf.h"

#define MAXM 16
#define MAXK 8
#define MAX_NEWTON 20
#define MAX_FACE_ROUNDS 8
#define NEGATIVE_ITERATES 3 /* Newton gives up on a cone negative this many times running */

/* return codes (0: settled) */
#define APEX -1
#define NO_FREE -2
#define NOT_PD -3
#define SINGULAR -4
#define NOT_FINITE -5
#define NO_CONVERGENCE -6
#define FACES_CYCLE -7
#define NEGATIVE_MULTIPLIER -8
#define FACES_UNSETTLED -9
#define SET_CYCLE -10
#define TOO_MANY_BINDING -11
#define SET_UNSETTLED -12

#define MAXC 64 /* cones of a program (the binding set's search, solve()) */
#define MAX_SET_ROUNDS 16

typedef struct {
    int m, k;      /* actions; cones in the binding set */
    int idx[MAXK]; /* the binding set: indices into the data's cones */
    const double *u_nom, *a0, *a, *G, *low, *high; /* a: (K, m), G: (K, m+1, m+1) row-major */
    const double *BtB; /* (K, m, m): B_i' B_i, B_i = G_i[:, 1:] */
} Problem;

/* v = G_q ubar (m + 1) of cone q at u; returns ||v||^2 */
static double cone_vector(const Problem *P, int q, const double *u, double *v)
{
    const int m = P->m, n1 = m + 1;
    const double *Gq = P->G + (size_t)q * n1 * n1;
    double s2 = 0.0;
    for (int r = 0; r < n1; r++) {
        const double *row = Gq + (size_t)r * n1;
        double x = row[0];
        for (int j = 0; j < m; j++)
            x += row[j + 1] * u[j];
        v[r] = x;
        s2 += x * x;
    }
    return s2;
}

/* c_i, grad c_i, w_i and ||v_i|| at u for the binding set; APEX if some v_i = 0 */
static int terms(const Problem *P, const double *u, double *c, double grad[][MAXM],
                 double w[][MAXM], double *nv)
{
    const int m = P->m, n1 = m + 1;
    for (int i = 0; i < P->k; i++) {
        const int q = P->idx[i];
        const double *Gi = P->G + (size_t)q * n1 * n1, *ai = P->a + (size_t)q * m;
        double v[MAXM + 1];
        const double n = sqrt(cone_vector(P, q, u, v));
        if (!(n > 0.0))
            return APEX;
        nv[i] = n;
        double t = P->a0[q];
        for (int j = 0; j < m; j++) {
            double x = 0.0;
            for (int r = 0; r < n1; r++)
                x += Gi[(size_t)r * n1 + j + 1] * v[r];
            w[i][j] = x / n;
            grad[i][j] = ai[j] - w[i][j];
            t += ai[j] * u[j];
        }
        c[i] = t - n;
    }
    return 0;
}

/* the margin a0_q + a_q u - ||G_q ubar|| of cone q */
static double margin(const Problem *P, int q, const double *u)
{
    const int m = P->m, n1 = m + 1;
    const double *Gq = P->G + (size_t)q * n1 * n1, *aq = P->a + (size_t)q * m;
    double s2 = 0.0, t = P->a0[q];
    for (int r = 0; r < n1; r++) {
        const double *row = Gq + (size_t)r * n1;
        double x = row[0];
        for (int j = 0; j < m; j++)
            x += row[j + 1] * u[j];
        s2 += x * x;
    }
    for (int j = 0; j < m; j++)
        t += aq[j] * u[j];
    return t - sqrt(s2);
}

/* B_q' B_q of cone q into out (m, m) */
static void gram(const Problem *P, int q, double *out)
{
    const int m = P->m, n1 = m + 1;
    const double *Gq = P->G + (size_t)q * n1 * n1;
    for (int p = 0; p < m; p++)
        for (int r = 0; r <= p; r++) {
            double x = 0.0;
            for (int l = 0; l < n1; l++)
                x += Gq[(size_t)l * n1 + p + 1] * Gq[(size_t)l * n1 + r + 1];
            out[p * m + r] = out[r * m + p] = x;
        }
}

/* solve the k x k system S x = S[:, k] by Gaussian elimination with partial pivoting */
static int solve_small(double S[][MAXK + 1], int k, double *x)
{
    for (int p = 0; p < k; p++) {
        int piv = p;
        for (int r = p + 1; r < k; r++)
            if (fabs(S[r][p]) > fabs(S[piv][p]))
                piv = r;
        if (!(fabs(S[piv][p]) > 0.0))
            return SINGULAR;
        if (piv != p)
            for (int q = 0; q <= k; q++) {
                double tmp = S[p][q];
                S[p][q] = S[piv][q];
                S[piv][q] = tmp;
            }
        for (int r = p + 1; r < k; r++) {
            const double f = S[r][p] / S[p][p];
            for (int q = p; q <= k; q++)
                S[r][q] -= f * S[p][q];
        }
    }
    for (int p = k - 1; p >= 0; p--) {
        double y = S[p][k];
        for (int q = p + 1; q < k; q++)
            y -= S[p][q] * x[q];
        x[p] = y / S[p][p];
    }
    return 0;
}

/* Newton's method on the KKT system with the coordinates `fixed` held at their values */
static int newton(const Problem *P, double *u, double *lam, const unsigned char *fixed)
{
    const int m = P->m, k = P->k;
    int F[MAXM], nf = 0;
    for (int j = 0; j < m; j++)
        if (!fixed[j])
            F[nf++] = j;
    if (nf < k)
        return NO_FREE; /* k boundary equations need k free coordinates */
    double c[MAXK], grad[MAXK][MAXM], w[MAXK][MAXM], nv[MAXK];
    int negative = 0; /* consecutive iterates with a negative multiplier */
    for (int it = 0; it < MAX_NEWTON; it++) {
        int rc = terms(P, u, c, grad, w, nv);
        if (rc)
            return rc;
        double H[MAXM][MAXM], X[MAXM][MAXK + 1], s[MAXK];
        for (int i = 0; i < k; i++) /* a negative iterate's curvature left out: H stays > 0 */
            s[i] = fmax(lam[i], 0.0) / nv[i];
        for (int p = 0; p < nf; p++) {
            const int jp = F[p];
            double g = u[jp] - P->u_nom[jp];
            for (int i = 0; i < k; i++)
                g -= lam[i] * grad[i][jp];
            X[p][0] = g; /* the Lagrangian's gradient r1 */
            for (int i = 0; i < k; i++)
                X[p][i + 1] = grad[i][jp];
            for (int q = 0; q <= p; q++) {
                const int jq = F[q];
                double h = (p == q) ? 1.0 : 0.0;
                for (int i = 0; i < k; i++)
                    h += s[i] * (P->BtB[((size_t)P->idx[i] * m + jp) * m + jq] -
                                 w[i][jp] * w[i][jq]);
                H[p][q] = h;
            }
        }
        for (int p = 0; p < nf; p++) { /* H = L L' in the lower triangle */
            double d = H[p][p];
            for (int q = 0; q < p; q++)
                d -= H[p][q] * H[p][q];
            if (!(d > 0.0))
                return NOT_PD;
            d = sqrt(d);
            H[p][p] = d;
            for (int r = p + 1; r < nf; r++) {
                double x = H[r][p];
                for (int q = 0; q < p; q++)
                    x -= H[r][q] * H[p][q];
                H[r][p] = x / d;
            }
        }
        for (int col = 0; col <= k; col++) { /* X = H^-1 [r1, J'] */
            for (int p = 0; p < nf; p++) {
                double x = X[p][col];
                for (int q = 0; q < p; q++)
                    x -= H[p][q] * X[q][col];
                X[p][col] = x / H[p][p];
            }
            for (int p = nf - 1; p >= 0; p--) {
                double x = X[p][col];
                for (int q = p + 1; q < nf; q++)
                    x -= H[q][p] * X[q][col];
                X[p][col] = x / H[p][p];
            }
        }
        double S[MAXK][MAXK + 1], dlam[MAXK]; /* (J H^-1 J') dlam = J H^-1 r1 - c */
        for (int i = 0; i < k; i++) {
            double r = -c[i];
            for (int p = 0; p < nf; p++)
                r += grad[i][F[p]] * X[p][0];
            S[i][k] = r;
            for (int l = 0; l < k; l++) {
                double x = 0.0;
                for (int p = 0; p < nf; p++)
                    x += grad[i][F[p]] * X[p][l + 1];
                S[i][l] = x;
            }
        }
        rc = solve_small(S, k, dlam);
        if (rc)
            return rc;
        double dumax = 0.0, umax = 0.0, dlmax = 0.0, lmax = 0.0;
        for (int p = 0; p < nf; p++) {
            double du = -X[p][0];
            for (int i = 0; i < k; i++)
                du += X[p][i + 1] * dlam[i];
            u[F[p]] += du;
            dumax = fmax(dumax, fabs(du));
        }
        for (int j = 0; j < m; j++)
            umax = fmax(umax, fabs(u[j]));
        for (int i = 0; i < k; i++) {
            lam[i] += dlam[i];
            dlmax = fmax(dlmax, fabs(dlam[i]));
            lmax = fmax(lmax, fabs(lam[i]));
        }
        if (!(isfinite(dumax) && isfinite(umax) && isfinite(dlmax) && isfinite(lmax)))
            return NOT_FINITE;
        if (dumax <= 1e-13 * (1.0 + umax) && dlmax <= 1e-11 * (1.0 + lmax))
            return 0;
        double lmin = lam[0];
        for (int i = 1; i < k; i++)
            lmin = fmin(lmin, lam[i]);
        negative = (lmin < 0.0) ? negative + 1 : 0;
        if (negative >= NEGATIVE_ITERATES)
            return NEGATIVE_MULTIPLIER; /* that cone does not bind: the caller drops it */
    }
    return NO_CONVERGENCE;
}

/* the face iteration around newton(): fix the coordinate farthest outside the box, else
 * release the face whose multiplier pushes outwards; then snap to the box */
static int project(const Problem *P, double *u, double *lam, unsigned char *fixed)
{
    const int m = P->m, k = P->k;
    const double *low = P->low, *high = P->high;
    unsigned char seen[MAX_FACE_ROUNDS][MAXM];
    for (int j = 0; j < m; j++)
        u[j] = fmin(fmax(u[j], low[j]), high[j]);
    for (int round = 0; round < MAX_FACE_ROUNDS; round++) {
        for (int s = 0; s < round; s++)
            if (memcmp(seen[s], fixed, (size_t)m) == 0)
                return FACES_CYCLE;
        memcpy(seen[round], fixed, (size_t)m);
        int rc = newton(P, u, lam, fixed);
        if (rc)
            return rc;
        int jout = -1;
        double worst = 0.0;
        for (int j = 0; j < m; j++) {
            const double e = fmax(low[j] - u[j], u[j] - high[j]);
            if (e > worst) {
                worst = e;
                jout = j;
            }
        }
        if (jout >= 0) {
            for (int j = 0; j < m; j++)
                u[j] = fmin(fmax(u[j], low[j]), high[j]);
            fixed[jout] = 1;
            continue;
        }
        double c[MAXK], grad[MAXK][MAXM], w[MAXK][MAXM], nv[MAXK];
        rc = terms(P, u, c, grad, w, nv);
        if (rc)
            return rc;
        int jin = -1;
        double wrong_max = 0.0;
        for (int j = 0; j < m; j++) {
            if (!fixed[j])
                continue;
            double g = u[j] - P->u_nom[j];
            for (int i = 0; i < k; i++)
                g -= lam[i] * grad[i][j];
            const double wrong = (u[j] <= low[j]) ? -g : (u[j] >= high[j]) ? g : 0.0;
            if (wrong > wrong_max) {
                wrong_max = wrong;
                jin = j;
            }
        }
        if (jin >= 0) {
            fixed[jin] = 0;
            continue;
        }
        for (int i = 0; i < k; i++)
            if (!(lam[i] >= 0.0))
                return NEGATIVE_MULTIPLIER;
        for (int j = 0; j < m; j++) {
            const double tol = 1e-13 * (high[j] - low[j]);
            if (u[j] - low[j] <= tol)
                u[j] = low[j];
            else if (high[j] - u[j] <= tol)
                u[j] = high[j];
        }
        return 0;
    }
    return FACES_UNSETTLED;
}

/* the cone outside the binding set most violated at u beyond its tolerance, relative to it
 * (margin / tol below -1); -1 if none, NOT_FINITE if a margin is NaN */
static int most_violated(const Problem *P, int K, const double *tol, const double *u)
{
    int found = -1;
    double worst = -1.0;
    for (int q = 0; q < K; q++) {
        int in = 0;
        for (int i = 0; i < P->k; i++)
            in |= P->idx[i] == q;
        if (in)
            continue;
        const double r = margin(P, q, u) / tol[q];
        if (isnan(r))
            return NOT_FINITE;
        if (r < worst) {
            worst = r;
            found = q;
        }
    }
    return found;
}

/* the binding set among all K cones: project() onto the set (from u, lam), then the cone most
 * violated beyond its tolerance (relative to it) joins with multiplier 0, or the cone with
 * the most negative multiplier leaves, until no other cone is violated; lam_all (K) and
 * binding (K) in/out: the start and the answer */
static int solve_set(Problem *P, int K, const double *tol, int max_binding, double *u,
                     double *lam_all, unsigned char *binding)
{
    const int m = P->m;
    unsigned long long tried[MAX_SET_ROUNDS];
    double lam[MAXK];
    unsigned char fixed[MAXM];
    P->k = 0;
    for (int q = 0; q < K; q++)
        if (binding[q]) {
            if (P->k == max_binding)
                return TOO_MANY_BINDING;
            lam[P->k] = lam_all[q];
            P->idx[P->k++] = q;
        }
    if (P->k == 0) { /* no start set: the cone most violated at u, relative to its scale */
        const int first = most_violated(P, K, tol, u);
        if (first == NOT_FINITE)
            return NOT_FINITE;
        if (first < 0)
            return NO_FREE;
        lam[0] = 0.0;
        P->idx[P->k++] = first;
    }
    for (int round = 0; round < MAX_SET_ROUNDS; round++) {
        unsigned long long mask = 0;
        for (int i = 0; i < P->k; i++)
            mask |= 1ULL << P->idx[i];
        for (int r = 0; r < round; r++)
            if (tried[r] == mask)
                return SET_CYCLE;
        tried[round] = mask;
        for (int j = 0; j < m; j++)
            fixed[j] = (u[j] <= P->low[j]) || (u[j] >= P->high[j]);
        const int rc = project(P, u, lam, fixed);
        if (rc == NEGATIVE_MULTIPLIER) { /* that cone does not bind: it leaves */
            if (P->k == 1)
                return rc;
            int out = 0;
            for (int i = 1; i < P->k; i++)
                if (lam[i] < lam[out])
                    out = i;
            for (int i = out; i + 1 < P->k; i++) {
                P->idx[i] = P->idx[i + 1];
                lam[i] = lam[i + 1];
            }
            P->k--;
            continue;
        }
        if (rc)
            return rc;
        const int join = most_violated(P, K, tol, u);
        if (join == NOT_FINITE)
            return NOT_FINITE;
        if (join < 0) {
            for (int q = 0; q < K; q++) {
                lam_all[q] = 0.0;
                binding[q] = 0;
            }
            for (int i = 0; i < P->k; i++) {
                lam_all[P->idx[i]] = lam[i];
                binding[P->idx[i]] = 1;
            }
            return 0;
        }
        if (P->k == max_binding)
            return TOO_MANY_BINDING;
        P->idx[P->k] = join;
        lam[P->k++] = 0.0;
    }
    return SET_UNSETTLED;
}

/* The KKT certificate of u for the whole program of K cones (fastpath.certify, the same
 * test): every margin c_q(u) (into c) >= -tol_q, the binding cones' multipliers lam_q >= 0,
 * and the distance bound ||rho|| + sqrt(||rho||^2 + 2 comp) <= dist_tol (1 + max|u|) with rho
 * = u - u_nom - sum_q lam_q grad c_q(u) less what the box faces u lies on absorb, comp =
 * sum lam_q c_q over the binding margins above their tolerance. 1: certified, 0: not (also
 * at a cone's apex and for NaN). */
static int certificate(const Problem *P, int K, const double *tol, const double *u,
                       const double *lam, const unsigned char *binding, double dist_tol,
                       double *c)
{
    const int m = P->m, n1 = m + 1;
    int ok = 1;
    for (int q = 0; q < K; q++) {
        c[q] = margin(P, q, u);
        ok &= c[q] >= 0.0 || c[q] + tol[q] >= 0.0; /* false for NaN */
    }
    if (!ok)
        return 0;
    double w[MAXM], comp = 0.0;
    for (int j = 0; j < m; j++)
        w[j] = u[j] - P->u_nom[j];
    for (int q = 0; q < K; q++) {
        if (!binding[q])
            continue;
        if (!(lam[q] >= 0.0))
            return 0;
        if (c[q] > tol[q])
            comp += lam[q] * c[q];
        const double *Gq = P->G + (size_t)q * n1 * n1, *aq = P->a + (size_t)q * m;
        double v[MAXM + 1];
        const double nv = sqrt(cone_vector(P, q, u, v));
        if (!(nv > 0.0))
            return 0;
        for (int j = 0; j < m; j++) {
            double x = 0.0;
            for (int r = 0; r < n1; r++)
                x += Gq[(size_t)r * n1 + j + 1] * v[r];
            w[j] -= lam[q] * (aq[j] - x / nv);
        }
    }
    double r2 = 0.0, umax = 0.0;
    for (int j = 0; j < m; j++) {
        double wj = w[j];
        if (u[j] <= P->low[j])
            wj = wj < 0.0 ? wj : 0.0;
        else if (u[j] >= P->high[j])
            wj = wj > 0.0 ? wj : 0.0;
        else if (!(P->low[j] < u[j] && u[j] < P->high[j]))
            return 0; /* NaN */
        r2 += wj * wj;
        umax = fmax(umax, fabs(u[j]));
    }
    const double r = sqrt(r2);
    return r + sqrt(r2 + 2.0 * comp) <= dist_tol * (1.0 + umax);
}

/* One argument of the Python entry points: its name, dtype and whether it is written
 * (afvsgp_gym/_cbuf.h), and its length: 'm' actions, 'k' cones, 'a' k x m, 'G' k x (m+1)^2. */
typedef struct {
    Spec spec;
    char len;
} Arg;

/* the buffers b[i] of the arguments o[i], m and k from the first two (u_nom: 1..MAXM
 * actions, a0: 1..max_k cones); -1 with an error naming the argument (and every buffer
 * released) */
static int take_args(PyObject **o, Py_buffer *b, const Arg *arg, int n_args, Py_ssize_t max_k,
                     Py_ssize_t *m, Py_ssize_t *k)
{
    for (int i = 0; i < n_args; i++) {
        const char len = arg[i].len;
        const Py_ssize_t want = i < 2 ? -1 : len == 'm' ? *m : len == 'k' ? *k
                                : len == 'a' ? *k * *m : *k * (*m + 1) * (*m + 1);
        if (take(o[i], &b[i], &arg[i].spec, want) < 0) {
            release_all(b, i);
            return -1;
        }
        if (i < 2) { /* u_nom and a0 set m and k */
            const Py_ssize_t top = (i == 0) ? MAXM : max_k, got = b[i].len / 8;
            if (got < 1 || got > top) {
                PyErr_Format(PyExc_ValueError, "%s must hold 1 to %zd float64 items",
                             arg[i].spec.name, top);
                release_all(b, i + 1);
                return -1;
            }
            *(i == 0 ? m : k) = got;
        }
    }
    return 0;
}

/* the problem's data from the buffers u_nom, a0, a, G, low, high */
static void set_data(Problem *P, Py_buffer *b, Py_ssize_t m)
{
    P->m = (int)m;
    P->k = 0;
    P->u_nom = b[0].buf;
    P->a0 = b[1].buf;
    P->a = b[2].buf;
    P->G = b[3].buf;
    P->low = b[4].buf;
    P->high = b[5].buf;
}

static PyObject *py_project(PyObject *self, PyObject *args)
{
    static const Arg spec[9] = {
        {{"u_nom", 'd', 0}, 'm'}, {{"a0", 'd', 0}, 'k'},  {{"a", 'd', 0}, 'a'},
        {{"G", 'd', 0}, 'G'},     {{"low", 'd', 0}, 'm'}, {{"high", 'd', 0}, 'm'},
        {{"u", 'd', 1}, 'm'},     {{"lam", 'd', 1}, 'k'}, {{"fixed", '?', 1}, 'm'}};
    PyObject *o[9];
    Py_buffer b[9];
    Py_ssize_t m = 0, k = 0;
    if (!PyArg_UnpackTuple(args, "project", 9, 9, &o[0], &o[1], &o[2], &o[3], &o[4], &o[5],
                           &o[6], &o[7], &o[8]))
        return NULL;
    if (take_args(o, b, spec, 9, MAXK, &m, &k) < 0)
        return NULL;
    Problem P;
    set_data(&P, b, m);
    P.k = (int)k;
    for (int i = 0; i < P.k; i++)
        P.idx[i] = i;
    double BtB[MAXK * MAXM * MAXM];
    for (int i = 0; i < P.k; i++)
        gram(&P, i, BtB + (size_t)i * m * m);
    P.BtB = BtB;
    const int rc = project(&P, b[6].buf, b[7].buf, b[8].buf);
    release_all(b, 9);
    return PyLong_FromLong(rc);
}

static PyObject *py_solve(PyObject *self, PyObject *args)
{
    static const Arg spec[10] = {
        {{"u_nom", 'd', 0}, 'm'}, {{"a0", 'd', 0}, 'k'},  {{"a", 'd', 0}, 'a'},
        {{"G", 'd', 0}, 'G'},     {{"low", 'd', 0}, 'm'}, {{"high", 'd', 0}, 'm'},
        {{"tol", 'd', 0}, 'k'},   {{"u", 'd', 1}, 'm'},   {{"lam", 'd', 1}, 'k'},
        {{"binding", '?', 1}, 'k'}};
    PyObject *o[10];
    Py_buffer b[10];
    Py_ssize_t m = 0, K = 0;
    int max_binding;
    if (!PyArg_ParseTuple(args, "OOOOOOOOOOi", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5], &o[6],
                          &o[7], &o[8], &o[9], &max_binding))
        return NULL;
    if (max_binding < 1 || max_binding > MAXK) {
        PyErr_Format(PyExc_ValueError, "max_binding must be in [1, %d]", MAXK);
        return NULL;
    }
    if (take_args(o, b, spec, 10, MAXC, &m, &K) < 0)
        return NULL;
    double *BtB = PyMem_Malloc(sizeof(double) * (size_t)(K * m * m));
    if (BtB == NULL) {
        release_all(b, 10);
        return PyErr_NoMemory();
    }
    Problem P;
    set_data(&P, b, m);
    for (int q = 0; q < K; q++)
        gram(&P, q, BtB + (size_t)q * m * m);
    P.BtB = BtB;
    const int rc = solve_set(&P, (int)K, b[6].buf, max_binding, b[7].buf, b[8].buf, b[9].buf);
    PyMem_Free(BtB);
    release_all(b, 10);
    return PyLong_FromLong(rc);
}

static PyObject *py_certify(PyObject *self, PyObject *args)
{
    static const Arg spec[11] = {
        {{"u_nom", 'd', 0}, 'm'}, {{"a0", 'd', 0}, 'k'},   {{"a", 'd', 0}, 'a'},
        {{"G", 'd', 0}, 'G'},     {{"low", 'd', 0}, 'm'},  {{"high", 'd', 0}, 'm'},
        {{"tol", 'd', 0}, 'k'},   {{"u", 'd', 0}, 'm'},    {{"lam", 'd', 0}, 'k'},
        {{"binding", '?', 0}, 'k'}, {{"margins", 'd', 1}, 'k'}};
    PyObject *o[11];
    Py_buffer b[11];
    Py_ssize_t m = 0, K = 0;
    double dist_tol;
    if (!PyArg_ParseTuple(args, "OOOOOOOOOOOd", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5],
                          &o[6], &o[7], &o[8], &o[9], &o[10], &dist_tol))
        return NULL;
    if (take_args(o, b, spec, 11, PY_SSIZE_T_MAX, &m, &K) < 0)
        return NULL;
    Problem P;
    set_data(&P, b, m);
    const int ok = certificate(&P, (int)K, b[6].buf, b[7].buf, b[8].buf, b[9].buf, dist_tol,
                               b[10].buf);
    release_all(b, 11);
    return PyBool_FromLong(ok);
}

static PyObject *py_margins(PyObject *self, PyObject *args)
{
    static const Arg spec[5] = {{{"u", 'd', 0}, 'm'},   {{"a0", 'd', 0}, 'k'},
                                {{"a", 'd', 0}, 'a'},   {{"G", 'd', 0}, 'G'},
                                {{"margins", 'd', 1}, 'k'}};
    PyObject *o[5];
    Py_buffer b[5];
    Py_ssize_t m = 0, K = 0;
    if (!PyArg_UnpackTuple(args, "margins", 5, 5, &o[0], &o[1], &o[2], &o[3], &o[4]))
        return NULL;
    if (take_args(o, b, spec, 5, PY_SSIZE_T_MAX, &m, &K) < 0)
        return NULL;
    Problem P = {.m = (int)m, .a0 = b[1].buf, .a = b[2].buf, .G = b[3].buf};
    double *c = b[4].buf;
    for (Py_ssize_t q = 0; q < K; q++)
        c[q] = margin(&P, (int)q, b[0].buf);
    release_all(b, 5);
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"solve", py_solve, METH_VARARGS,
     "solve(u_nom, a0, a, G, low, high, tol, u, lam, binding, max_binding) -> int: 0 when "
     "the binding set settled with no other cone violated beyond tol. u, lam (float64) and "
     "binding (bool, one per cone) are the start and are overwritten with the answer."},
    {"certify", py_certify, METH_VARARGS,
     "certify(u_nom, a0, a, G, low, high, tol, u, lam, binding, margins, dist_tol) -> bool: "
     "the KKT certificate of u for every cone (binding: those with a multiplier lam); "
     "margins (float64, one per cone) is overwritten with c_q(u)."},
    {"margins", py_margins, METH_VARARGS,
     "margins(u, a0, a, G, out) -> None: out[q] = a0[q] + a[q] @ u - ||G[q] [1, u]||."},
    {"project", py_project, METH_VARARGS,
     "project(u_nom, a0, a, G, low, high, u, lam, fixed) -> int: 0 when settled. u, lam "
     "(float64) and fixed (bool) are the start and are overwritten with the answer."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_cones",
                                    "Compiled core of afvsgp_gym.cbf.binding_cones.", -1,
                                    methods};

PyMODINIT_FUNC PyInit__cones(void) { return PyModule_Create(&module); }
