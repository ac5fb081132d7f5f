/* bsipipe.imaging._kernels: the per-frame sub-pixel fits of bsipipe.imaging.detect, compiled.
 *
 * SPDX-License-Identifier: GPL-3.0-or-later
 *
 * The tracker measures about a dozen small patches a frame; in NumPy each step of the
 * iterated centroid and of the Levenberg-Marquardt Gaussian fit is one call over all the
 * patches, so a frame costs a few hundred calls whatever the patches' size.  These loops do
 * the same arithmetic patch by patch in one call.  They follow detect._centroid_numpy and
 * detect._gaussian_fit_numpy operation for operation (the same formulas, clamps, NaN
 * propagation, acceptance of steps and stopping rule, the Gaussian fit's stopping rule
 * taken over the whole batch as NumPy's is); only the order of summation differs, so the
 * values agree to rounding (tests/test_detect_kernels.py holds them to that).
 *
 * Arrays arrive through the buffer protocol (C-contiguous float64, intp for indices, uint8
 * for masks); the Python side (detect.py) checks and converts them.  No NumPy C API: the
 * module builds with the compiler and Python headers alone.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <string.h>
#include <stdlib.h>

/* NumPy's minimum(maximum(x, lo), hi): NaN stays NaN */
static inline double clampd(double x, double lo, double hi)
{
    if (x < lo) x = lo;
    if (x > hi) x = hi;
    return x;
}

/* One array argument: the object, its item size, its number of items (-1: any number, for the
 * index arrays whose lengths size the rest), writable or not, None allowed or not, its name
 * for the error message. */
typedef struct {
    PyObject *o;
    Py_ssize_t item, count;
    int writable, optional;
    const char *name;
} Arg;

#define IDX ((Py_ssize_t)sizeof(Py_ssize_t))

/* Release b[0..m) (a buffer never acquired, zeroed, is skipped by PyBuffer_Release). */
static void release(Py_buffer *b, int m)
{
    for (int q = 0; q < m; q++)
        PyBuffer_Release(&b[q]);
}

/* Acquire args[0..m) into b[0..m): C-contiguous, their item sizes and counts checked; an
 * optional None is left as a zeroed buffer (.buf NULL).  On failure the ones already held
 * are released and -1 returned with the exception set. */
static int acquire(const Arg *args, int m, Py_buffer *b)
{
    memset(b, 0, sizeof(Py_buffer) * (size_t)m);
    for (int q = 0; q < m; q++) {
        const Arg *a = &args[q];
        if (a->optional && a->o == Py_None)
            continue;
        if (PyObject_GetBuffer(a->o, &b[q], PyBUF_C_CONTIGUOUS | (a->writable ? PyBUF_WRITABLE : 0)) < 0) {
            release(b, q);
            return -1;
        }
        if (b[q].itemsize != a->item || (a->count >= 0 && b[q].len != a->item * a->count)) {
            PyErr_Format(PyExc_ValueError, "%s: expected %zd items of %zd bytes, got %zd bytes of %zd-byte items",
                         a->name, a->count, a->item, b[q].len, b[q].itemsize);
            release(b, q + 1);
            return -1;
        }
    }
    return 0;
}

/* 0 where every index in idx[0..k) lies in [lo, hi); else -1 with an IndexError naming them */
static int indices_within(const Py_ssize_t *idx, Py_ssize_t k, Py_ssize_t lo, Py_ssize_t hi, const char *what)
{
    for (Py_ssize_t j = 0; j < k; j++) {
        if (idx[j] < lo || idx[j] >= hi) {
            PyErr_Format(PyExc_IndexError, "%s index outside the patch", what);
            return -1;
        }
    }
    return 0;
}

/* The index array ``o`` (intp) into ix[0], its length into *count, every index checked to lie
 * in [lo, hi): the array whose length sizes a kernel's other arguments.  -1 with the exception
 * set (and nothing held) on failure. */
static int acquire_index(PyObject *o, const char *name, Py_ssize_t lo, Py_ssize_t hi, Py_buffer *ix,
                         Py_ssize_t *count)
{
    const Arg a[] = {{o, IDX, -1, 0, 0, name}};
    if (acquire(a, 1, ix) < 0)
        return -1;
    *count = ix[0].len / IDX;
    if (indices_within((const Py_ssize_t *)ix[0].buf, *count, lo, hi, name) < 0) {
        release(ix, 1);
        return -1;
    }
    return 0;
}

/* LAPACK dgesv's method on one k x k system: LU with partial pivoting (idamax's choice: the
 * first largest |a| of the column, NaN never), then the two triangular solves; in place (A
 * row-major k x k, b overwritten by the solution).  Returns 1 where a pivot is exactly zero
 * (LAPACK's "singular": np.linalg.solve raises LinAlgError), else 0. */
static int solve_n(double *A, double *b, int k)
{
    for (int j = 0; j < k; j++) {
        int p = j;
        double best = fabs(A[j * k + j]);
        for (int r = j + 1; r < k; r++) {
            double v = fabs(A[r * k + j]);
            if (v > best) {
                best = v;
                p = r;
            }
        }
        if (A[p * k + j] == 0.0)
            return 1;
        if (p != j) {
            for (int c = 0; c < k; c++) {
                double t = A[j * k + c];
                A[j * k + c] = A[p * k + c];
                A[p * k + c] = t;
            }
            double t = b[j];
            b[j] = b[p];
            b[p] = t;
        }
        double inv = 1.0 / A[j * k + j];
        for (int r = j + 1; r < k; r++) {
            double f = A[r * k + j] * inv;
            A[r * k + j] = f;
            for (int c = j + 1; c < k; c++)
                A[r * k + c] -= f * A[j * k + c];
            b[r] -= f * b[j];
        }
    }
    for (int r = k - 1; r >= 0; r--) {
        double v = b[r];
        for (int c = r + 1; c < k; c++)
            v -= A[r * k + c] * b[c];
        b[r] = v / A[r * k + r];
    }
    return 0;
}

/* centroid(s, n, PP, support, X, Y, w0, radius, n_iter, c_out, m_out, elong_out)
 *
 * s (n, PP) patches; support (K,) intp indices into a patch; X, Y, w0 (K,); outputs c (n, 2),
 * m (n,), elong (n,).  detect._centroid_numpy's iterated soft-disc centroid. */
static PyObject *centroid(PyObject *self, PyObject *args)
{
    PyObject *o_s, *o_sup, *o_X, *o_Y, *o_w0, *o_c, *o_m, *o_e;
    Py_ssize_t n, PP, K;
    double radius;
    int n_iter;
    if (!PyArg_ParseTuple(args, "OnnOOOOdiOOO", &o_s, &n, &PP, &o_sup, &o_X, &o_Y, &o_w0, &radius, &n_iter,
                          &o_c, &o_m, &o_e))
        return NULL;
    Py_buffer ix[1], b[7];
    if (acquire_index(o_sup, "support", 0, PP, ix, &K) < 0)
        return NULL;
    const Arg arr[] = {{o_s, 8, n * PP, 0, 0, "s"}, {o_X, 8, K, 0, 0, "X"}, {o_Y, 8, K, 0, 0, "Y"},
                       {o_w0, 8, K, 0, 0, "w0"}, {o_c, 8, 2 * n, 1, 0, "c"}, {o_m, 8, n, 1, 0, "m"},
                       {o_e, 8, n, 1, 0, "elong"}};
    if (acquire(arr, 7, b) < 0) {
        release(ix, 1);
        return NULL;
    }
    PyObject *ret = NULL;
    double *work = NULL;
    const Py_ssize_t *sup = (const Py_ssize_t *)ix[0].buf;
    work = (double *)malloc(sizeof(double) * (size_t)(K > 0 ? 4 * K : 1));
    if (!work) {
        PyErr_NoMemory();
        goto done;
    }
    Py_BEGIN_ALLOW_THREADS                     /* no Python object is touched below */
    {
        const double *s = (const double *)b[0].buf, *X = (const double *)b[1].buf, *Y = (const double *)b[2].buf;
        const double *w0 = (const double *)b[3].buf;
        double *cout = (double *)b[4].buf, *mout = (double *)b[5].buf, *eout = (double *)b[6].buf;
        double *sp = work, *w = work + K, *ddx = work + 2 * K, *ddy = work + 3 * K;
        const double r1 = radius + 1.0, lim = 1.5;
        for (Py_ssize_t i = 0; i < n; i++) {
            const double *row = s + i * PP;
            for (Py_ssize_t k = 0; k < K; k++) {
                double v = row[sup[k]];
                sp[k] = (v < 0.0) ? 0.0 : v;          /* np.maximum(v, 0): NaN stays */
            }
            double cx = 0.0, cy = 0.0, m = 0.0, mm = 1.0;
            for (int it = 0; it <= n_iter; it++) {
                if (it == 0) {
                    for (Py_ssize_t k = 0; k < K; k++) {
                        ddx[k] = X[k];
                        ddy[k] = Y[k];
                        w[k] = sp[k] * w0[k];
                    }
                } else {
                    for (Py_ssize_t k = 0; k < K; k++) {
                        double dx = X[k] - cx, dy = Y[k] - cy;
                        ddx[k] = dx;
                        ddy[k] = dy;
                        double d = r1 - sqrt(dx * dx + dy * dy);
                        w[k] = clampd(d, 0.0, 1.0) * sp[k];
                    }
                }
                double sm = 0.0, sx = 0.0, sy = 0.0;
                for (Py_ssize_t k = 0; k < K; k++) {
                    sm += w[k];
                    sx += w[k] * ddx[k];
                    sy += w[k] * ddy[k];
                }
                m = sm;
                double nx = cx, ny = cy;
                if (m > 0.0) {
                    mm = m;
                    nx = cx + sx / m;
                    ny = cy + sy / m;
                } else {
                    mm = 1.0;
                }
                cx = clampd(nx, -lim, lim);
                cy = clampd(ny, -lim, lim);
            }
            double sxx = 0.0, syy = 0.0, sxy = 0.0;
            for (Py_ssize_t k = 0; k < K; k++) {
                double wdx = w[k] * ddx[k], wdy = w[k] * ddy[k];
                sxx += wdx * ddx[k];
                syy += wdy * ddy[k];
                sxy += wdx * ddy[k];
            }
            double ixx = sxx / mm, iyy = syy / mm, ixy = sxy / mm;
            double tr = ixx + iyy, det = ixx * iyy - ixy * ixy;
            double q = tr * tr / 4 - det;
            if (q < 0.0) q = 0.0;
            double disc = sqrt(q);
            double lo = tr / 2 - disc;
            if (lo < 1e-12) lo = 1e-12;
            cout[2 * i] = cx;
            cout[2 * i + 1] = cy;
            mout[i] = m;
            eout[i] = sqrt((tr / 2 + disc) / lo);
        }
    }
    Py_END_ALLOW_THREADS
    Py_INCREF(Py_None);
    ret = Py_None;
done:
    free(work);
    release(b, 7);
    release(ix, 1);
    return ret;
}

/* the model's values at parameters p (x0, y0, sigma, amplitude, offset) over one patch's K
 * support pixels: r2, g, the residual data - model, and the windowed cost sum(win res^2) */
static double gauss_model(const double *p, const double *S, const double *X, const double *Y, const double *win,
                          Py_ssize_t K, double *ex, double *ey, double *r2, double *g, double *res)
{
    const double a = -0.5 / (p[2] * p[2]);
    double cost = 0.0;
    for (Py_ssize_t k = 0; k < K; k++) {
        double dx = X[k] - p[0], dy = Y[k] - p[1];
        double rr = dx * dx + dy * dy;
        double gg = exp(rr * a);
        double rs = S[k] - (p[3] * gg + p[4]);
        ex[k] = dx;
        ey[k] = dy;
        r2[k] = rr;
        g[k] = gg;
        res[k] = rs;
        cost += win[k] * rs * rs;
    }
    return cost;
}

/* gaussian_fit(s, n, PP, sup, X, Y, start, valid, radius, sigma0, lim_sig, n_iter, P_out)
 *
 * s (n, PP) patches; sup (K,) intp support indices with offsets X, Y (K,); start (n, 2);
 * valid (n, PP) uint8 or None; P_out (n, 5): x0, y0, sigma, amplitude, offset.
 * detect._gaussian_fit_numpy's batched Levenberg-Marquardt fit. */
static PyObject *gaussian_fit(PyObject *self, PyObject *args)
{
    PyObject *o_s, *o_sup, *o_X, *o_Y, *o_start, *o_valid, *o_P;
    Py_ssize_t n, PP, K;
    double radius, sigma0, lim_sig;
    int n_iter;
    if (!PyArg_ParseTuple(args, "OnnOOOOOdddiO", &o_s, &n, &PP, &o_sup, &o_X, &o_Y, &o_start, &o_valid, &radius,
                          &sigma0, &lim_sig, &n_iter, &o_P))
        return NULL;
    Py_buffer ix[1], b[6];
    if (acquire_index(o_sup, "support", 0, PP, ix, &K) < 0)
        return NULL;
    const Arg arr[] = {{o_s, 8, n * PP, 0, 0, "s"}, {o_X, 8, K, 0, 0, "X"}, {o_Y, 8, K, 0, 0, "Y"},
                       {o_start, 8, 2 * n, 0, 0, "start"}, {o_valid, 1, n * PP, 0, 1, "valid"},
                       {o_P, 8, 5 * n, 1, 0, "P"}};
    if (acquire(arr, 6, b) < 0) {
        release(ix, 1);
        return NULL;
    }
    PyObject *ret = NULL;
    double *work = NULL;
    const Py_ssize_t *sup = (const Py_ssize_t *)ix[0].buf;
    /* per patch: S, win, current (ex, ey, r2, g, res), candidate (ex, ey, r2, g, res); per
     * patch scalars: lam, cost, step (5) */
    const size_t per = (size_t)(K > 0 ? K : 1);
    work = (double *)malloc(sizeof(double) * ((size_t)n * per * 7 + per * 5 + (size_t)n * 7 + 1));
    if (!work) {
        PyErr_NoMemory();
        goto done;
    }
    Py_BEGIN_ALLOW_THREADS                     /* no Python object is touched below */
    {
        const double *s = (const double *)b[0].buf, *X = (const double *)b[1].buf, *Y = (const double *)b[2].buf;
        const double *start = (const double *)b[3].buf;
        const unsigned char *valid = (const unsigned char *)b[4].buf;     /* NULL: None */
        double *P = (double *)b[5].buf;
        double *S = work, *WIN = S + n * per, *CUR = WIN + n * per;        /* CUR: n blocks of 5 K */
        double *TMP = CUR + 5 * n * per;                                    /* one block of 5 K */
        double *lam = TMP + 5 * per, *cost = lam + n, *step = cost + n;     /* step: n x 5 */
        const double r_win = radius + 1.0;
        for (Py_ssize_t i = 0; i < n; i++) {
            const double *row = s + i * PP;
            double *Si = S + i * per, *Wi = WIN + i * per;
            double amp0 = -INFINITY;
            int nan_seen = 0;
            for (Py_ssize_t k = 0; k < K; k++) {
                double dx = X[k] - start[2 * i], dy = Y[k] - start[2 * i + 1];
                double dist = hypot(dx, dy);
                double v = row[sup[k]];
                Si[k] = v;
                double w = (dist <= r_win) ? 1.0 : 0.0;
                if (valid) w *= (double)(valid[i * PP + sup[k]] != 0);
                Wi[k] = w;
                double a = v * ((dist <= 1.0) ? 1.0 : 0.0);                  /* S * (dist <= 1) */
                if (isnan(a)) nan_seen = 1;
                else if (a > amp0) amp0 = a;
            }
            if (nan_seen) amp0 = NAN;
            else if (amp0 < 1e-6) amp0 = 1e-6;
            double *p = P + 5 * i;
            p[0] = start[2 * i];
            p[1] = start[2 * i + 1];
            p[2] = sigma0;
            p[3] = amp0;
            p[4] = 0.0;
            lam[i] = 1e-3;
            double *c = CUR + 5 * i * per;
            cost[i] = gauss_model(p, Si, X, Y, Wi, K, c, c + per, c + 2 * per, c + 3 * per, c + 4 * per);
        }
        for (int it = 0; it < n_iter; it++) {
            int singular = 0;
            for (Py_ssize_t i = 0; i < n && !singular; i++) {
                const double *p = P + 5 * i, *Wi = WIN + i * per;
                const double *c = CUR + 5 * i * per;
                const double *ex = c, *ey = c + per, *r2 = c + 2 * per, *g = c + 3 * per, *res = c + 4 * per;
                const double sig = p[2], sig2 = sig * sig;
                double H[5][5] = {{0}}, gv[5] = {0};
                for (Py_ssize_t k = 0; k < K; k++) {
                    double ags = p[3] * g[k] / sig2;
                    double J[5] = {ags * ex[k], ags * ey[k], ags / sig * r2[k], g[k], 1.0};
                    double Jw[5];
                    for (int a = 0; a < 5; a++)
                        Jw[a] = J[a] * Wi[k];
                    for (int a = 0; a < 5; a++) {
                        for (int b = 0; b < 5; b++)
                            H[a][b] += Jw[a] * J[b];
                        gv[a] += Jw[a] * res[k];
                    }
                }
                for (int a = 0; a < 5; a++)
                    H[a][a] += lam[i] * (H[a][a] + 1e-12);
                singular = solve_n(&H[0][0], gv, 5);
                memcpy(step + 5 * i, gv, sizeof gv);
            }
            if (singular)
                break;                                  /* np.linalg.solve's LinAlgError */
            int all_done = 1, lam_ok = 1;
            for (Py_ssize_t i = 0; i < n; i++) {
                double *p = P + 5 * i, *st = step + 5 * i;
                const double *Si = S + i * per, *Wi = WIN + i * per;
                double cand[5];
                for (int a = 0; a < 5; a++)
                    cand[a] = p[a] + st[a];
                cand[2] = clampd(cand[2], 0.3, lim_sig);
                double nc = gauss_model(cand, Si, X, Y, Wi, K, TMP, TMP + per, TMP + 2 * per, TMP + 3 * per,
                                        TMP + 4 * per);
                int better = nc < cost[i];
                if (better) {
                    memcpy(p, cand, sizeof cand);
                    memcpy(CUR + 5 * i * per, TMP, sizeof(double) * 5 * per);
                    cost[i] = nc;
                    lam[i] *= 0.3;
                } else {
                    lam[i] *= 10.0;
                }
                double mx = fabs(st[0]), my = fabs(st[1]);
                int small = (mx < 1e-3) && (my < 1e-3);
                if (!(small || !better)) all_done = 0;
                if (!(lam[i] < 1e3)) lam_ok = 0;
            }
            if (all_done && lam_ok)
                break;
        }
    }
    Py_END_ALLOW_THREADS
    Py_INCREF(Py_None);
    ret = Py_None;
done:
    free(work);
    release(b, 6);
    release(ix, 1);
    return ret;
}

/* the t-th smallest of v[0..k) (no NaN), v reordered: quickselect */
static double select_kth(double *v, Py_ssize_t k, Py_ssize_t t)
{
    Py_ssize_t lo = 0, hi = k - 1;
    while (hi > lo) {
        Py_ssize_t mid = lo + (hi - lo) / 2;
        /* median of three as the pivot */
        double a = v[lo], b = v[mid], c = v[hi];
        double piv = (a < b) ? ((b < c) ? b : ((a < c) ? c : a)) : ((a < c) ? a : ((b < c) ? c : b));
        Py_ssize_t i = lo, j = hi;
        while (i <= j) {
            while (v[i] < piv) i++;
            while (v[j] > piv) j--;
            if (i <= j) {
                double tmp = v[i];
                v[i] = v[j];
                v[j] = tmp;
                i++;
                j--;
            }
        }
        if (t <= j) hi = j;
        else if (t >= i) lo = i;
        else return v[t];
    }
    return v[t];
}

/* the median of v[j] over the j with mask[j] (all where mask is NULL): the mean of the middle
 * pair of the values sorted NaN last (np.sort's order), NaN for none (detect._row_median) */
static double masked_median(const double *v, const unsigned char *mask, Py_ssize_t R, double *buf)
{
    Py_ssize_t k = 0, m = 0;
    for (Py_ssize_t j = 0; j < R; j++) {
        if (mask && !mask[j]) continue;
        k++;
        if (!isnan(v[j])) buf[m++] = v[j];
    }
    if (k == 0) return NAN;
    Py_ssize_t lo = (k - 1) / 2, hi = k / 2;
    if (hi >= m) return NAN;                  /* a middle value is one of the NaNs sorted last */
    double vh = select_kth(buf, m, hi);
    if (lo == hi) return 0.5 * (vh + vh);
    /* after the selection every value before position hi is <= vh: the lower middle is their largest */
    double vl = buf[0];
    for (Py_ssize_t j = 1; j < hi; j++)
        if (buf[j] > vl) vl = buf[j];
    return 0.5 * (vl + vh);
}

/* plane_removed(p, n, PP, ring, dx, dy, valid, sign, mad_scale, tiny, out) -> bool
 *
 * p (n, PP) raw patches; ring (R,) intp indices of the ring pixels; dx, dy (PP,) pixel offsets;
 * valid (n, PP) uint8 or None; out (n, PP): sign * (plane - p).  detect._plane_removed_numpy's
 * robust plane: the ring's pixels within 3 robust sd of its median, then of the first plane.
 * Returns True where a 3 x 3 system was singular (nothing usable written: the caller falls back
 * to NumPy, which raises as np.linalg.solve does). */
static PyObject *plane_removed(PyObject *self, PyObject *args)
{
    PyObject *o_p, *o_ring, *o_dx, *o_dy, *o_valid, *o_out;
    Py_ssize_t n, PP, R;
    double sign, mad_scale, tiny;
    if (!PyArg_ParseTuple(args, "OnnOOOOdddO", &o_p, &n, &PP, &o_ring, &o_dx, &o_dy, &o_valid, &sign, &mad_scale,
                          &tiny, &o_out))
        return NULL;
    Py_buffer ix[1], b[5];
    if (acquire_index(o_ring, "ring", 0, PP, ix, &R) < 0)
        return NULL;
    const Arg arr[] = {{o_p, 8, n * PP, 0, 0, "p"}, {o_dx, 8, PP, 0, 0, "dx"}, {o_dy, 8, PP, 0, 0, "dy"},
                       {o_valid, 1, n * PP, 0, 1, "valid"}, {o_out, 8, n * PP, 1, 0, "out"}};
    if (acquire(arr, 5, b) < 0) {
        release(ix, 1);
        return NULL;
    }
    int singular = 0;
    PyObject *ret = NULL;
    double *work = NULL;
    const Py_ssize_t *ring = (const Py_ssize_t *)ix[0].buf;
    const size_t per = (size_t)(R > 0 ? R : 1);
    work = (double *)malloc(sizeof(double) * (per * 4 + (size_t)n * 3) + per * 3);
    if (!work) {
        PyErr_NoMemory();
        goto done;
    }
    Py_BEGIN_ALLOW_THREADS                     /* no Python object is touched below */
    {
        const double *P = (const double *)b[0].buf, *DX = (const double *)b[1].buf, *DY = (const double *)b[2].buf;
        const unsigned char *valid = (const unsigned char *)b[3].buf;     /* NULL: None */
        double *out = (double *)b[4].buf;
        double *r = work, *dev = r + per, *buf = dev + per, *res = buf + per, *coefs = res + per;
        unsigned char *w0 = (unsigned char *)(coefs + 3 * n), *w = w0 + per, *nw = w + per;
        for (Py_ssize_t i = 0; i < n && !singular; i++) {
            const double *pi = P + i * PP;
            for (Py_ssize_t j = 0; j < R; j++) {
                r[j] = pi[ring[j]];
                w0[j] = valid ? (valid[i * PP + ring[j]] != 0) : 1;
            }
            double med = masked_median(r, w0, R, buf);
            for (Py_ssize_t j = 0; j < R; j++)
                dev[j] = fabs(r[j] - med);
            double mad = mad_scale * masked_median(dev, w0, R, buf);
            if (!(mad > 0)) mad = INFINITY;
            double lim = 3 * mad + 1e-9;
            for (Py_ssize_t j = 0; j < R; j++)
                w[j] = (dev[j] <= lim) && w0[j];
            double coef[3];
            for (int it = 0; it < 2; it++) {
                double M[3][3] = {{0}}, b[3] = {0};
                for (Py_ssize_t j = 0; j < R; j++) {
                    /* NumPy's products with the 0/1 weights: a NaN pixel left out still makes b NaN */
                    double wf = (double)w[j];
                    double a[3] = {1.0, DX[ring[j]], DY[ring[j]]};
                    for (int u = 0; u < 3; u++) {
                        for (int v = 0; v < 3; v++)
                            M[u][v] += wf * (a[u] * a[v]);
                        b[u] += (wf * r[j]) * a[u];
                    }
                }
                for (int u = 0; u < 3; u++)
                    M[u][u] += tiny;
                if (solve_n(&M[0][0], b, 3)) {
                    singular = 1;
                    break;
                }
                memcpy(coef, b, sizeof coef);
                if (it == 1)
                    break;
                for (Py_ssize_t j = 0; j < R; j++)
                    res[j] = r[j] - ((coef[0] + coef[1] * DX[ring[j]]) + coef[2] * DY[ring[j]]);
                double mr = masked_median(res, w, R, buf);
                for (Py_ssize_t j = 0; j < R; j++)
                    dev[j] = fabs(res[j] - mr);
                double sd = mad_scale * masked_median(dev, w, R, buf);
                if (!(sd > 0)) sd = INFINITY;
                double lim2 = 3 * sd + 1e-9;
                Py_ssize_t kept = 0;
                for (Py_ssize_t j = 0; j < R; j++) {
                    nw[j] = (fabs(res[j]) <= lim2) && w0[j];
                    kept += nw[j];
                }
                if (kept >= 6)
                    memcpy(w, nw, (size_t)R);
            }
            for (int u = 0; u < 3; u++)
                coefs[3 * i + u] = coef[u];
        }
        if (!singular) {
            for (Py_ssize_t i = 0; i < n; i++) {
                const double *pi = P + i * PP, *c = coefs + 3 * i;
                double *oi = out + i * PP;
                for (Py_ssize_t k = 0; k < PP; k++)
                    oi[k] = sign * (((c[0] + c[1] * DX[k]) + c[2] * DY[k]) - pi[k]);
            }
        }
    }
    Py_END_ALLOW_THREADS
    ret = PyBool_FromLong(singular);
done:
    free(work);
    release(b, 5);
    release(ix, 1);
    return ret;
}

/* edge_fit(p, n, PP, P, ring, gi, near1, dx, dy, w, crowded, valid, sig, K, nk, pen, knot_px, tiny,
 *          look, coef, m, rssp, c, cs, sn, rss1, k1, depth, span) -> bool
 *
 * The arithmetic of detect._edge_background_numpy between its set-up (the ring's weights w
 * (n, R) with the neighbours' pixels out, the crowded rows, the pixel noise sig) and its
 * decision (the F test, the residual, the range): per patch the ring's least-squares plane
 * (coef (n, 3), m, rssp) and whether it is looked at (look); for those, the edge's
 * direction (cs, sn), the penalised piecewise-linear profile across it (c (n, nk)), its
 * residual rss1, the knots it reaches k1, the marker's depth under the plane and the profile's
 * range over the ring's weighted pixels.  Returns True where a system was singular (the caller
 * falls back to NumPy). */
static PyObject *edge_fit(PyObject *self, PyObject *args)
{
    PyObject *o_p, *o_ring, *o_gi, *o_near, *o_dx, *o_dy, *o_w, *o_crowd, *o_valid, *o_sig, *o_pen;
    PyObject *o_look, *o_coef, *o_m, *o_rssp, *o_c, *o_cs, *o_sn, *o_rss1, *o_k1, *o_depth, *o_span;
    Py_ssize_t n, PP, P;
    int K, nk;
    double knot_px, tiny;
    if (!PyArg_ParseTuple(args, "OnnnOOOOOOOOOiiOddOOOOOOOOOOO", &o_p, &n, &PP, &P, &o_ring, &o_gi, &o_near, &o_dx,
                          &o_dy, &o_w, &o_crowd, &o_valid, &o_sig, &K, &nk, &o_pen, &knot_px, &tiny, &o_look, &o_coef,
                          &o_m, &o_rssp, &o_c, &o_cs, &o_sn, &o_rss1, &o_k1, &o_depth, &o_span))
        return NULL;
    /* the index arrays first: their lengths size the rest */
    Py_buffer ix[3], b[19];
    const Arg idx[] = {{o_ring, IDX, -1, 0, 0, "ring"}, {o_gi, IDX, -1, 0, 0, "gi"}, {o_near, IDX, -1, 0, 0, "near1"}};
    if (acquire(idx, 3, ix) < 0)
        return NULL;
    const Py_ssize_t R = ix[0].len / IDX, G = ix[1].len / IDX, Q = ix[2].len / IDX;
    const Arg arr[] = {
        {o_p, 8, n * PP, 0, 0, "p"}, {o_dx, 8, PP, 0, 0, "dx"}, {o_dy, 8, PP, 0, 0, "dy"}, {o_w, 8, n * R, 0, 0, "w"},
        {o_crowd, 1, n, 0, 0, "crowded"}, {o_sig, 8, n, 0, 0, "sig"}, {o_pen, 8, (Py_ssize_t)nk * nk, 0, 0, "pen"},
        {o_look, 1, n, 1, 0, "look"}, {o_coef, 8, 3 * n, 1, 0, "coef"}, {o_m, 8, n, 1, 0, "m"},
        {o_rssp, 8, n, 1, 0, "rssp"}, {o_c, 8, n * nk, 1, 0, "c"}, {o_cs, 8, n, 1, 0, "cs"}, {o_sn, 8, n, 1, 0, "sn"},
        {o_rss1, 8, n, 1, 0, "rss1"}, {o_k1, 8, n, 1, 0, "k1"}, {o_depth, 8, n, 1, 0, "depth"},
        {o_span, 8, n, 1, 0, "span"}, {o_valid, 1, n * PP, 0, 1, "valid"}};
    if (acquire(arr, 19, b) < 0) {
        release(ix, 3);
        return NULL;
    }
    int singular = 0;
    PyObject *ret = NULL;
    double *work = NULL;
    const Py_ssize_t *ring = (const Py_ssize_t *)ix[0].buf, *gi = (const Py_ssize_t *)ix[1].buf;
    const Py_ssize_t *near1 = (const Py_ssize_t *)ix[2].buf;
    if (indices_within(ring, R, 0, PP, "ring") < 0 || indices_within(gi, G, P, PP - P, "gradient pixel") < 0
        || indices_within(near1, Q, 0, PP, "centre pixel") < 0)
        goto done;
    if (nk < 2) {
        PyErr_SetString(PyExc_ValueError, "fewer than two knots");
        goto done;
    }
    work = (double *)malloc(sizeof(double) * ((size_t)R * 3 + (size_t)nk * 8 + (size_t)nk * nk + 1));
    if (!work) {
        PyErr_NoMemory();
        goto done;
    }
    Py_BEGIN_ALLOW_THREADS                         /* no Python object is touched below */
    {
        const double *pp = (const double *)b[0].buf, *DX = (const double *)b[1].buf, *DY = (const double *)b[2].buf;
        const double *W = (const double *)b[3].buf, *sig = (const double *)b[5].buf, *pen = (const double *)b[6].buf;
        const unsigned char *crowded = (const unsigned char *)b[4].buf;
        unsigned char *look = (unsigned char *)b[7].buf;
        double *coef = (double *)b[8].buf, *mo = (double *)b[9].buf, *rssp = (double *)b[10].buf;
        double *cc = (double *)b[11].buf, *cso = (double *)b[12].buf, *sno = (double *)b[13].buf;
        double *rss1 = (double *)b[14].buf, *k1o = (double *)b[15].buf, *depth = (double *)b[16].buf;
        double *span = (double *)b[17].buf;
        const unsigned char *valid = (const unsigned char *)b[18].buf;    /* NULL: None */
        const size_t nkk = (size_t)nk;
        /* per ring pixel: its knot, fraction, bg; per knot: d (two parts), off, rhs (two), reach (two); M */
        double *kf = work, *fr = kf + R, *bg = fr + R;
        double *dA = bg + R, *dB = dA + nk, *off = dB + nk, *rA = off + nk, *rB = rA + nk, *qA = rB + nk, *qB = qA + nk;
        double *M = qB + nk, *rhs = M + nkk * nkk;
        const double inv_knot = 1.0 / knot_px;
        for (Py_ssize_t i = 0; i < n && !singular; i++) {
            const double *pi = pp + i * PP, *wi = W + i * R;
            /* the ring's least-squares plane (weights 0/1: exact sums for integer pixels) */
            double A3[3][3] = {{0}}, b3[3] = {0}, cf[3];
            double m = 0.0;
            for (Py_ssize_t j = 0; j < R; j++) {
                double a[3] = {1.0, DX[ring[j]], DY[ring[j]]};
                double wr = wi[j] * pi[ring[j]];
                for (int u = 0; u < 3; u++) {
                    for (int v = 0; v < 3; v++)
                        A3[u][v] += wi[j] * (a[u] * a[v]);
                    b3[u] += wr * a[u];
                }
                m += wi[j];
            }
            for (int u = 0; u < 3; u++)
                A3[u][u] += tiny;
            if (solve_n(&A3[0][0], b3, 3)) { singular = 1; break; }
            memcpy(cf, b3, sizeof cf);
            double rp = 0.0;
            for (Py_ssize_t j = 0; j < R; j++) {
                double pl = (cf[0] + cf[1] * DX[ring[j]]) + cf[2] * DY[ring[j]];
                double d = pi[ring[j]] - pl;
                rp += wi[j] * (d * d);
            }
            coef[3 * i] = cf[0];
            coef[3 * i + 1] = cf[1];
            coef[3 * i + 2] = cf[2];
            mo[i] = m;
            rssp[i] = rp;
            double dfp = m - 3.0;
            if (!(dfp >= 1.0)) dfp = (dfp < 1.0) ? 1.0 : dfp;          /* np.maximum(m - 3, 1) */
            double s2 = sig[i] * sig[i];
            int lk = (rp / dfp > s2 * (1.0 + 3.0 * sqrt(2.0 / dfp))) && !crowded[i] && (m >= 20);
            look[i] = (unsigned char)lk;
            if (!lk) continue;
            /* the edge's normal: the main axis of the ring's gradients */
            double jxx = 0.0, jyy = 0.0, jxy = 0.0;
            for (Py_ssize_t j = 0; j < G; j++) {
                Py_ssize_t q = gi[j];
                double gx = pi[q + 1] - pi[q - 1], gy = pi[q + P] - pi[q - P];
                double wg = valid ? (double)(valid[i * PP + q] != 0) : 1.0;
                jxx += (wg * gx) * gx;
                jyy += (wg * gy) * gy;
                jxy += (wg * gx) * gy;
            }
            double th = 0.5 * atan2(2.0 * jxy, jxx - jyy);
            double cs = cos(th), sn = sin(th);
            cso[i] = cs;
            sno[i] = sn;
            /* the penalised piecewise-linear profile across the edge (detect._hat_fit) */
            for (int q = 0; q < nk; q++)
                dA[q] = dB[q] = off[q] = rA[q] = rB[q] = qA[q] = qB[q] = 0.0;
            int bad_knot = 0;
            for (Py_ssize_t j = 0; j < R; j++) {
                double us = (DX[ring[j]] * cs + DY[ring[j]] * sn) * inv_knot + K;
                double k0 = floor(us);
                double f = us - k0;
                int kq = (int)k0;
                if (kq < 0 || kq + 1 >= nk) { bad_knot = 1; break; }
                kf[j] = k0;
                fr[j] = f;
                double a = wi[j] * (1.0 - f), bb = wi[j] * f, v = pi[ring[j]];
                dA[kq] += a * (1.0 - f);
                dB[kq + 1] += bb * f;
                off[kq] += a * f;
                rA[kq] += a * v;
                rB[kq + 1] += bb * v;
                qA[kq] += a;
                qB[kq + 1] += bb;
            }
            if (bad_knot) { singular = 1; break; }          /* a NaN angle: NumPy's way */
            memcpy(M, pen, sizeof(double) * nkk * nkk);
            for (int q = 0; q < nk; q++) {
                M[q * nk + q] += dA[q] + dB[q];
                rhs[q] = rA[q] + rB[q];
            }
            for (int q = 0; q + 1 < nk; q++) {
                M[q * nk + q + 1] += off[q];
                M[(q + 1) * nk + q] += off[q];
            }
            int reached = 0;
            for (int q = 0; q < nk; q++)
                reached += (qA[q] + qB[q]) > 0.5;
            if (solve_n(M, rhs, nk)) { singular = 1; break; }
            double *ci = cc + i * nk;
            memcpy(ci, rhs, sizeof(double) * nkk);
            double r1 = 0.0, lo = INFINITY, hi = -INFINITY;
            int snan = 0;
            for (Py_ssize_t j = 0; j < R; j++) {
                int kq = (int)kf[j];
                double f = fr[j];
                double v = ci[kq] * (1.0 - f) + ci[kq + 1] * f;
                double d = pi[ring[j]] - v;
                r1 += wi[j] * (d * d);
                if (wi[j] > 0) {
                    if (isnan(v)) snan = 1;
                    if (v > hi) hi = v;
                    if (v < lo) lo = v;
                }
            }
            rss1[i] = r1;
            k1o[i] = (double)reached + 1.0;
            span[i] = snan ? NAN : hi - lo;
            double dp = 0.0;
            int dnan = 0;
            for (Py_ssize_t j = 0; j < Q; j++) {
                Py_ssize_t q = near1[j];
                double v = fabs(((cf[0] + cf[1] * DX[q]) + cf[2] * DY[q]) - pi[q]);
                if (isnan(v)) dnan = 1;
                else if (v > dp || j == 0) dp = v;
            }
            depth[i] = dnan ? NAN : dp;
        }
    }
    Py_END_ALLOW_THREADS
    ret = PyBool_FromLong(singular);
done:
    free(work);
    release(b, 19);
    release(ix, 3);
    return ret;
}

static PyMethodDef methods[] = {
    {"centroid", centroid, METH_VARARGS, "Iterated soft-disc centroids of patches (detect._centroid)."},
    {"gaussian_fit", gaussian_fit, METH_VARARGS,
     "Levenberg-Marquardt Gaussian fits of patches (detect._gaussian_fit)."},
    {"plane_removed", plane_removed, METH_VARARGS,
     "Patches with a robust background plane removed (detect._plane_removed)."},
    {"edge_fit", edge_fit, METH_VARARGS, "The edge background's plane and profile fits (detect._edge_background)."},
    {NULL, NULL, 0, NULL}};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_kernels",
                                    "The per-frame sub-pixel fits of bsipipe.imaging.detect, compiled.", -1,
                                    methods};

/* detect.py uses the module only where its VERSION is the one it was written for (a module
 * built from an older _kernels.c is left aside, with a warning to rebuild) */
#define KERNELS_VERSION 1

PyMODINIT_FUNC PyInit__kernels(void)
{
    PyObject *m = PyModule_Create(&module);
    if (m && PyModule_AddIntConstant(m, "VERSION", KERNELS_VERSION) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
