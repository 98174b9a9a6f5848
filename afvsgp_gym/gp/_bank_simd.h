/* The hot loops of the learners' core (afvsgp_gym/gp/_bank.c), written once for a vector of
 * VL float64 lanes and included once per instruction set: _bank.c defines VL (8 for AVX-512,
 * 4 for AVX2, 2 for the baseline SSE2 or NEON) and SIMD(name) (the suffix of this copy's
 * names) and compiles each copy for its target, so that the vectors are the machine's own
 * registers (GCC lowers a wider vector type through memory). No FMA, and every vector
 * operation elementwise: each output is the same sum of the same products in the same order
 * in every copy, so every copy rounds the same. The blocks of VL outputs start at
 * min(VL t, n - VL): the last overlaps the one before and recomputes the same values. */

typedef double SIMD(vec) __attribute__((vector_size(8 * VL)));
#define VEC SIMD(vec)
/* the same vector at any double's address (GCC/Clang: unaligned, may alias a double) */
typedef double SIMD(uvec) __attribute__((vector_size(8 * VL), aligned(8), may_alias));

/* the VL doubles at p as a vector, and back: one unaligned load or store (memcpy into an
 * element of an array of vectors can go through the stack, in halves) */
__attribute__((always_inline)) static inline VEC SIMD(load)(const double *p)
{
    return *(const SIMD(uvec) *)p;
}

__attribute__((always_inline)) static inline void SIMD(store)(double *p, VEC v)
{
    *(SIMD(uvec) *)p = v;
}

/* the vector with every lane x */
__attribute__((always_inline)) static inline VEC SIMD(splat)(double x)
{
    VEC v;
    for (int l = 0; l < VL; l++)
        v[l] = x;
    return v;
}

/* y += a x + b w (n) */
__attribute__((always_inline)) static inline void
SIMD(axpby)(double *restrict y, double a, const double *restrict x, double b,
            const double *restrict w, int n)
{
    for (int l = 0; l < n; l++)
        y[l] += a * x[l] + b * w[l];
}

/* y += a x (n) */
__attribute__((always_inline)) static inline void SIMD(axpy)(double *restrict y, double a,
                                                            const double *restrict x, int n)
{
    for (int l = 0; l < n; l++)
        y[l] += a * x[l];
}

/* out_a[j], out_b[j] (n) = sum_r wa[r] rows[r, j], sum_r wb[r] rows[r, j] over r = 0 .. nrows - 1
 * in order, from 0.0 (rows row-major with stride ld; out_b, wb NULL for one sum): each output
 * the same sum of the same products as nrows calls of axpy, but four blocks of VL outputs at
 * a time in independent vector accumulators */
__attribute__((always_inline)) static inline void
SIMD(weighted_row_sums2)(const double *restrict rows, size_t ld, const double *restrict wa,
                         const double *restrict wb, int nrows, int n, double *restrict out_a,
                         double *restrict out_b)
{
    if (n < VL) {
        for (int pass = 0; pass < (out_b != NULL ? 2 : 1); pass++) {
            double *out = pass ? out_b : out_a;
            const double *w = pass ? wb : wa;
            for (int j = 0; j < n; j++)
                out[j] = 0.0;
            for (int r = 0; r < nrows; r++)
                SIMD(axpy)(out, w[r], rows + (size_t)r * ld, n);
        }
        return;
    }
    const int nb = (n + VL - 1) / VL;
    for (int t = 0; t < nb; t += 4) {
        int j[4];
        for (int u = 0; u < 4; u++)
            j[u] = VL * (t + u) + VL <= n ? VL * (t + u) : n - VL;
        VEC a[4], b[4];
        for (int u = 0; u < 4; u++)
            a[u] = b[u] = SIMD(splat)(0.0);
        if (out_b != NULL) {
            for (int r = 0; r < nrows; r++) {
                const double *row = rows + (size_t)r * ld;
                const VEC xv = SIMD(splat)(wa[r]), yv = SIMD(splat)(wb[r]);
                for (int u = 0; u < 4; u++) {
                    const VEC s = SIMD(load)(row + j[u]);
                    a[u] += xv * s;
                    b[u] += yv * s;
                }
            }
        } else {
            for (int r = 0; r < nrows; r++) {
                const double *row = rows + (size_t)r * ld;
                const VEC xv = SIMD(splat)(wa[r]);
                for (int u = 0; u < 4; u++) {
                    const VEC s = SIMD(load)(row + j[u]);
                    a[u] += xv * s;
                }
            }
        }
        for (int u = 0; u < 4; u++) {
            SIMD(store)(out_a + j[u], a[u]);
            if (out_b != NULL)
                SIMD(store)(out_b + j[u], b[u]);
        }
    }
}

/* v = A x for a symmetric (n, n) A, by columns (x[l] times column l, summed over l in order) */
__attribute__((always_inline)) static inline void
SIMD(symv_inline)(const double *restrict A, const double *restrict x, int n, double *restrict v)
{
    SIMD(weighted_row_sums2)(A, (size_t)n, x, NULL, n, n, v, NULL);
}

static void SIMD(symv)(const double *restrict A, const double *restrict x, int n,
                       double *restrict v)
{
    SIMD(symv_inline)(A, x, n, v);
}

/* out[j] (n) = sum_r wts[r] rows[r, j] in order, over r < nrows (e.g. the candidate's new
 * row of S over the window, eq. 30) */
static void SIMD(weighted_row_sums)(const double *rows, size_t ld, const double *wts, int nrows,
                                    int n, double *out)
{
    SIMD(weighted_row_sums2)(rows, ld, wts, NULL, nrows, n, out, NULL);
}

/* g (q, q): g_il = sum_p X[p, i] X[p, l] for the row-major (n, q) X with row stride ldx, the
 * sum over p outermost (a rank-1 update by each row). For q = 8 or 9 (the Franka's ubar and
 * [ubar, 1]) the sums stay in vector accumulators, VL columns of the first eight at a time:
 * row i's in one, the ninth column's (x_i x_8 = x_8 x_i exactly, so g_8l = g_l8) in another */
static void SIMD(gram_rows)(const double *restrict X, int n, int ldx, int q, double *restrict g)
{
    if (q == 8 || q == 9) {
        for (int h = 0; h < 8; h += VL) {
            VEC acc[9], last = SIMD(splat)(0.0);
            double corner = 0.0;
            for (int i = 0; i < 9; i++)
                acc[i] = SIMD(splat)(0.0);
            for (int p = 0; p < n; p++) {
                const double *row = X + (size_t)p * ldx;
                const VEC r = SIMD(load)(row + h);
                for (int i = 0; i < 8; i++)
                    acc[i] += SIMD(splat)(row[i]) * r;
                if (q == 9) {
                    const VEC xv = SIMD(splat)(row[8]);
                    acc[8] += xv * r;
                    last += r * xv; /* rows h .. h + VL of the ninth column */
                    if (h == 0)
                        corner += row[8] * row[8];
                }
            }
            for (int i = 0; i < 8; i++)
                SIMD(store)(g + i * q + h, acc[i]);
            if (q == 9) {
                SIMD(store)(g + 8 * q + h, acc[8]);
                for (int l = 0; l < VL; l++)
                    g[(h + l) * q + 8] = last[l];
                if (h == 0)
                    g[8 * q + 8] = corner;
            }
        }
        return;
    }
    for (int i = 0; i < q * q; i++)
        g[i] = 0.0;
    for (int p = 0; p < n; p++) {
        const double *row = X + (size_t)p * ldx;
        for (int i = 0; i < q; i++) {
            const double xi = row[i];
            double *gi = g + i * q;
            for (int l = 0; l < q; l++)
                gi[l] += xi * row[l];
        }
    }
}

/* Row p of lower_solve_rows on the cnt blocks of VL columns starting at j[u]: each block
 * from bp's values on entry (so a block may overlap another), bp <- (alpha bp - sum_{q<p}
 * L_pq b_q) / L_pp in vector accumulators, stored at the end */
__attribute__((always_inline)) static inline void
SIMD(solve_row_blocks)(const double *restrict lp, int p, const double *restrict B, int ldb,
                       double *restrict bp, double alpha, const int *j, int cnt)
{
    const VEC va = SIMD(splat)(alpha), vd = SIMD(splat)(lp[p]);
    VEC acc[4];
    for (int u = 0; u < cnt; u++)
        acc[u] = SIMD(load)(bp + j[u]) * va;
    for (int q = 0; q < p; q++) {
        const double *bq = B + (size_t)q * ldb;
        const VEC lv = SIMD(splat)(lp[q]);
        for (int u = 0; u < cnt; u++) {
            acc[u] -= lv * SIMD(load)(bq + j[u]);
        }
    }
    for (int u = 0; u < cnt; u++) {
        acc[u] /= vd;
        SIMD(store)(bp + j[u], acc[u]);
    }
}

/* B <- alpha L^-1 B by forward substitution over rows, b_p <- (alpha b_p - sum_{q<p} L_pq
 * b_q) / L_pp: L (n, n) lower triangular and row-major, B (n, cols) row-major with row stride
 * ldb (each row a vector of the cols right-hand sides). With cols >= VL, four blocks of VL
 * columns at a time in independent vector accumulators, plus one at cols - VL when cols is
 * not a multiple of VL, which overlaps the block before it (the same values again); the
 * groups run from the last, so that a block and its overlapping neighbour share a group and
 * every block starts from the values on entry. */
static void SIMD(lower_solve_rows)(const double *restrict L, int n, double *restrict B, int ldb,
                                   int cols, double alpha)
{
    if (cols < VL) {
        for (int p = 0; p < n; p++) {
            double *bp = B + (size_t)p * ldb;
            const double *lp = L + (size_t)p * n;
            for (int j = 0; j < cols; j++) {
                double acc = bp[j] * alpha;
                for (int q = 0; q < p; q++)
                    acc -= lp[q] * B[(size_t)q * ldb + j];
                bp[j] = acc / lp[p];
            }
        }
        return;
    }
    const int nf = cols / VL, nb = nf + (cols % VL != 0);
    for (int p = 0; p < n; p++) {
        double *bp = B + (size_t)p * ldb;
        const double *lp = L + (size_t)p * n;
        for (int g = nb; g > 0; g -= 4) {
            const int g0 = g >= 4 ? g - 4 : 0, cnt = g - g0;
            int j[4];
            for (int u = 0; u < cnt; u++)
                j[u] = g0 + u < nf ? VL * (g0 + u) : cols - VL;
            switch (cnt) { /* constant counts: the accumulators stay in registers */
            case 4:
                SIMD(solve_row_blocks)(lp, p, B, ldb, bp, alpha, j, 4);
                break;
            case 3:
                SIMD(solve_row_blocks)(lp, p, B, ldb, bp, alpha, j, 3);
                break;
            case 2:
                SIMD(solve_row_blocks)(lp, p, B, ldb, bp, alpha, j, 2);
                break;
            default:
                SIMD(solve_row_blocks)(lp, p, B, ldb, bp, alpha, j, 1);
            }
        }
    }
}

/* The exponents of Kt (c, Mp) of learner k at x (b) (eq. 21) into e, from the differences:
 * log s_i - 1/2 sum_d (x_d - o_jd)^2 / l_id^2 (ind_xit (K, b, Mp) the inducing inputs by
 * dimension, log_var (K, c), il2 (K, c, b)), the squares sq (b, Mp) as scratch; OVERFLOW when
 * one is NaN. */
static int SIMD(exponents)(const Dims *D, const double *ind_xit, const double *log_var,
                           const double *il2, int k, const double *x, double *restrict e,
                           double *restrict sq)
{
    const size_t b = (size_t)D->b, c = (size_t)D->c, mp = (size_t)D->mp;
    const double *O = ind_xit + (size_t)k * b * mp, *L2 = il2 + (size_t)k * c * b;
    const double *lv = log_var + (size_t)k * c;
    for (size_t d = 0; d < b * mp; d += mp) {
        const double xd = x[d / mp], *od = O + d;
        double *row = sq + d;
        for (size_t j = 0; j < mp; j++) {
            const double t = xd - od[j];
            row[j] = t * t;
        }
    }
    for (size_t i = 0; i < c; i += 2) /* the sums over d in order, two kernels at a time */
        SIMD(weighted_row_sums2)(sq, mp, L2 + i * b, i + 1 < c ? L2 + (i + 1) * b : NULL,
                                 (int)b, (int)mp, e + i * mp, i + 1 < c ? e + (i + 1) * mp : NULL);
    int bad = 0;
    for (size_t i = 0; i < c; i++) {
        double *er = e + i * mp;
        for (size_t j = 0; j < mp; j++) {
            er[j] = lv[i] - 0.5 * er[j];
            bad |= isnan(er[j]);
        }
    }
    return bad ? OVERFLOW : 0;
}

/* acc (cnt) = log s - 1/2 sum_d w_d (wxt[d, t] - x_d)^2: one kernel's exponents at the window
 * samples t (wxt (b, P), the samples' inputs by dimension) */
static void SIMD(window_exponents)(double *restrict acc, const double *restrict w, double lv,
                                   const double *restrict x, const double *restrict wxt, int b,
                                   int P, int cnt)
{
    for (int t = 0; t < cnt; t++)
        acc[t] = 0.0;
    for (int d = 0; d < b; d++) {
        const double wd = w[d], xd = x[d], *row = wxt + (size_t)d * P;
        for (int t = 0; t < cnt; t++) {
            const double e = row[t] - xd;
            acc[t] += wd * (e * e);
        }
    }
    for (int t = 0; t < cnt; t++)
        acc[t] = lv - 0.5 * acc[t];
}

/* y += a (x * w) elementwise (n) */
static void SIMD(add_scaled_product)(double *restrict y, double a, const double *restrict x,
                                     const double *restrict w, int n)
{
    for (int t = 0; t < n; t++)
        y[t] += a * (x[t] * w[t]);
}

/* k_new (mp) = ub' (Kt * Ubar) of one learner (eq. 22): the rows of kt (c, mp) are scaled
 * in place by those of U (the inducing points' ubar, transposed), then summed with weights
 * ub in order */
static void SIMD(kernel_row)(double *restrict kt, const double *restrict U,
                             const double *restrict ub, int c, int mp, double *restrict kn)
{
    for (int i = 0; i < c * mp; i++)
        kt[i] *= U[i];
    SIMD(weighted_row_sums2)(kt, (size_t)mp, ub, NULL, c, mp, kn, NULL);
}

/* One learner's window step on [r, S] st (mp, mp + 1) (eqs. 24-26): st += s kn [z, kn'] (zs =
 * z s) and, when full, + f ko [z_old, ko'] (zo = z_old f); then the slot's kernel row ko <- kn.
 * Returns kn' K_oo^-1 kn (eq. 27) with Ki = K_oo^-1. */
static double SIMD(window_step)(double *restrict st, const double *restrict kn,
                                double *restrict ko, double s, double zs, int full, double f,
                                double zo, const double *restrict Ki, int mp)
{
    if (full) {
        for (int p = 0; p < mp; p++) {
            double *row = st + p * (mp + 1);
            const double kp = kn[p], op = ko[p];
            row[0] += kp * zs + op * zo;
            SIMD(axpby)(row + 1, kp * s, kn, op * f, ko, mp);
        }
    } else {
        for (int p = 0; p < mp; p++) {
            double *row = st + p * (mp + 1);
            row[0] += kn[p] * zs;
            SIMD(axpy)(row + 1, kn[p] * s, kn, mp);
        }
    }
    memcpy(ko, kn, sizeof(double) * (size_t)mp);
    double v[MAXW];
    SIMD(symv_inline)(Ki, kn, mp, v);
    double q = 0.0;
    for (int p = 0; p < mp; p++)
        q += kn[p] * v[p];
    return q;
}

/* The window step on the whitened statistics A (mp, mp) = L^-1 S L^-T: A += s l l' and,
 * when full, + f lo lo' (l = L^-1 kn, lo = L^-1 ko), as window_step on S. */
static void SIMD(whitened_step)(double *restrict A, const double *restrict l,
                                const double *restrict lo, double s, int full, double f, int mp)
{
    for (int p = 0; p < mp; p++) {
        if (full)
            SIMD(axpby)(A + (size_t)p * mp, l[p] * s, l, lo[p] * f, lo, mp);
        else
            SIMD(axpy)(A + (size_t)p * mp, l[p] * s, l, mp);
    }
}

/* exp(v) for a vector inside [EXP_LO, EXP_HI], by the steps of vexp_one (_bank.c) */
__attribute__((always_inline)) static inline VEC SIMD(exp_in_range)(VEC v)
{
    typedef unsigned long long uvec __attribute__((vector_size(8 * VL)));
    const VEC t = v * EXP_INV_LN2 + EXP_SHIFT, k = t - EXP_SHIFT;
    const VEC r = (v - k * EXP_LN2_HI) - k * EXP_LN2_LO, r2 = r * r, r4 = r2 * r2;
    const VEC p = EXP_REDUCED(r, r2, r4);
    return (VEC)((uvec)p + ((uvec)t << 52)); /* p 2^k: k in t's low bits, wrapping */
}

/* whether every lane of v lies in [EXP_LO, EXP_HI] (not NaN) */
__attribute__((always_inline)) static inline int SIMD(exp_range_ok)(VEC v)
{
    typedef long long ivec __attribute__((vector_size(8 * VL)));
    const ivec ok = (v >= EXP_LO) & (v <= EXP_HI);
    long long all = -1;
    for (int l = 0; l < VL; l++)
        all &= ok[l];
    return all != 0;
}

/* x <- exp(x) in place (n): the same digits as vexp_one on every element, 2 VL at a time; a
 * vector with a lane outside [EXP_LO, EXP_HI] or NaN by vexp_one. */
static void SIMD(vexp)(double *restrict x, Py_ssize_t n)
{
    Py_ssize_t i = 0;
    for (; i + 2 * VL <= n; i += 2 * VL) {
        const VEC a = SIMD(load)(x + i), b = SIMD(load)(x + i + VL);
        if (SIMD(exp_range_ok)(a) && SIMD(exp_range_ok)(b)) {
            SIMD(store)(x + i, SIMD(exp_in_range)(a));
            SIMD(store)(x + i + VL, SIMD(exp_in_range)(b));
        } else {
            for (int l = 0; l < 2 * VL; l++)
                x[i + l] = vexp_one(x[i + l]);
        }
    }
    for (; i < n; i++)
        x[i] = vexp_one(x[i]);
}

/* this copy's entry points */
static const Simd SIMD(table) = {
    .name = SIMD_NAME,
    .weighted_row_sums = SIMD(weighted_row_sums),
    .symv = SIMD(symv),
    .gram_rows = SIMD(gram_rows),
    .lower_solve_rows = SIMD(lower_solve_rows),
    .exponents = SIMD(exponents),
    .window_exponents = SIMD(window_exponents),
    .add_scaled_product = SIMD(add_scaled_product),
    .kernel_row = SIMD(kernel_row),
    .window_step = SIMD(window_step),
    .whitened_step = SIMD(whitened_step),
    .vexp = SIMD(vexp),
};

#undef VEC
