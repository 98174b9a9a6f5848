/* The Franka bridge's per-tick geometry, compiled.
 *
 * The compiled core of afvsgp_gym.robots.kinematics.SphereKinematics.__call__ (points on the
 * links of a 7-joint modified-DH chain: positions, velocities, Jacobians and J' q') and of the
 * sphere pairs of afvsgp_gym.robots.terms.BarrierModel.terms (h, h', lf, lg, the features and
 * the projection rows n'(J_a - J_b) of every (sphere, obstacle) and self-collision pair). Their
 * docstrings state the formulas; the numpy versions are the reference (tests/robots agree to
 * rounding) and run where this is not built or for what it does not cover (non-sphere
 * obstacles, an obstacle covariance). Row-major float64, one tick at a time.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>

#include "../_cbuf.h"

#define NJ 7        /* joints */
#define NFEAT 20    /* [q, q', p_a - p_b, v_a - v_b] */

static inline void cross(const double *a, const double *b, double *out)
{
    out[0] = a[1] * b[2] - a[2] * b[1];
    out[1] = a[2] * b[0] - a[0] * b[2];
    out[2] = a[0] * b[1] - a[1] * b[0];
}

static inline double dot(const double *a, const double *b)
{
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
}

/* rot (3x3, row-major) times x */
static inline void rotate(const double *rot, const double *x, double *out)
{
    for (int r = 0; r < 3; r++)
        out[r] = rot[3 * r] * x[0] + rot[3 * r + 1] * x[1] + rot[3 * r + 2] * x[2];
}

static PyObject *py_kinematics(PyObject *self, PyObject *args)
{
    enum { Q, QD, THETA, RX, SHIFT, FRAME, OFFSET, P, V, JAC, ACC, N };
    static const Spec spec[N] = {
        {"q", 'd', 0},     {"qd", 'd', 0},     {"theta_offset", 'd', 0}, {"rx", 'd', 0},
        {"shift", 'd', 0}, {"frame", 'q', 0},  {"offsets", 'd', 0},      {"p", 'd', 1},
        {"v", 'd', 1},     {"jac", 'd', 1},    {"acc", 'd', 1}};
    PyObject *o[N];
    Py_buffer b[N];
    int S;
    if (!PyArg_ParseTuple(args, "iOOOOOOOOOOO", &S, &o[Q], &o[QD], &o[THETA], &o[RX],
                          &o[SHIFT], &o[FRAME], &o[OFFSET], &o[P], &o[V], &o[JAC], &o[ACC]))
        return NULL;
    if (S < 0) {
        PyErr_SetString(PyExc_ValueError, "S must be >= 0");
        return NULL;
    }
    const Py_ssize_t s3 = (Py_ssize_t)S * 3;
    const Py_ssize_t size[N] = {NJ, NJ, NJ, NJ * 9, NJ * 3, S, s3, s3, s3, s3 * NJ, s3};
    if (take_all(o, b, spec, size, N) < 0)
        return NULL;
    const double *q = b[Q].buf, *qd = b[QD].buf, *th = b[THETA].buf, *rx = b[RX].buf,
                 *shift = b[SHIFT].buf, *off = b[OFFSET].buf;
    const long long *frame = b[FRAME].buf;
    double *p = b[P].buf, *v = b[V].buf, *jac = b[JAC].buf, *acc = b[ACC].buf;
    for (int s = 0; s < S; s++)
        if (frame[s] < 0 || frame[s] >= NJ) {
            release_all(b, N);
            PyErr_SetString(PyExc_ValueError, "frame must hold link indices 0-6");
            return NULL;
        }

    /* frames: R_i = R_{i-1} Rot_x(alpha_i) Rot_z(theta_i), o_i = o_{i-1} + R_{i-1} shift_i */
    double rot[NJ][9], org[NJ][3], z[NJ][3], w[NJ][3], bias[NJ][3], vo[NJ][3], ao[NJ][3];
    for (int i = 0; i < NJ; i++) {
        const double c = cos(q[i] + th[i]), sn = sin(q[i] + th[i]);
        const double *x = rx + 9 * i;
        double local[9];
        for (int r = 0; r < 3; r++) {
            local[3 * r] = x[3 * r] * c + x[3 * r + 1] * sn;
            local[3 * r + 1] = x[3 * r + 1] * c - x[3 * r] * sn;
            local[3 * r + 2] = x[3 * r + 2];
        }
        if (i == 0) {
            for (int k = 0; k < 9; k++)
                rot[0][k] = local[k];
            for (int r = 0; r < 3; r++)
                org[0][r] = shift[r];
        } else {
            for (int r = 0; r < 3; r++)
                for (int col = 0; col < 3; col++)
                    rot[i][3 * r + col] = rot[i - 1][3 * r] * local[col] +
                                          rot[i - 1][3 * r + 1] * local[3 + col] +
                                          rot[i - 1][3 * r + 2] * local[6 + col];
            double step[3];
            rotate(rot[i - 1], shift + 3 * i, step);
            for (int r = 0; r < 3; r++)
                org[i][r] = org[i - 1][r] + step[r];
        }
        for (int r = 0; r < 3; r++)
            z[i][r] = rot[i][3 * r + 2];
    }
    /* w_i = sum_{j<=i} q'_j z_j; b_i = sum_{j<=i} q'_j (w_j x z_j); origins' velocity and
     * velocity-product acceleration: o_{i+1} rides on frame i at e_i = o_{i+1} - o_i */
    for (int i = 0; i < NJ; i++) {
        double wz[3];
        for (int r = 0; r < 3; r++)
            w[i][r] = (i ? w[i - 1][r] : 0.0) + qd[i] * z[i][r];
        cross(w[i], z[i], wz);
        for (int r = 0; r < 3; r++)
            bias[i][r] = (i ? bias[i - 1][r] : 0.0) + qd[i] * wz[r];
    }
    for (int r = 0; r < 3; r++)
        vo[0][r] = ao[0][r] = 0.0;
    for (int i = 0; i + 1 < NJ; i++) {
        double e[3], we[3], be[3], wwe[3];
        for (int r = 0; r < 3; r++)
            e[r] = org[i + 1][r] - org[i][r];
        cross(w[i], e, we);
        cross(bias[i], e, be);
        cross(w[i], we, wwe);
        for (int r = 0; r < 3; r++) {
            vo[i + 1][r] = vo[i][r] + we[r];
            ao[i + 1][r] = ao[i][r] + (be[r] + wwe[r]);
        }
    }
    /* the points: p = R_f offset + o_f, J's column i = z_i x (p - o_i) for i <= f, v = v_o +
     * w_f x r, J' q' = a_o + b_f x r + w_f x (w_f x r) with r = p - o_f */
    for (int s = 0; s < S; s++) {
        const int f = (int)frame[s];
        double *ps = p + 3 * s, *js = jac + (size_t)s * 3 * NJ, rr[3], wr[3], br[3], wwr[3];
        rotate(rot[f], off + 3 * s, rr);
        for (int r = 0; r < 3; r++)
            ps[r] = rr[r] + org[f][r];
        for (int i = 0; i < NJ; i++) {
            double col[3] = {0.0, 0.0, 0.0};
            if (i <= f) {
                const double d[3] = {ps[0] - org[i][0], ps[1] - org[i][1], ps[2] - org[i][2]};
                cross(z[i], d, col);
            }
            for (int r = 0; r < 3; r++)
                js[r * NJ + i] = col[r];
        }
        for (int r = 0; r < 3; r++)
            rr[r] = ps[r] - org[f][r];
        cross(w[f], rr, wr);
        cross(bias[f], rr, br);
        cross(w[f], wr, wwr);
        for (int r = 0; r < 3; r++) {
            v[3 * s + r] = vo[f][r] + wr[r];
            acc[3 * s + r] = ao[f][r] + (br[r] + wwr[r]);
        }
    }
    release_all(b, N);
    Py_RETURN_NONE;
}

/* The pairs' rows. Pair k keeps sphere first[k] (moving, index < S) at least radius[k] from
 * second[k]: a moving sphere (>= 0), obstacle o (-1 - o, o < O: its position, velocity and
 * acceleration) or fixed sphere f (-1 - O - f: at rest at fixed[f]). With d = p_a - p_b, v_rel
 * = v_a - v_b, n = d / max(|d|, 1e-9): h = |d| - radius, h' = n.v_rel, curvature = (|v_rel|^2 -
 * h'^2) / |d|, lf = n.(a_a - a_b) + curvature with each sphere's acceleration at zero action
 * a_s = J_s q''_0 + (J' q')_s, rows = n'(J_a - J_b), lg = rows gain (gain = M^-1
 * diag(action_scale)), xi = [q, q', d, v_rel]. */
static PyObject *py_pair_terms(PyObject *self, PyObject *args)
{
    enum { FIRST, SECOND, RADIUS, P, V, JAC, BIASACC, QACC0, OP, OV, OA, FIXED, GAIN, Q, QD,
           DERIVS, LF, LG, XI, ROWS, N };
    static const Spec spec[N] = {
        {"first", 'q', 0},        {"second", 'q', 0},     {"radius", 'd', 0},
        {"p", 'd', 0},            {"v", 'd', 0},          {"jac", 'd', 0},
        {"bias", 'd', 0},         {"qacc0", 'd', 0},      {"obstacle_position", 'd', 0},
        {"obstacle_velocity", 'd', 0}, {"obstacle_acceleration", 'd', 0},
        {"fixed", 'd', 0},        {"gain", 'd', 0},       {"q", 'd', 0},
        {"qd", 'd', 0},           {"derivatives", 'd', 1}, {"lf", 'd', 1},
        {"lg", 'd', 1},           {"xi", 'd', 1},         {"rows", 'd', 1}};
    PyObject *o[N];
    Py_buffer b[N];
    int S, P_, O, F;
    if (!PyArg_ParseTuple(args, "iiiiOOOOOOOOOOOOOOOOOOOO", &S, &P_, &O, &F, &o[FIRST],
                          &o[SECOND], &o[RADIUS], &o[P], &o[V], &o[JAC], &o[BIASACC],
                          &o[QACC0], &o[OP], &o[OV], &o[OA], &o[FIXED], &o[GAIN], &o[Q],
                          &o[QD], &o[DERIVS], &o[LF], &o[LG], &o[XI], &o[ROWS]))
        return NULL;
    if (S < 0 || P_ < 0 || O < 0 || F < 0) {
        PyErr_SetString(PyExc_ValueError, "S, P, O and F must be >= 0");
        return NULL;
    }
    const Py_ssize_t s3 = (Py_ssize_t)S * 3, np_ = P_;
    const Py_ssize_t size[N] = {np_, np_, np_, s3, s3, s3 * NJ, s3, NJ, (Py_ssize_t)O * 3,
                                (Py_ssize_t)O * 3, (Py_ssize_t)O * 3, (Py_ssize_t)F * 3,
                                NJ * NJ, NJ, NJ, 2 * np_, np_, NJ * np_, NFEAT * np_,
                                NJ * np_};
    if (take_all(o, b, spec, size, N) < 0)
        return NULL;
    const long long *first = b[FIRST].buf, *second = b[SECOND].buf;
    for (int k = 0; k < P_; k++)
        if (first[k] < 0 || first[k] >= S || second[k] >= S ||
            second[k] < -(long long)O - F) {
            release_all(b, N);
            PyErr_SetString(PyExc_ValueError, "first must index moving spheres and second a "
                                              "moving sphere, an obstacle or a fixed sphere");
            return NULL;
        }
    const double *radius = b[RADIUS].buf, *p = b[P].buf, *v = b[V].buf, *jac = b[JAC].buf,
                 *jqd = b[BIASACC].buf, *qacc0 = b[QACC0].buf, *op = b[OP].buf,
                 *ov = b[OV].buf, *oa = b[OA].buf, *fixed = b[FIXED].buf, *gain = b[GAIN].buf,
                 *q = b[Q].buf, *qd = b[QD].buf;
    double *derivs = b[DERIVS].buf, *lf = b[LF].buf, *lg = b[LG].buf, *xi = b[XI].buf,
           *rows = b[ROWS].buf;
    double *acc = PyMem_Malloc((size_t)(S ? s3 : 1) * sizeof(double));
    if (acc == NULL) {
        release_all(b, N);
        return PyErr_NoMemory();
    }
    for (int s = 0; s < S; s++)
        for (int r = 0; r < 3; r++) {
            const double *jr = jac + ((size_t)s * 3 + r) * NJ;
            double x = jqd[3 * s + r];
            for (int i = 0; i < NJ; i++)
                x += jr[i] * qacc0[i];
            acc[3 * s + r] = x;
        }
    static const double rest[3] = {0.0, 0.0, 0.0};
    for (int k = 0; k < P_; k++) {
        const int a = (int)first[k];
        const long long sb = second[k];
        const double *pb, *vb, *ab, *jb = NULL;
        if (sb >= 0) {
            pb = p + 3 * sb, vb = v + 3 * sb, ab = acc + 3 * sb;
            jb = jac + (size_t)sb * 3 * NJ;
        } else if (-1 - sb < O) {
            const long long ob = -1 - sb;
            pb = op + 3 * ob, vb = ov + 3 * ob, ab = oa + 3 * ob;
        } else {
            pb = fixed + 3 * (-1 - sb - O), vb = rest, ab = rest;
        }
        const double *ja = jac + (size_t)a * 3 * NJ;
        double d[3], vr[3], da[3], n[3];
        for (int r = 0; r < 3; r++) {
            d[r] = p[3 * a + r] - pb[r];
            vr[r] = v[3 * a + r] - vb[r];
            da[r] = acc[3 * a + r] - ab[r];
        }
        double dist = sqrt(dot(d, d));
        if (!(dist >= 1e-9))
            dist = dist != dist ? dist : 1e-9; /* NaN stays NaN */
        for (int r = 0; r < 3; r++)
            n[r] = d[r] / dist;
        const double hd = dot(n, vr);
        const double curv = (dot(vr, vr) - hd * hd) / dist;
        derivs[2 * k] = dist - radius[k];
        derivs[2 * k + 1] = hd;
        lf[k] = dot(n, da) + curv;
        double *row = rows + (size_t)k * NJ, *g = lg + (size_t)k * NJ;
        for (int i = 0; i < NJ; i++) {
            double x = 0.0;
            for (int r = 0; r < 3; r++)
                x += n[r] * (ja[r * NJ + i] - (jb ? jb[r * NJ + i] : 0.0));
            row[i] = x;
        }
        for (int j = 0; j < NJ; j++) {
            double x = 0.0;
            for (int i = 0; i < NJ; i++)
                x += row[i] * gain[i * NJ + j];
            g[j] = x;
        }
        double *xk = xi + (size_t)k * NFEAT;
        for (int i = 0; i < NJ; i++) {
            xk[i] = q[i];
            xk[NJ + i] = qd[i];
        }
        for (int r = 0; r < 3; r++) {
            xk[2 * NJ + r] = d[r];
            xk[2 * NJ + 3 + r] = vr[r];
        }
    }
    PyMem_Free(acc);
    release_all(b, N);
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"kinematics", py_kinematics, METH_VARARGS,
     "kinematics(S, q, qd, theta_offset, rx, shift, frame, offsets, p, v, jac, acc) -> None: "
     "the S points' positions, velocities, Jacobians (S, 3, 7) and J' q' into p, v, jac, acc "
     "(SphereKinematics.__call__)."},
    {"pair_terms", py_pair_terms, METH_VARARGS,
     "pair_terms(S, P, O, F, first, second, radius, p, v, jac, bias, qacc0, "
     "obstacle_position, obstacle_velocity, obstacle_acceleration, fixed, gain, q, qd, "
     "derivatives, lf, lg, xi, rows) -> None: the P sphere pairs' rows."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_arm",
                                    "Compiled core of the Franka bridge's per-tick geometry: "
                                    "the spheres' kinematics and the sphere pairs' barrier "
                                    "terms.", -1, methods};

PyMODINIT_FUNC PyInit__arm(void) { return PyModule_Create(&module); }
