/* Portable C99 evaluator of a deltatwin-physics-controller model: controller_evaluator.h has
 * the interface and the block layout; controller_evaluator.py (numpy) is the readable
 * reference of every step, which this file follows function by function for one point. */
#include "controller_evaluator.h"

#include <math.h>
#include <stdio.h>

#define KINEMATICS_TOL_M 1e-14          /* Newton step at which a pose has converged */
#define CLOSURE_TOL_M 1e-12             /* largest |rod length - L| accepted */
#define MAX_ITER 50
#define N_STATICS 42                    /* preload (6) and compliance (36) per node */
#define FIXED_SIZE 127                  /* the block up to its optics steps */
static const double MU0 = 4e-7 * 3.14159265358979323846;
static const double PI = 3.14159265358979323846;

/* -- small vector algebra ------------------------------------------------------------------- */

static double dot(const double a[3], const double b[3]) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }

static void cross(const double a[3], const double b[3], double out[3])
{
    double o0 = a[1] * b[2] - a[2] * b[1], o1 = a[2] * b[0] - a[0] * b[2];
    double o2 = a[0] * b[1] - a[1] * b[0];
    out[0] = o0; out[1] = o1; out[2] = o2;
}

static void matvec(double R[3][3], const double v[3], double out[3])
{
    int a;
    for (a = 0; a < 3; a++) out[a] = R[a][0] * v[0] + R[a][1] * v[1] + R[a][2] * v[2];
}

static void matmul(double A[3][3], double B[3][3], double out[3][3])
{
    double t[3][3];
    int a, b;
    for (a = 0; a < 3; a++)
        for (b = 0; b < 3; b++) t[a][b] = A[a][0] * B[0][b] + A[a][1] * B[1][b] + A[a][2] * B[2][b];
    for (a = 0; a < 3; a++)
        for (b = 0; b < 3; b++) out[a][b] = t[a][b];
}

/* Rotation matrix of a rotation vector w (Rodrigues; a series below 1e-4 rad) */
static void rotation(const double w[3], double R[3][3])
{
    double t2 = dot(w, w), a, b, K[3][3], K2[3][3];
    int i, j;
    if (t2 < 1e-8) {
        a = 1.0 - t2 / 6.0 + t2 * t2 / 120.0;
        b = 0.5 - t2 / 24.0 + t2 * t2 / 720.0;
    } else {
        double t = sqrt(t2), s = sin(0.5 * t) / t;
        a = sin(t) / t;
        b = 2.0 * s * s;
    }
    K[0][0] = 0.0; K[0][1] = -w[2]; K[0][2] = w[1];
    K[1][0] = w[2]; K[1][1] = 0.0; K[1][2] = -w[0];
    K[2][0] = -w[1]; K[2][1] = w[0]; K[2][2] = 0.0;
    matmul(K, K, K2);
    for (i = 0; i < 3; i++)
        for (j = 0; j < 3; j++) R[i][j] = (i == j) + a * K[i][j] + b * K2[i][j];
}

/* Solve M x = rhs (n <= 9) by Gaussian elimination with partial pivoting (LAPACK's getrf
 * does the same); M and rhs are overwritten. Returns 0, or -1 on a zero pivot. */
static int solve(int n, double M[9][9], double rhs[9], double x[9])
{
    int i, j, k;
    for (k = 0; k < n; k++) {
        int piv = k;
        for (i = k + 1; i < n; i++)
            if (fabs(M[i][k]) > fabs(M[piv][k])) piv = i;
        if (M[piv][k] == 0.0) return -1;
        if (piv != k) {
            double t;
            for (j = 0; j < n; j++) { t = M[k][j]; M[k][j] = M[piv][j]; M[piv][j] = t; }
            t = rhs[k]; rhs[k] = rhs[piv]; rhs[piv] = t;
        }
        for (i = k + 1; i < n; i++) {
            double f = M[i][k] / M[k][k];
            for (j = k; j < n; j++) M[i][j] -= f * M[k][j];
            rhs[i] -= f * rhs[k];
        }
    }
    for (i = n - 1; i >= 0; i--) {
        double s = rhs[i];
        for (j = i + 1; j < n; j++) s -= M[i][j] * x[j];
        x[i] = s / M[i][i];
    }
    return 0;
}

/* -- the model block ------------------------------------------------------------------------ */

static void take(const double **at, double *out, int n)
{
    int i;
    for (i = 0; i < n; i++) out[i] = (*at)[i];
    *at += n;
}

int dtc_model_init(dtc_model *m, const double *block, size_t n)
{
    const double *at = block;
    double head[3], flag[1];
    size_t nodes;
    int k;
    if (n < FIXED_SIZE || block[0] != DTC_MAGIC || block[1] != DTC_LAYOUT_VERSION || block[2] != (double)n)
        return DTC_ERR_BLOCK;
    at += 3;
    take(&at, &m->T_ref, 1);
    take(&at, m->cte, 4);
    take(&at, &m->B[0][0], 9);
    take(&at, &m->axis[0][0], 9);
    take(&at, &m->arm_vec[0][0][0], 18);
    take(&at, &m->P0[0][0][0], 18);
    take(&at, &m->L[0][0], 6);
    take(&at, m->theta_zero, 3);
    take(&at, m->cube_offset, 3);
    take(&at, &m->cube_size, 1);
    take(&at, m->stroke, 2);
    take(&at, flag, 1);
    m->has_gravity = flag[0] != 0.0;
    take(&at, m->gravity_N, 3);
    take(&at, flag, 1);
    m->has_magnetic = flag[0] != 0.0;
    take(&at, &m->magnet_moment, 1);
    take(&at, &m->coil_moment_per_A, 1);
    take(&at, &m->magnets[0][0], 9);
    take(&at, &m->coils[0][0], 9);
    take(&at, &m->heads[0][0], 9);
    take(&at, &m->directions[0][0], 9);
    take(&at, m->fold, 3);
    take(&at, m->fold_normal, 3);
    take(&at, flag, 1);
    m->n_steps = (int)flag[0];
    if (flag[0] != (double)m->n_steps || m->n_steps < 0 || m->n_steps > DTC_MAX_STEPS)
        return DTC_ERR_BLOCK;
    if ((size_t)(at - block) + (size_t)m->n_steps * DTC_STEP_SIZE + 3 > n) return DTC_ERR_BLOCK;
    for (k = 0; k < m->n_steps; k++) {
        take(&at, flag, 1);
        m->steps[k].kind = (int)flag[0];
        if (m->steps[k].kind < DTC_LOOP_DRIFT || m->steps[k].kind > DTC_AIR_REFRACTION)
            return DTC_ERR_BLOCK;
        take(&at, m->steps[k].v, DTC_STEP_SIZE - 1);
    }
    take(&at, head, 3);
    m->q_range[0] = head[0];
    m->q_range[1] = head[1];
    m->degree = (int)head[2];
    if (head[2] != (double)m->degree || m->degree < 0 || m->degree > DTC_MAX_DEGREE
        || !(m->q_range[1] > m->q_range[0]))
        return DTC_ERR_BLOCK;
    nodes = (size_t)(m->degree + 1) * (size_t)(m->degree + 1) * (size_t)(m->degree + 1);
    if ((size_t)(at - block) + nodes * N_STATICS != n) return DTC_ERR_BLOCK;
    m->statics = at;
    return DTC_OK;
}

int dtc_read_block(const char *path, double *buf, size_t cap, size_t *n)
{
    FILE *f = fopen(path, "rb");
    size_t got;
    if (f == NULL) return DTC_ERR_FILE;
    got = fread(buf, sizeof(double), cap, f);
    if (got == cap && fgetc(f) != EOF) got = 0;          /* larger than the buffer */
    fclose(f);
    *n = got;
    if (got < 3 || buf[0] != DTC_MAGIC) return DTC_ERR_FILE;
    return got == (size_t)buf[2] ? DTC_OK : DTC_ERR_FILE;
}

void dtc_conditions_reference(const dtc_model *m, dtc_conditions *c)
{
    int k;
    for (k = 0; k < DTC_N_TEMPERATURES; k++) c->T_C[k] = m->T_ref;
    c->pressure_Pa = 101325.0;
    c->currents_A[0] = c->currents_A[1] = c->currents_A[2] = 0.0;
}

/* -- 1. geometry at the part temperatures ----------------------------------------------------- */

typedef struct {
    double B[3][3], arm_vec[3][2][3], P0[3][2][3], L[3][2], cube_offset[3];
} geometry;

static void geometry_at(const dtc_model *m, const dtc_conditions *c, geometry *g)
{
    const double *T = c->T_C;
    double s_base = 1.0 + m->cte[0] * (T[DTC_BASE] - m->T_ref);
    double s_plat = 1.0 + m->cte[3] * (T[DTC_PLATFORM] - m->T_ref);
    int i, j, a;
    for (i = 0; i < 3; i++) {
        double s_arm = 1.0 + m->cte[1] * (T[DTC_ARM1 + i] - m->T_ref);
        double s_rod = 1.0 + m->cte[2] * (T[DTC_ROD1 + i] - m->T_ref);
        for (a = 0; a < 3; a++) g->B[i][a] = s_base * m->B[i][a];
        for (j = 0; j < 2; j++) {
            for (a = 0; a < 3; a++) {
                g->arm_vec[i][j][a] = s_arm * m->arm_vec[i][j][a];
                g->P0[i][j][a] = s_plat * m->P0[i][j][a];
            }
            g->L[i][j] = s_rod * m->L[i][j];
        }
        g->cube_offset[i] = s_plat * m->cube_offset[i];
    }
}

/* Elbow hinges A at motor coordinates q and dA/dq_i */
static void elbows(const dtc_model *m, const geometry *g, const double q[3], double A[3][2][3],
                   double dA[3][2][3])
{
    int i, j, a;
    for (i = 0; i < 3; i++) {
        double th = q[i] + m->theta_zero[i], ct = cos(th), st = sin(th);
        const double *ax = m->axis[i];
        for (j = 0; j < 2; j++) {
            const double *v = g->arm_vec[i][j];
            double axv[3], rot[3], along = dot(ax, v);
            cross(ax, v, axv);
            for (a = 0; a < 3; a++) rot[a] = v[a] * ct + axv[a] * st + ax[a] * along * (1.0 - ct);
            for (a = 0; a < 3; a++) A[i][j][a] = g->B[i][a] + rot[a];
            cross(ax, rot, dA[i][j]);
        }
    }
}

/* -- 2. kinematic pose ---------------------------------------------------------------------- */

/* Rod equations f (6), their derivatives in (p, rotation) (6,6) and the rod vectors d */
static void rod_system(const geometry *g, double A[3][2][3], const double p[3],
                       double R[3][3], double f[6], double J[9][9], double d[3][2][3])
{
    int i, j, a;
    for (i = 0; i < 3; i++)
        for (j = 0; j < 2; j++) {
            double w[3], wd[3], *dd = d[i][j];
            int r = 2 * i + j;
            matvec(R, g->P0[i][j], w);
            for (a = 0; a < 3; a++) dd[a] = p[a] + w[a] - A[i][j][a];
            f[r] = dot(dd, dd) - g->L[i][j] * g->L[i][j];
            cross(w, dd, wd);
            for (a = 0; a < 3; a++) {
                J[r][a] = 2.0 * dd[a];
                J[r][3 + a] = 2.0 * wd[a];
            }
        }
}

/* Closed-form start: each parallelogram's centre line, the lower intersection of three spheres */
static int start_pose(const geometry *g, double A[3][2][3], double p[3], double R[3][3])
{
    double c[3][3], r[3], ex[3], ey[3], ez[3], d31[3], d, i, j, x, y, z2, zz[3];
    int k, a;
    for (k = 0; k < 3; k++) {
        for (a = 0; a < 3; a++)
            c[k][a] = 0.5 * (A[k][0][a] + A[k][1][a]) - 0.5 * (g->P0[k][0][a] + g->P0[k][1][a]);
        r[k] = 0.5 * (g->L[k][0] + g->L[k][1]);
    }
    for (a = 0; a < 3; a++) ex[a] = c[1][a] - c[0][a];
    d = sqrt(dot(ex, ex));
    for (a = 0; a < 3; a++) { ex[a] /= d; d31[a] = c[2][a] - c[0][a]; }
    i = dot(ex, d31);
    for (a = 0; a < 3; a++) ey[a] = d31[a] - i * ex[a];
    j = sqrt(dot(ey, ey));
    for (a = 0; a < 3; a++) ey[a] /= j;
    cross(ex, ey, ez);
    x = (r[0] * r[0] - r[1] * r[1] + d * d) / (2 * d);
    y = (r[0] * r[0] - r[2] * r[2] + i * i + j * j) / (2 * j) - i * x / j;
    z2 = r[0] * r[0] - x * x - y * y;
    if (!(z2 >= 0.0)) return DTC_ERR_NO_POSE;
    for (a = 0; a < 3; a++) zz[a] = sqrt(z2) * ez[a];
    for (a = 0; a < 3; a++) {
        double base = c[0][a] + x * ex[a] + y * ey[a];
        p[a] = zz[2] > 0 ? base - zz[a] : base + zz[a];
    }
    for (a = 0; a < 3; a++)
        for (k = 0; k < 3; k++) R[a][k] = (a == k);
    return DTC_OK;
}

static void set_pose(dtc_pose *pose, const double p[3], double R[3][3])
{
    int a, b;
    if (pose == NULL) return;
    pose->valid = 1;
    for (a = 0; a < 3; a++) {
        pose->p[a] = p[a];
        for (b = 0; b < 3; b++) pose->R[a][b] = R[a][b];
    }
}

static int initial_pose(const geometry *g, double A[3][2][3], const dtc_pose *pose,
                        double p[3], double R[3][3])
{
    int a, b;
    if (pose == NULL || !pose->valid) return start_pose(g, A, p, R);
    for (a = 0; a < 3; a++) {
        p[a] = pose->p[a];
        for (b = 0; b < 3; b++) R[a][b] = pose->R[a][b];
    }
    return DTC_OK;
}

/* Platform pose at q: Newton on the six rod equations; the loop closure is checked */
static int kinematic_pose(const dtc_model *m, const geometry *g, const double q[3],
                          const dtc_pose *from, double p[3], double R[3][3])
{
    double A[3][2][3], dA[3][2][3], f[6], J[9][9], d[3][2][3], rhs[9], step[9], dR[3][3];
    int it, k, i, j, rc;
    elbows(m, g, q, A, dA);
    rc = initial_pose(g, A, from, p, R);
    if (rc != DTC_OK) return rc;
    for (it = 0; it < MAX_ITER; it++) {
        int small = 1;
        rod_system(g, A, p, R, f, J, d);
        for (k = 0; k < 6; k++) rhs[k] = -f[k];
        if (solve(6, J, rhs, step) != 0) return DTC_ERR_NOT_CLOSED;
        for (k = 0; k < 3; k++) p[k] += step[k];
        rotation(step + 3, dR);
        matmul(dR, R, R);
        for (k = 0; k < 6; k++) small = small && fabs(step[k]) < KINEMATICS_TOL_M;
        if (small) break;
    }
    rod_system(g, A, p, R, f, J, d);
    for (i = 0; i < 3; i++)
        for (j = 0; j < 2; j++)
            if (!(fabs(sqrt(dot(d[i][j], d[i][j])) - g->L[i][j]) < CLOSURE_TOL_M))
                return DTC_ERR_NOT_CLOSED;
    return DTC_OK;
}

/* -- 3. load -------------------------------------------------------------------------------- */

/* The statics series at q: the preload deflection y[0..5], the compliance y[6..41] */
static void statics_at(const dtc_model *m, const double q[3], double y[N_STATICS])
{
    double T[3][DTC_MAX_DEGREE + 1];
    const double *c = m->statics;
    int deg = m->degree, a, i, j, k, v;
    for (a = 0; a < 3; a++) {
        double x = (2.0 * q[a] - (m->q_range[0] + m->q_range[1])) / (m->q_range[1] - m->q_range[0]);
        T[a][0] = 1.0;
        if (deg > 0) T[a][1] = x;
        for (k = 2; k <= deg; k++) T[a][k] = 2.0 * x * T[a][k - 1] - T[a][k - 2];
    }
    for (v = 0; v < N_STATICS; v++) y[v] = 0.0;
    for (i = 0; i <= deg; i++)
        for (j = 0; j <= deg; j++) {
            double tij = T[0][i] * T[1][j];
            for (k = 0; k <= deg; k++, c += N_STATICS) {
                double b = tij * T[2][k];
                for (v = 0; v < N_STATICS; v++) y[v] += b * c[v];
            }
        }
}

/* Wrench (6) on the platform at its origin: the weight and the coil-magnet dipole forces */
static void wrench(const dtc_model *m, const dtc_conditions *c, const double p[3],
                   double R[3][3], double w[6])
{
    int k, l, a;
    for (a = 0; a < 6; a++) w[a] = 0.0;
    if (m->has_gravity)
        for (a = 0; a < 3; a++) w[a] += m->gravity_N[a];
    if (!m->has_magnetic) return;
    for (k = 0; k < 3; k++) {                       /* each magnet */
        double arm[3], r2[3], m2[3], F_tot[3] = {0, 0, 0}, tau_tot[3] = {0, 0, 0}, t[3];
        matvec(R, m->magnets[k], arm);
        for (a = 0; a < 3; a++) {
            r2[a] = p[a] + arm[a];
            m2[a] = -m->magnet_moment * R[a][2];
        }
        for (l = 0; l < 3; l++) {                   /* each coil */
            double m1[3], r[3], u[3], d2, d, m1u, m2u, m1m2, fF, fB, B[3], tq[3];
            m1[0] = 0.0; m1[1] = 0.0; m1[2] = m->coil_moment_per_A * c->currents_A[l];
            for (a = 0; a < 3; a++) r[a] = r2[a] - m->coils[l][a];
            d2 = dot(r, r);
            d = sqrt(d2);
            for (a = 0; a < 3; a++) u[a] = r[a] / d;
            m1u = dot(m1, u);
            m2u = dot(m2, u);
            m1m2 = dot(m1, m2);
            fF = 3 * MU0 / (4 * PI * d2 * d2);
            fB = MU0 / (4 * PI * d2 * d);
            for (a = 0; a < 3; a++) {
                F_tot[a] += fF * (m2[a] * m1u + m1[a] * m2u + u[a] * m1m2 - 5 * u[a] * m1u * m2u);
                B[a] = fB * (3 * u[a] * m1u - m1[a]);
            }
            cross(m2, B, tq);
            for (a = 0; a < 3; a++) tau_tot[a] += tq[a];
        }
        cross(arm, F_tot, t);
        for (a = 0; a < 3; a++) {
            w[a] += F_tot[a];
            w[3 + a] += t[a] + tau_tot[a];
        }
    }
}

/* The platform's pose under its load: preload deflection + compliance x wrench */
static void deflected(const dtc_model *m, const dtc_conditions *c, const double q[3],
                      const double p[3], double R[3][3], double pd[3], double Rd[3][3])
{
    double y[N_STATICS], dR[3][3];
    int a, b;
    statics_at(m, q, y);
    if (m->has_gravity || m->has_magnetic) {
        double w[6];
        wrench(m, c, p, R, w);
        for (a = 0; a < 6; a++) {
            double s = 0.0;
            for (b = 0; b < 6; b++) s += y[6 + 6 * a + b] * w[b];
            y[a] += s;
        }
    }
    for (a = 0; a < 3; a++) pd[a] = p[a] + y[a];
    rotation(y + 3, dR);
    matmul(dR, R, Rd);
}

/* -- 4. optics ------------------------------------------------------------------------------ */

typedef struct {
    double vertex[3][3], beam[3][3];    /* effective straight beams (Z imaged in the fold) */
    double n_air[3], n_comp[3];
} optics_state;

static double air_index(double T_C, double p_Pa, double vapour_Pa, double wavelength_m)
{
    double s = 1e-6 / wavelength_m, sigma2 = s * s;
    double ns = 1e-8 * (8342.54 + 2406147.0 / (130.0 - sigma2) + 15998.0 / (38.9 - sigma2));
    double ntp = p_Pa * ns / 96095.43 * (1.0 + 1e-8 * (0.601 - 0.00972 * T_C) * p_Pa)
                 / (1.0 + 0.003661 * T_C);
    return 1.0 + ntp - vapour_Pa * (3.7345 - 0.0401 * sigma2) * 1e-10;
}

/* Displacement of an optical element at pos standing on a support at support_C (loop drift) */
static void loop_drift(const double *v, const dtc_conditions *c, const double pos[3],
                       double support_C, double out[3])
{
    /* v: reference_C, frame_height_m, frame_arm_m (2), table, frame, support cte_per_K */
    double dT_table = c->T_C[DTC_TABLE] - v[0], dT_frame = c->T_C[DTC_FRAME] - v[0];
    double height = v[1] + pos[2], shift = v[4] * dT_table - v[5] * dT_frame;
    out[0] = v[4] * dT_table * pos[0] - shift * v[2];
    out[1] = v[4] * dT_table * pos[1] - shift * v[3];
    out[2] = v[6] * (support_C - v[0]) * height - v[5] * dT_frame * v[1];
}

/* A beam direction tilted by two small angles about the axes across it */
static void tilt(double d[3], const double angles[2], double e1[3], double e2[3])
{
    double up[3] = {0.0, 0.0, 0.0}, nrm;
    int a;
    up[fabs(d[2]) < 0.9 ? 2 : 0] = 1.0;
    cross(d, up, e1);
    nrm = sqrt(dot(e1, e1));
    for (a = 0; a < 3; a++) e1[a] /= nrm;
    cross(d, e1, e2);
    for (a = 0; a < 3; a++) d[a] = d[a] + angles[0] * e1[a] + angles[1] * e2[a];
    nrm = sqrt(dot(d, d));
    for (a = 0; a < 3; a++) d[a] /= nrm;
}

static void optics_at(const dtc_model *m, const dtc_conditions *c, optics_state *o)
{
    double head[3][3], dir[3][3], fold[3], shift[3], nrm, x[3];
    int k, a, s;
    for (k = 0; k < 3; k++) {
        for (a = 0; a < 3; a++) { head[k][a] = m->heads[k][a]; dir[k][a] = m->directions[k][a]; }
        o->n_air[k] = o->n_comp[k] = 1.0;
        fold[k] = m->fold[k];
    }
    for (s = 0; s < m->n_steps; s++) {
        const double *v = m->steps[s].v;
        if (m->steps[s].kind == DTC_LOOP_DRIFT) {
            for (k = 0; k < 3; k++) {       /* every support stands on the table */
                loop_drift(v, c, head[k], c->T_C[DTC_SUPPORT], shift);
                for (a = 0; a < 3; a++) head[k][a] += shift[a];
            }
            loop_drift(v, c, fold, c->T_C[DTC_TABLE], shift);
            for (a = 0; a < 3; a++) fold[a] += shift[a];
        } else if (m->steps[s].kind == DTC_BEAM_MISALIGNMENT) {
            /* v: angle_rad (3,2), abbe_offset_m (3,2) */
            for (k = 0; k < 3; k++) {
                double e1[3], e2[3];
                tilt(dir[k], v + 2 * k, e1, e2);
                for (a = 0; a < 3; a++) head[k][a] += v[6 + 2 * k] * e1[a] + v[7 + 2 * k] * e2[a];
            }
        } else {                            /* DTC_AIR_REFRACTION */
            /* v: wavelength_m, beam_room_fraction, compensation_offset_C (3),
               assumed_pressure_Pa, vapour_pressure_Pa */
            for (k = 0; k < 3; k++) {
                double T_beam = (1.0 - v[1]) * c->T_C[DTC_AIR_X + k] + v[1] * c->T_C[DTC_ROOM];
                o->n_air[k] = air_index(T_beam, c->pressure_Pa, v[6], v[0]);
                o->n_comp[k] = air_index(c->T_C[DTC_COMP_X + k] + v[2 + k], v[5], v[6], v[0]);
            }
        }
    }
    for (k = 0; k < 3; k++) {
        nrm = sqrt(dot(dir[k], dir[k]));
        for (a = 0; a < 3; a++) { o->vertex[k][a] = head[k][a]; o->beam[k][a] = dir[k][a] / nrm; }
    }
    /* Z: the head and the beam imaged in the fold mirror */
    for (a = 0; a < 3; a++) x[a] = head[2][a] - fold[a];
    nrm = dot(x, m->fold_normal);
    for (a = 0; a < 3; a++) o->vertex[2][a] = fold[a] + x[a] - 2.0 * nrm * m->fold_normal[a];
    for (a = 0; a < 3; a++) x[a] = o->beam[2][a];
    nrm = dot(x, m->fold_normal);
    for (a = 0; a < 3; a++) o->beam[2][a] = x[a] - 2.0 * nrm * m->fold_normal[a];
}

/* Optical paths n h cos(alpha) of the three double-pass interferometers; J (3,6) their
 * derivatives in (p, rotation) of the rigid platform (cos alpha held), when J != NULL */
static void optical_paths(const dtc_model *m, const optics_state *o, const geometry *g,
                          const double p[3], double R[3][3], double path[3], double J[3][6])
{
    int k, a;
    for (k = 0; k < 3; k++) {
        double local[3], centre[3], nw[3], rel[3], h, cosb, arm[3];
        for (a = 0; a < 3; a++) local[a] = g->cube_offset[a] - 0.5 * m->cube_size * (a == k);
        matvec(R, local, centre);
        for (a = 0; a < 3; a++) {
            centre[a] += p[a];
            nw[a] = -R[a][k];               /* R times the face normal -e_k */
            rel[a] = o->vertex[k][a] - centre[a];
        }
        h = dot(nw, rel);
        cosb = -dot(nw, o->beam[k]);
        path[k] = o->n_air[k] * h * cosb;
        if (J != NULL) {
            double scale = o->n_air[k] * cosb, vp[3];
            for (a = 0; a < 3; a++) vp[a] = o->vertex[k][a] - p[a];
            cross(nw, vp, arm);
            for (a = 0; a < 3; a++) {
                J[k][a] = -scale * nw[a];
                J[k][3 + a] = scale * arm[a];
            }
        }
    }
}

/* -- 5. readings ---------------------------------------------------------------------------- */

static int paths_at(const dtc_model *m, const dtc_conditions *c, const double q[3],
                    dtc_pose *pose, double path[3], optics_state *o)
{
    geometry g;
    double p[3], R[3][3], pd[3], Rd[3][3];
    int rc;
    geometry_at(m, c, &g);
    rc = kinematic_pose(m, &g, q, pose, p, R);
    if (rc != DTC_OK) return rc;
    set_pose(pose, p, R);
    deflected(m, c, q, p, R, pd, Rd);
    optics_at(m, c, o);
    optical_paths(m, o, &g, pd, Rd, path, NULL);
    return DTC_OK;
}

int dtc_session_init(dtc_session *s, const dtc_model *m, const dtc_conditions *zero)
{
    dtc_conditions c = *zero;
    optics_state o;
    const double home[3] = {0.0, 0.0, 0.0};
    s->model = m;
    c.currents_A[0] = c.currents_A[1] = c.currents_A[2] = 0.0;
    return paths_at(m, &c, home, NULL, s->paths_zero, &o);
}

int dtc_forward(const dtc_session *s, const double q[3], const dtc_conditions *c,
                dtc_pose *pose, double readings_m[3])
{
    double path[3];
    optics_state o;
    int k, rc = paths_at(s->model, c, q, pose, path, &o);
    if (rc != DTC_OK) return rc;
    for (k = 0; k < 3; k++) readings_m[k] = (path[k] - s->paths_zero[k]) / o.n_comp[k];
    return DTC_OK;
}

int dtc_inverse(const dtc_session *s, const double target_m[3], const dtc_conditions *c,
                const double q0[3], dtc_pose *pose, double tol_m, int max_iter, double q[3],
                double *residual_m, int *iterations)
{
    const dtc_model *m = s->model;
    geometry g;
    optics_state o;
    double A[3][2][3], dA[3][2][3], d[3][2][3], f[6], M[9][9], rhs[9], step[9];
    double p[3], R[3][3], pd[3], Rd[3][3], path[3], r[3], Jp[3][6], dR[3][3], resid = INFINITY;
    int steps = 0, kin_ok = 0, it, i, j, k, a, status, rc;
    geometry_at(m, c, &g);
    optics_at(m, c, &o);
    for (i = 0; i < 3; i++) q[i] = q0 == NULL ? 0.0 : q0[i];
    elbows(m, &g, q, A, dA);
    rc = initial_pose(&g, A, pose, p, R);
    if (rc != DTC_OK) return rc;
    for (it = 0; it <= max_iter; it++) {    /* the last pass evaluates the last step only */
        elbows(m, &g, q, A, dA);
        for (i = 0; i < 9; i++)
            for (j = 0; j < 9; j++) M[i][j] = 0.0;
        rod_system(&g, A, p, R, f, M, d);   /* rows 0-5, columns 0-5: move them to 3-8 below */
        deflected(m, c, q, p, R, pd, Rd);
        optical_paths(m, &o, &g, pd, Rd, path, Jp);
        resid = 0.0;
        for (k = 0; k < 3; k++) {
            r[k] = (path[k] - s->paths_zero[k]) / o.n_comp[k] - target_m[k];
            resid = fabs(r[k]) > resid || r[k] != r[k] ? fabs(r[k]) : resid;
        }
        /* |d|^2 - L^2 = 2 L (|d| - L): the rods closed to 1e-13 m */
        kin_ok = 1;
        for (i = 0; i < 3; i++)
            for (j = 0; j < 2; j++) kin_ok = kin_ok && fabs(f[2 * i + j]) / (2.0 * g.L[i][j]) < 1e-13;
        if ((resid <= tol_m && kin_ok) || steps == max_iter) break;
        /* rows: 6 rod equations, 3 readings; columns: q (3), p (3), rotation (3) */
        for (i = 0; i < 6; i++) {
            for (j = 5; j >= 0; j--) M[i][3 + j] = M[i][j];
            M[i][0] = M[i][1] = M[i][2] = 0.0;
        }
        for (i = 0; i < 3; i++)
            for (j = 0; j < 2; j++) M[2 * i + j][i] = -2.0 * dot(d[i][j], dA[i][j]);
        for (k = 0; k < 3; k++)
            for (a = 0; a < 6; a++) M[6 + k][3 + a] = Jp[k][a] / o.n_comp[k];
        for (i = 0; i < 6; i++) rhs[i] = -f[i];
        for (k = 0; k < 3; k++) rhs[6 + k] = -r[k];
        if (solve(9, M, rhs, step) != 0) { resid = NAN; break; }
        for (i = 0; i < 3; i++) {
            q[i] += step[i];
            p[i] += step[3 + i];
        }
        rotation(step + 6, dR);
        matmul(dR, R, R);
        steps++;
    }
    status = resid <= tol_m && kin_ok ? DTC_CONVERGED : DTC_NOT_CONVERGED;
    for (i = 0; i < 3; i++)
        if (q[i] < m->stroke[0] - 1e-12 || q[i] > m->stroke[1] + 1e-12) status = DTC_OUT_OF_STROKE;
    if (!(isfinite(q[0]) && isfinite(q[1]) && isfinite(q[2]) && isfinite(resid)))
        status = DTC_NOT_FINITE;
    set_pose(pose, p, R);
    *residual_m = resid;
    *iterations = steps;
    return status;
}
