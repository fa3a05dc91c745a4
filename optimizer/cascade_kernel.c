/* Cascade quadrature of the original model under piecewise-constant rates, compiled.
 *
 * The same algorithm as optimizer/cascade.py's integrate_cascade(constant_pieces=True), step
 * for step (same panels, same refinement decisions, same error estimate), without numpy's
 * per-operation overhead: for a 12-panel, 12-node plan of 3 joints the numpy code spends
 * most of its ~1 ms in a hundred small array operations. optimizer/cascade_kernel.py loads
 * it with ctypes; the quadrature rule and the model come from Python, so that both paths
 * share one definition of every matrix.
 *
 * Model: phi' = u1, th1' = u2, th_i' = K_i cos(th_{i-1})^m_i u1 (i = 2..n), and the energy
 * u1^2 + u2^2. Rates are constant on every panel (a panel never straddles a piece of the
 * schedule; cut panels inherit their parent's rates).
 */
#include <math.h>
#include <stdlib.h>
#include <string.h>

#define CK_OK 0
#define CK_NONFINITE 1
#define CK_NOMEM 2
#define CK_CAPACITY 3

/* din:     n, p, P0 (initial panels), split (children per cut panel), max_rounds,
 *          max_panels, tail, M (samples), capacity (panels the outputs can hold) (integers,
 *          as doubles); tol, half_pi, plateau, noise, T; gains (n-1), exponents (n-1);
 *          q0 (nq); initial panels a (P0), h (P0), u1 (P0), u2 (P0); t_eval (M)
 * rule:    x (p), cum_total ((p+1) x p, row p = total), to_coef (p x p), xb (p+2), wb (p+2),
 *          cut_starts (split), cut_widths (split)
 * dout:    panels, rounds, bounded, evaluations (integers, as doubles); energy, estimate,
 *          singular_time (NaN: none); q at t_eval (M x nq); mesh_t (rows),
 *          mesh_q (rows x nq), rows = capacity (p+1) + 1: every panel's start and nodes,
 *          then T (P (p+1) + 1 of them are used). More than capacity panels: CK_CAPACITY,
 *          panels = P, and the caller runs again.
 */

typedef struct {
    int n, nq, p, split, tail;
    const double *x, *cum, *total, *to_coef, *xb, *wb;
    const double *gains, *exps;
    const double *q0;
    double share, plateau, noise;
} Ctx;

typedef struct {
    int P;
    double *F;     /* (nq + 1) x P x p: u1, u2, joint integrands, energy */
    double *X;     /* nq x P x p: states at the nodes */
    double *ends;  /* nq x (P + 1): states at the panel ends */
    double *err;   /* (nq + 1) x P: tails (zero for the rates and the energy) */
    double *lam;   /* n - 1 */
    double energy;
} Pass;

static void pass_free(Pass *w) {
    free(w->F); free(w->X); free(w->ends); free(w->err); free(w->lam);
    memset(w, 0, sizeof *w);
}

static int pass_alloc(Pass *w, const Ctx *c, int P) {
    pass_free(w);
    w->P = P;
    w->F = malloc(sizeof(double) * (size_t)(c->nq + 1) * P * c->p);
    w->X = malloc(sizeof(double) * (size_t)c->nq * P * c->p);
    w->ends = malloc(sizeof(double) * (size_t)c->nq * (P + 1));
    w->err = calloc((size_t)(c->nq + 1) * P, sizeof(double));
    w->lam = malloc(sizeof(double) * (size_t)(c->n > 1 ? c->n - 1 : 1));
    return (w->F && w->X && w->ends && w->err && w->lam) ? CK_OK : CK_NOMEM;
}

/* out (rows) = A (rows x cols, row-major) f (cols): the column loop outside, so that the
 * rows' sums are independent chains (a dot product per row is bound by the adds' latency) */
static void matvec(int rows, int cols, const double *A, const double *f, double *out) {
    for (int r = 0; r < rows; r++) out[r] = 0.0;
    for (int k = 0; k < cols; k++) {
        const double fk = f[k];
        for (int r = 0; r < rows; r++) out[r] += A[(size_t)r * cols + k] * fk;
    }
}

/* |Chebyshev coefficients| of the values f (p) */
static void coefficients(const Ctx *c, const double *f, double *out) {
    matvec(c->p, c->p, c->to_coef, f, out);
    for (int l = 0; l < c->p; l++) out[l] = fabs(out[l]);
}

static double tail_max(const Ctx *c, const double *C) {
    double t = 0.0;
    for (int l = c->p - c->tail; l < c->p; l++) t = C[l] > t ? C[l] : t;
    return t;
}

/* a plateau of rounding noise (cascade.py's _noise) */
static int is_noise(const Ctx *c, const double *C) {
    int p = c->p;
    int lo = p / 2 < p - c->tail - 1 ? p / 2 : p - c->tail - 1;
    double tail = tail_max(c, C), mid = 0.0, top = 0.0;
    for (int l = lo; l < p - c->tail; l++) mid = C[l] > mid ? C[l] : mid;
    for (int l = 0; l < p; l++) top = C[l] > top ? C[l] : top;
    return tail >= c->plateau * mid && tail <= c->noise * top;
}

/* The cascade on the mesh (a, h, u1, u2 in time order): states, energy, Lambda_i, tails. */
/* w->F[0], w->F[1] hold u1, u2 at the nodes (filled by the caller) */
static int cascade_pass(const Ctx *c, Pass *w, const double *h, double *coef_out) {
    const int P = w->P, p = c->p, nq = c->nq, n = c->n;
    const size_t Pp = (size_t)P * p;
    const double *u1 = w->F, *u2 = w->F + Pp;
    double *R = malloc(sizeof(double) * (size_t)(p + 1));
    double *cosx = malloc(sizeof(double) * Pp * (size_t)(n > 1 ? n - 1 : 1));
    if (!R || !cosx) { free(R); free(cosx); return CK_NOMEM; }
    for (size_t i = 0; i < Pp; i++) w->F[(size_t)nq * Pp + i] = u1[i] * u1[i] + u2[i] * u2[i];
    for (int s = 0; s < nq; s++) {
        const double *Fs = w->F + (size_t)s * Pp;
        double *Xs = w->X + (size_t)s * Pp;
        double *es = w->ends + (size_t)s * (P + 1);
        double run = 0.0;
        es[0] = c->q0[s];
        for (int j = 0; j < P; j++) {
            const double half = 0.5 * h[j];
            matvec(p + 1, p, c->cum, Fs + (size_t)j * p, R);
            for (int r = 0; r <= p; r++) R[r] *= half;
            for (int k = 0; k < p; k++) Xs[j * p + k] = R[k] + es[j];
            run += R[p];
            es[j + 1] = run + c->q0[s];
        }
        if (s >= 1 && s < n) {  /* th_s drives th_{s+1} */
            double *cs = cosx + (size_t)(s - 1) * Pp;
            double *Fn = w->F + (size_t)(s + 1) * Pp;
            const double K = c->gains[s - 1];
            const int m = (int)c->exps[s - 1];
            for (size_t i = 0; i < Pp; i++) {
                double cv = cos(Xs[i]), pw = cv;
                for (int e = 1; e < m; e++) pw = pw * cv;
                cs[i] = cv;
                Fn[i] = K * pw * u1[i];
            }
        }
    }
    /* energy = sum_j half_j sum_k total_k (u1^2 + u2^2) */
    {
        const double *Fe = w->F + (size_t)nq * Pp;
        double en = 0.0;
        for (int j = 0; j < P; j++) {
            double acc = 0.0;
            for (int k = 0; k < p; k++) acc += Fe[j * p + k] * c->total[k];
            en += acc * (0.5 * h[j]);
        }
        w->energy = en;
    }
    /* Lambda_i = K_i m_i int |cos^(m_i - 1) sin u1| dt, i = 2..n */
    for (int i = 0; i < n - 1; i++) {
        const double *cs = cosx + (size_t)i * Pp, *Xs = w->X + (size_t)(i + 1) * Pp;
        const int mm = (int)c->exps[i] - 1;  /* integer exponents (the model's) */
        double acc_all = 0.0;
        for (int j = 0; j < P; j++) {
            double acc = 0.0;
            for (int k = 0; k < p; k++) {
                size_t idx = (size_t)j * p + k;
                double pw = 1.0;
                for (int e = 0; e < mm; e++) pw *= cs[idx];
                acc += fabs(pw * sin(Xs[idx]) * u1[idx]) * c->total[k];
            }
            acc_all += acc * (0.5 * h[j]);
        }
        w->lam[i] = c->gains[i] * c->exps[i] * acc_all;
    }
    /* tails of the joints' integrands (the rates' and the energy's quadrature is exact) */
    for (int s = 2; s < nq; s++)
        for (int j = 0; j < P; j++) {
            /* the magnitudes kept in coef_out ((n-1) x P x p) when asked for */
            double *C = coef_out ? coef_out + ((size_t)(s - 2) * P + j) * p : R;
            coefficients(c, w->F + (size_t)s * Pp + (size_t)j * p, C);
            w->err[(size_t)s * P + j] = 2.0 * h[j] * tail_max(c, C);
        }
    free(R);
    free(cosx);
    return CK_OK;
}

/* chain[j - 1] = max(1, max_i prod_{l=j+1..i} Lambda_l), j = 1..n */
static void chain_weights(int n, const double *lam, double *chain) {
    chain[n - 1] = 1.0;
    for (int i = n - 2; i >= 0; i--) {
        double v = lam[i] * chain[i + 1];
        chain[i] = v > 1.0 ? v : 1.0;
    }
}

/* panels to cut: some joint integrand's weighted tail over the panel's share, not noise */
static int mark_panels(const Ctx *c, const Pass *w, const double *h, const double *chain,
                       unsigned char *mark) {
    const int P = w->P, p = c->p;
    const size_t Pp = (size_t)P * p;
    int count = 0;
    double C[64];
    for (int j = 0; j < P; j++) {
        const double limit = c->share * h[j];
        mark[j] = 0;
        for (int s = 2; s < c->nq && !mark[j]; s++) {
            if (!(w->err[(size_t)s * P + j] * chain[s - 1] > limit)) continue;
            coefficients(c, w->F + (size_t)s * Pp + (size_t)j * p, C);
            if (!is_noise(c, C)) mark[j] = 1;
        }
        count += mark[j];
    }
    return count;
}

/* barycentric weights wd (nb = p + 2) at the local time d0, and their sum */
static double bary(const Ctx *c, double d0, double *wd) {
    const int nb = c->p + 2;
    double den = 0.0;
    for (int k = 0; k < nb; k++) {
        wd[k] = c->wb[k] / (d0 - c->xb[k]);
        den += wd[k];
    }
    return den;
}

/* the point nearest d0 (d0 on a point: the barycentric formula is not finite there) */
static int nearest(const Ctx *c, double d0) {
    double best = INFINITY;
    int at = 0;
    for (int k = 0; k < c->p + 2; k++)
        if (fabs(d0 - c->xb[k]) < best) { best = fabs(d0 - c->xb[k]); at = k; }
    return at;
}

/* The outputs on the final mesh: mesh_t, mesh_q (every panel's start and nodes, then T),
 * the samples q_out at t_eval (clipped to [0, T]) and the first time a joint th_1..th_{n-1}
 * is outside (0, pi/2) at a node, a panel end or a sample (NaN: never). */
static double outputs(const Ctx *c, int P, const double *a, const double *h, const double *X,
                      const double *ends, double T, double half_pi, int M,
                      const double *t_eval, double *q_out, double *mesh_t, double *mesh_q) {
    const int p = c->p, nq = c->nq, n = c->n;
    const size_t Pp = (size_t)P * p;
    /* mesh: every panel's start and nodes, then T */
    double wd[64];
    for (int j = 0; j < P; j++) {
        const double half = 0.5 * h[j];
        for (int r = 0; r <= p; r++) {
            size_t row = (size_t)j * (p + 1) + r;
            mesh_t[row] = a[j] + half * (c->xb[r] + 1.0);
            for (int s = 0; s < nq; s++)
                mesh_q[row * nq + s] = r == 0 ? ends[(size_t)s * (P + 1) + j]
                                              : X[(size_t)s * Pp + (size_t)j * p + r - 1];
        }
    }
    mesh_t[(size_t)P * (p + 1)] = T;
    for (int s = 0; s < nq; s++)
        mesh_q[(size_t)P * (p + 1) * nq + s] = ends[(size_t)s * (P + 1) + P];
    /* singularity at the nodes and panel ends (samples below) */
    double sing = NAN;
    for (int j = 0; j < P && isnan(sing); j++)
        for (int r = 0; r <= p && isnan(sing); r++) {
            const double *row = mesh_q + ((size_t)j * (p + 1) + r) * nq;
            for (int s = 1; s < n; s++)
                if (row[s] <= 0.0 || row[s] >= half_pi) { sing = mesh_t[(size_t)j * (p + 1) + r]; break; }
        }
    for (int s = 1; s < n && !(sing <= T); s++) {
        double v = ends[(size_t)s * (P + 1) + P];
        if (v <= 0.0 || v >= half_pi) sing = T;
    }
    /* samples: the integrated interpolant (degree p) through the panel ends and nodes */
    for (int i = 0; i < M; i++) {
        double te = t_eval[i] < 0.0 ? 0.0 : (t_eval[i] > T ? T : t_eval[i]);
        int lo = 0, hi = P;  /* first panel whose start is > te, minus one */
        while (lo < hi) { int mid = (lo + hi) / 2; if (a[mid] <= te) lo = mid + 1; else hi = mid; }
        int j = lo - 1 < 0 ? 0 : lo - 1;
        double d0 = 2.0 * (te - a[j]) / h[j] - 1.0;
        double den = bary(c, d0, wd);
        /* the panel's p + 2 points (start, nodes, end) are consecutive rows of the mesh */
        const double *Xb = mesh_q + (size_t)j * (p + 1) * nq;
        double *qi = q_out + (size_t)i * nq;
        for (int s = 0; s < nq; s++) {
            double acc0 = 0.0, acc1 = 0.0;  /* two chains: the sum's latency halved */
            int k = 0;
            for (; k + 1 < p + 2; k += 2) {
                acc0 += wd[k] * Xb[(size_t)k * nq + s];
                acc1 += wd[k + 1] * Xb[(size_t)(k + 1) * nq + s];
            }
            if (k < p + 2) acc0 += wd[k] * Xb[(size_t)k * nq + s];
            qi[s] = (acc0 + acc1) / den;
        }
        if (!isfinite(qi[0])) {  /* as cascade.py: phi decides whether the formula holds */
            const int at = nearest(c, d0);
            for (int s = 0; s < nq; s++) qi[s] = Xb[(size_t)at * nq + s];
        }
        for (int s = 1; s < n; s++)
            if ((qi[s] <= 0.0 || qi[s] >= half_pi) && !(sing <= te)) sing = te;
    }
    return sing;
}

int cascade_constant_pieces(const double *din, const double *rule, double *dout) {
    Ctx c;
    const int n = (int)din[0], p = (int)din[1], P0 = (int)din[2], split = (int)din[3];
    const int max_rounds = (int)din[4], max_panels = (int)din[5], M = (int)din[7];
    const int capacity = (int)din[8];
    const size_t rows = (size_t)capacity * (p + 1) + 1;
    const double *dparams = din + 9, *model = dparams + 5, *q0 = model + 2 * (n - 1);
    const double *panels0 = q0 + (n + 1), *t_eval = panels0 + 4 * (size_t)P0;
    double *counts = dout, *scalars = dout + 4, *q_out = dout + 7;
    double *mesh_t = q_out + (size_t)M * (n + 1), *mesh_q = mesh_t + rows;
    const double tol = dparams[0], half_pi = dparams[1], T = dparams[4];
    c.n = n; c.nq = n + 1; c.p = p; c.split = split; c.tail = (int)din[6];
    c.x = rule;
    c.cum = rule + p;
    c.total = c.cum + (size_t)p * p;
    c.to_coef = c.cum + (size_t)(p + 1) * p;
    c.xb = c.to_coef + (size_t)p * p;
    c.wb = c.xb + p + 2;
    const double *cut_starts = c.wb + p + 2, *cut_widths = cut_starts + split;
    c.gains = model; c.exps = model + (n - 1);
    c.q0 = q0;
    c.share = tol / T / (double)(c.nq + 1);
    c.plateau = dparams[2]; c.noise = dparams[3];
    if (p + 2 > 64) return CK_NOMEM;

    int cap = max_panels > P0 ? max_panels : P0;
    double *a = malloc(sizeof(double) * cap), *h = malloc(sizeof(double) * cap);
    double *u1 = malloc(sizeof(double) * cap), *u2 = malloc(sizeof(double) * cap);
    double *chain = malloc(sizeof(double) * (size_t)n);
    unsigned char *mark = malloc((size_t)cap);
    Pass w;
    memset(&w, 0, sizeof w);
    int status = (a && h && u1 && u2 && chain && mark) ? CK_OK : CK_NOMEM;
    int P = P0, rounds = 0, bounded = 0, evaluations = P0;
    if (status == CK_OK) {
        memcpy(a, panels0, sizeof(double) * P0);
        memcpy(h, panels0 + P0, sizeof(double) * P0);
        memcpy(u1, panels0 + 2 * P0, sizeof(double) * P0);
        memcpy(u2, panels0 + 3 * P0, sizeof(double) * P0);
    }
    while (status == CK_OK) {
        status = pass_alloc(&w, &c, P);
        if (status != CK_OK) break;
        for (int j = 0; j < P; j++)  /* constant on each panel */
            for (int k = 0; k < p; k++) {
                w.F[(size_t)j * p + k] = u1[j];
                w.F[(size_t)(P + j) * p + k] = u2[j];
            }
        status = cascade_pass(&c, &w, h, NULL);
        if (status != CK_OK) break;
        double sum = 0.0;
        for (int s = 0; s < c.nq; s++) sum += w.ends[(size_t)s * (P + 1) + P];
        if (!isfinite(sum) || !isfinite(w.energy)) { status = CK_NONFINITE; break; }
        chain_weights(n, w.lam, chain);
        int count = mark_panels(&c, &w, h, chain, mark);
        int fits = rounds < max_rounds && P + (split - 1) * count <= max_panels;
        if (!(count > 0 && fits)) { bounded = count > 0; break; }
        rounds++;
        /* cut the marked panels in place (children in time order, rates inherited) */
        int Pn = P + (split - 1) * count;
        for (int j = P - 1, dst = Pn - 1; j >= 0; j--) {
            if (mark[j]) {
                for (int i = split - 1; i >= 0; i--, dst--) {
                    a[dst] = a[j] + h[j] * cut_starts[i];
                    h[dst] = h[j] * cut_widths[i];
                    u1[dst] = u1[j];
                    u2[dst] = u2[j];
                }
            } else {
                a[dst] = a[j]; h[dst] = h[j]; u1[dst] = u1[j]; u2[dst] = u2[j];
                dst--;
            }
        }
        evaluations += split * count;
        P = Pn;
    }
    if (status == CK_OK && P > capacity) status = CK_CAPACITY;
    if (status == CK_OK) {
        /* the estimate: est_i = quad_i + Lambda_i est_{i-1}; rates and energy exact */
        const int nq = c.nq;
        double est = 0.0, estimate = 0.0;
        for (int s = 2; s < nq; s++) {
            double quad = 0.0;
            for (int j = 0; j < P; j++) quad += w.err[(size_t)s * P + j];
            est = quad + w.lam[s - 2] * est;
            estimate = est > estimate ? est : estimate;
        }
        double sing = outputs(&c, P, a, h, w.X, w.ends, T, half_pi, M, t_eval, q_out, mesh_t,
                              mesh_q);
        scalars[0] = w.energy;
        scalars[1] = estimate;
        scalars[2] = sing;
    }
    counts[0] = P; counts[1] = rounds; counts[2] = bounded; counts[3] = evaluations;
    pass_free(&w);
    free(a); free(h); free(u1); free(u2); free(chain); free(mark);
    return status;
}

/* ---- the general case: inputs known at the nodes, the refinement loop in Python ---- */

static void rule_init(Ctx *c, int n, int p, int tail, const double *rule, const double *model,
                      const double *q0) {
    memset(c, 0, sizeof *c);
    c->n = n; c->nq = n + 1; c->p = p; c->tail = tail;
    c->x = rule;
    c->cum = rule + p;
    c->total = c->cum + (size_t)p * p;
    c->to_coef = c->cum + (size_t)(p + 1) * p;
    c->xb = c->to_coef + (size_t)p * p;
    c->wb = c->xb + p + 2;
    c->gains = model; c->exps = model ? model + (n - 1) : NULL;
    c->q0 = q0;
}

/* One cascade on a mesh in time order, as cascade.py's loop body.
 * din:  n, p, P, tail; gains (n-1), exponents (n-1); q0 (nq); h (P)
 * U:    u1 (P x p), u2 (P x p) at the nodes
 * dout: energy; Lambda_2..n (n-1); X (nq x P x p); ends (nq x (P+1));
 *       tails of the joints' integrands th_2'..th_n' ((n-1) x P) and their coefficients'
 *       magnitudes ((n-1) x P x p) */
int cascade_general_pass(const double *din, const double *rule, const double *U, double *dout) {
    Ctx c;
    const int n = (int)din[0], p = (int)din[1], P = (int)din[2];
    const double *model = din + 4, *q0 = model + 2 * (n - 1), *h = q0 + (n + 1);
    if (p + 2 > 64) return CK_NOMEM;
    rule_init(&c, n, p, (int)din[3], rule, model, q0);
    const int nq = c.nq;
    const size_t Pp = (size_t)P * p;
    Pass w;
    memset(&w, 0, sizeof w);
    int status = pass_alloc(&w, &c, P);
    double *lam = dout + 1, *X = lam + (n - 1), *ends = X + (size_t)nq * Pp;
    double *err = ends + (size_t)nq * (P + 1), *coef = err + (size_t)(n - 1) * P;
    if (status == CK_OK) {
        memcpy(w.F, U, sizeof(double) * 2 * Pp);
        status = cascade_pass(&c, &w, h, coef);
    }
    if (status == CK_OK) {
        dout[0] = w.energy;
        memcpy(lam, w.lam, sizeof(double) * (n - 1));
        memcpy(X, w.X, sizeof(double) * nq * Pp);
        memcpy(ends, w.ends, sizeof(double) * nq * (P + 1));
        memcpy(err, w.err + 2 * (size_t)P, sizeof(double) * (n - 1) * P);
    }
    pass_free(&w);
    return status;
}

/* The outputs of a finished run (see outputs()).
 * din:  n, p, P, M, T, half_pi; a (P), h (P); t_eval (M)
 * X, ends: as cascade_general_pass gives them
 * dout: singular_time (NaN: none); q (M x nq); mesh_t (P (p+1) + 1); mesh_q (same rows x nq) */
int cascade_general_outputs(const double *din, const double *rule, const double *X,
                            const double *ends, double *dout) {
    Ctx c;
    const int n = (int)din[0], p = (int)din[1], P = (int)din[2], M = (int)din[3];
    const double T = din[4], half_pi = din[5];
    const double *a = din + 6, *h = a + P, *t_eval = h + P;
    if (p + 2 > 64) return CK_NOMEM;
    rule_init(&c, n, p, 4, rule, NULL, NULL);
    const size_t rows = (size_t)P * (p + 1) + 1;
    double *q_out = dout + 1, *mesh_t = q_out + (size_t)M * c.nq, *mesh_q = mesh_t + rows;
    dout[0] = outputs(&c, P, a, h, X, ends, T, half_pi, M, t_eval, q_out, mesh_t, mesh_q);
    return CK_OK;
}
