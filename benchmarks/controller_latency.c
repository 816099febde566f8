/* The C evaluator's inverse timed in C alone (no Python, no ctypes), for
 * benchmarks/bench_controller.py: controller_latency BLOCK.bin POINTS.bin REPEAT
 *
 * POINTS.bin (float64): the session zero's conditions (18 temperatures degC, pressure Pa,
 * 3 currents A), then per point its target (3, m) and conditions (22). Each point is solved
 * from home (its q and pose kept), then, timed, from home and as the next point of a path (the
 * target 1 um further on each axis) warm-started from that q and pose, REPEAT times over the
 * points. Prints: points, CPU us per point from home, warm-started, the mean Newton steps of
 * each, and the number of points not converged. */
#include <stdio.h>
#include <stdlib.h>
#include <time.h>

#include "controller_evaluator.h"

#define MAX_POINTS 2000
#define COND_SIZE (DTC_N_TEMPERATURES + 4)

static double block[400000];
static double points[COND_SIZE + MAX_POINTS * (3 + COND_SIZE)];
static dtc_conditions cond[MAX_POINTS];
static dtc_pose poses[MAX_POINTS];
static double q_home[MAX_POINTS][3];

static void conditions(const double *v, dtc_conditions *c)
{
    int k;
    for (k = 0; k < DTC_N_TEMPERATURES; k++) c->T_C[k] = v[k];
    c->pressure_Pa = v[DTC_N_TEMPERATURES];
    for (k = 0; k < 3; k++) c->currents_A[k] = v[DTC_N_TEMPERATURES + 1 + k];
}

int main(int argc, char **argv)
{
    dtc_model model;
    dtc_session session;
    dtc_conditions zero;
    size_t n, got;
    int n_points, repeat, i, r, k, steps, bad = 0;
    double q[3], resid, cold_steps = 0, warm_steps = 0, cold_us, warm_us;
    const double *target;
    clock_t t0;
    FILE *f;
    if (argc != 4) {
        fprintf(stderr, "usage: controller_latency BLOCK.bin POINTS.bin REPEAT\n");
        return 2;
    }
    if (dtc_read_block(argv[1], block, sizeof block / sizeof *block, &n) != DTC_OK
        || dtc_model_init(&model, block, n) != DTC_OK) {
        fprintf(stderr, "%s: not a controller block\n", argv[1]);
        return 2;
    }
    f = fopen(argv[2], "rb");
    if (f == NULL) return 2;
    got = fread(points, sizeof(double), sizeof points / sizeof *points, f);
    fclose(f);
    n_points = (int)((got - COND_SIZE) / (3 + COND_SIZE));
    repeat = atoi(argv[3]);
    conditions(points, &zero);
    if (n_points < 1 || repeat < 1 || dtc_session_init(&session, &model, &zero) != DTC_OK) return 2;
    for (i = 0; i < n_points; i++)
        conditions(points + COND_SIZE + i * (3 + COND_SIZE) + 3, &cond[i]);
    t0 = clock();
    for (r = 0; r < repeat; r++)
        for (i = 0; i < n_points; i++) {
            target = points + COND_SIZE + i * (3 + COND_SIZE);
            poses[i].valid = 0;
            bad += dtc_inverse(&session, target, &cond[i], NULL, &poses[i], 1e-12, 20, q_home[i],
                               &resid, &steps) != DTC_CONVERGED;
            cold_steps += steps;
        }
    cold_us = (double)(clock() - t0) / CLOCKS_PER_SEC / (repeat * n_points) * 1e6;
    t0 = clock();
    for (r = 0; r < repeat; r++)
        for (i = 0; i < n_points; i++) {
            double next[3];
            dtc_pose pose = poses[i];
            target = points + COND_SIZE + i * (3 + COND_SIZE);
            for (k = 0; k < 3; k++) next[k] = target[k] + 1e-6;
            bad += dtc_inverse(&session, next, &cond[i], q_home[i], &pose, 1e-12, 20, q, &resid,
                               &steps) != DTC_CONVERGED;
            warm_steps += steps;
        }
    warm_us = (double)(clock() - t0) / CLOCKS_PER_SEC / (repeat * n_points) * 1e6;
    printf("%d %.3f %.3f %.2f %.2f %d\n", n_points, cold_us, warm_us,
           cold_steps / (repeat * n_points), warm_steps / (repeat * n_points), bad);
    return 0;
}
