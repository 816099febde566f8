/* Portable C99 evaluator of a physics model exported for a real-time controller
 * (deltatwin-physics-controller): the same model as controller_evaluator.py, the numpy
 * reference, written for embedding: libm only, no allocation, every per-point call on the
 * stack. docs/compensation.md ("The C evaluator") describes its use.
 *
 * The model: the exporter (calibration/physics/export.py) writes beside FILE.json a flat block
 * FILE.bin of little-endian IEEE-754 doubles, generated from the same contents as the JSON
 * (calibration/physics/controller_c.py, coefficient_block, is the layout's one definition):
 *
 *   magic DTC_MAGIC, layout version DTC_LAYOUT_VERSION, length of the block (doubles),
 *   reference_C, cte_per_K base, arms, rods, platform,
 *   B_m (3,3), axis (3,3), arm_vec_m (3,2,3), P0_m (3,2,3), L_m (3,2), theta_zero_rad (3),
 *   cube_offset_m (3), cube_size_m, stroke_rad (2),
 *   has_gravity, gravity_N (3), has_magnetic, magnet_moment_Am2, coil_moment_per_A,
 *   magnets_platform_m (3,3), coils_m (3,3),
 *   heads_m (3,3), directions (3,3), fold_m (3), fold_normal (3),
 *   number of optics steps, each DTC_STEP_SIZE doubles: its kind (DTC_LOOP_DRIFT: reference_C,
 *   frame_height_m, frame_arm_m (2), table, frame, support cte_per_K; DTC_BEAM_MISALIGNMENT:
 *   angle_rad (3,2), abbe_offset_m (3,2); DTC_AIR_REFRACTION: wavelength_m,
 *   beam_room_fraction, compensation_offset_C (3), assumed_pressure_Pa, vapour_pressure_Pa),
 *   zero-padded,
 *   statics q_range_rad (2), degree d, coefficients (d+1, d+1, d+1, 42) row-major: the preload
 *   deflection (6) then the compliance (6,6) row-major.
 *
 * Use: read the block once at start-up (dtc_read_block into a static buffer, or link it in),
 * dtc_model_init; per session zero dtc_session_init; per point dtc_inverse (target readings ->
 * motor coordinates) or dtc_forward. Units: m, rad, degC, Pa, A, N.
 */
#ifndef DELTATWIN_CONTROLLER_EVALUATOR_H
#define DELTATWIN_CONTROLLER_EVALUATOR_H

#include <stddef.h>

#define DTC_MAGIC 1146373937.0          /* "DTC1" as an integer */
#define DTC_LAYOUT_VERSION 1.0
#define DTC_MAX_STEPS 8
#define DTC_STEP_SIZE 13
#define DTC_MAX_DEGREE 20
#define DTC_LOOP_DRIFT 1
#define DTC_BEAM_MISALIGNMENT 2
#define DTC_AIR_REFRACTION 3

/* the conditions' temperatures, degC, in the JSON's inputs.temperatures_C order */
enum {
    DTC_BASE, DTC_ARM1, DTC_ARM2, DTC_ARM3, DTC_ROD1, DTC_ROD2, DTC_ROD3, DTC_PLATFORM,
    DTC_TABLE, DTC_FRAME, DTC_AIR_X, DTC_AIR_Y, DTC_AIR_Z, DTC_COMP_X, DTC_COMP_Y, DTC_COMP_Z,
    DTC_ROOM, DTC_SUPPORT, DTC_N_TEMPERATURES
};

/* what dtc_inverse returns (the numpy evaluator's statuses); errors are negative */
enum {
    DTC_CONVERGED = 0, DTC_NOT_CONVERGED = 1, DTC_OUT_OF_STROKE = 2, DTC_NOT_FINITE = 3,
    DTC_OK = 0,
    DTC_ERR_BLOCK = -1,         /* not a block of this layout (magic, version, length, kind) */
    DTC_ERR_NO_POSE = -2,       /* the rods cannot reach the platform at these q */
    DTC_ERR_NOT_CLOSED = -3,    /* the kinematic loop did not close to 1e-12 m */
    DTC_ERR_FILE = -4           /* the block file cannot be read or does not fit the buffer */
};

typedef struct {
    int kind;
    double v[DTC_STEP_SIZE - 1];
} dtc_step;

typedef struct {
    double T_ref, cte[4];               /* base, arms, rods, platform; 1/K */
    double B[3][3], axis[3][3], arm_vec[3][2][3], P0[3][2][3], L[3][2], theta_zero[3];
    double cube_offset[3], cube_size, stroke[2];
    int has_gravity, has_magnetic;
    double gravity_N[3], magnet_moment, coil_moment_per_A, magnets[3][3], coils[3][3];
    double heads[3][3], directions[3][3], fold[3], fold_normal[3];
    int n_steps;
    dtc_step steps[DTC_MAX_STEPS];
    double q_range[2];
    int degree;
    const double *statics;              /* into the caller's block: (d+1)^3 x 42 */
} dtc_model;

typedef struct {
    double T_C[DTC_N_TEMPERATURES];     /* degC */
    double pressure_Pa;
    double currents_A[3];
} dtc_conditions;

typedef struct {                        /* the platform's kinematic pose: a warm start */
    int valid;
    double p[3], R[3][3];
} dtc_pose;

typedef struct {
    const dtc_model *model;
    double paths_zero[3];               /* optical paths at the session's zero, m */
} dtc_session;

/* the model from a block of n doubles; the block must outlive the model (not copied) */
int dtc_model_init(dtc_model *m, const double *block, size_t n);
/* a block file into buf (capacity cap doubles); *n its length. Start-up only (stdio). */
int dtc_read_block(const char *path, double *buf, size_t cap, size_t *n);
/* conditions at the reference temperature, 101325 Pa, coils off */
void dtc_conditions_reference(const dtc_model *m, dtc_conditions *c);
/* a session's zero: home, coils off (its currents are ignored), the zero's conditions */
int dtc_session_init(dtc_session *s, const dtc_model *m, const dtc_conditions *zero);
/* readings (3) m counted from the session's zero at motor coordinates q (3) rad; pose: a
 * warm start when pose->valid, set to the kinematic pose found (NULL: none) */
int dtc_forward(const dtc_session *s, const double q[3], const dtc_conditions *c,
                dtc_pose *pose, double readings_m[3]);
/* motor coordinates q (3) rad at which the readings equal target_m (3): Newton on (q, p, R),
 * from q0 (NULL: home) and pose (valid: a previous solution's; else the closed-form start at
 * q0; set to the solution's). Converged when every axis' residual, the model evaluated in
 * full, is <= tol_m and the rods close to 1e-13 m; at most max_iter steps. Returns the status;
 * *residual_m the largest axis residual, *iterations the steps taken. */
int dtc_inverse(const dtc_session *s, const double target_m[3], const dtc_conditions *c,
                const double q0[3], dtc_pose *pose, double tol_m, int max_iter, double q[3],
                double *residual_m, int *iterations);

#endif
