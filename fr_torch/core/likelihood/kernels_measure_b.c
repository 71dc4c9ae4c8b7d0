/* Fused measure-b scoring (fr_measure_b_scores), the refinement's objective with its gradient
 * (fr_measure_b_grad) and the refinement loop, with or without the division model's k
 * (fr_measure_b_refine): fr_torch/core/likelihood/native.py builds, checks and calls this file.
 *
 * Every value is the torch path's (fr_torch/core/likelihood/objective.py: objective_b_nograd,
 * measure_b_forward / measure_b_backward; fr_torch/core/search/refine.py and lens.py for the loop)
 * bit for bit:
 * the same IEEE float32 operations in the same order (compiled with -ffp-contract=off, no fast
 * math), and atan / exp / log / sin / cos / sqrt through the same MKL VML routines torch's CPU
 * kernels call (their addresses are passed in by the caller).  Only the sum over segments is done differently: each
 * term is rounded to the image's fixed-point grid (fr_torch/core/exact.py, exact_sum) and the
 * integers are added in double, where every order gives the same sum.  The per-segment deviations
 * are never stored: a tile of hypotheses is scored a few segments at a time in small buffers.
 */
#include <float.h>
#include <math.h>
#include <stdint.h>

typedef void (*vml_fn)(int n, const float *a, float *r);

#define TILE 256 /* at most this many hypotheses per tile: buffers of a few KB, in L1 */

/* |s / t| with NaN -> 0 and +inf -> FLT_MAX (torch's div_, abs_, nan_to_num_(nan=0)) */
/* round half to even (torch.round, nearbyint in the default rounding mode) without a libm call:
 * below 2^23 adding and subtracting 2^23 rounds to an integer; from 2^23 on a float is one */
static inline float round_even(float x) {
    const float a = fabsf(x);
    const float rounded = copysignf((a + 0x1p23f) - 0x1p23f, x);
    return a < 0x1p23f ? rounded : x;  /* both sides computed: the loops vectorise */
}

static inline float ratio(float s, float t) {
    const float r = fabsf(s / t);
    const float finite = r > FLT_MAX ? FLT_MAX : r;
    return r != r ? 0.0f : finite;
}

/* Elements per MKL call: each call costs about as much as a hundred elements, so rows of several
 * segments are gathered into one call. */
#define CALL 1024

/* One work item = (image b, tile of `tile` <= TILE hypotheses, a multiple of `block`).
 *
 * line_along (B, 2N, 3): the N line rows then the N along rows; factor (B, N): weight * scale of
 * the exact sum (float32, as exact_sum forms it); scale (B,): the exact sum's power of two (double);
 * flat (B, 3, 3H): VP-major vanishing points, column k * H + h = VP k of hypothesis h.
 * coef[6] = (-1/lambda, log(prior/lambda)) of VP 0, 1, 2; vertical = the vertical VP's index;
 * block: runs of `block` hypotheses share the vertical VP (scored once, at the run's first).
 * out (B, H) double. */
void fr_measure_b_scores(int64_t first_item, int64_t last_item, int64_t tiles_per_image, int64_t tile,
                         int64_t n_seg, int64_t hyp, int64_t block, int64_t vertical,
                         const float *line_along, const float *factor, const double *scale,
                         const float *flat, const float *coef, float background, float floor_value,
                         vml_fn v_atan, vml_fn v_exp, vml_fn v_ln, double *out) {
    float col[3][3][TILE];               /* [VP][coordinate][hypothesis in tile] */
    float x[CALL + 3 * TILE], p[CALL + TILE];
    double acc[TILE];
    int horizontal[2], k = 0;
    for (int vp = 0; vp < 3; vp++) if (vp != vertical) horizontal[k++] = vp;
    for (int64_t item = first_item; item < last_item; item++) {
        int64_t b = item / tiles_per_image;
        int64_t h0 = (item % tiles_per_image) * tile;
        int64_t width = hyp - h0 < tile ? hyp - h0 : tile;
        int64_t runs = (width + block - 1) / block;   /* vertical VPs in this tile (h0 is a multiple of block) */
        int64_t stride = 2 * width + runs;           /* a segment's row of x: horizontal 0, horizontal 1, vertical */
        int64_t rows = CALL / stride > 1 ? CALL / stride : 1;
        const float *fb = flat + b * 9 * hyp;
        for (int vp = 0; vp < 3; vp++)
            for (int c = 0; c < 3; c++)
                for (int64_t j = 0; j < width; j++) col[vp][c][j] = fb[c * 3 * hyp + vp * hyp + h0 + j];
        for (int64_t j = 0; j < width; j++) acc[j] = 0.0;
        const float *lines = line_along + b * 2 * n_seg * 3;
        const float *alongs = lines + n_seg * 3;
        for (int64_t i0 = 0; i0 < n_seg; i0 += rows) {
            int64_t count = n_seg - i0 < rows ? n_seg - i0 : rows;
            for (int64_t r = 0; r < count; r++) {
                const int64_t i = i0 + r;
                const float l0 = lines[3 * i], l1 = lines[3 * i + 1], l2 = lines[3 * i + 2];
                const float g0 = alongs[3 * i], g1 = alongs[3 * i + 1], g2 = alongs[3 * i + 2];
                float *row = x + r * stride;
                for (int q = 0; q < 3; q++) {
                    const int vp = q < 2 ? horizontal[q] : (int)vertical;
                    const int64_t step = q < 2 ? 1 : block, n = q < 2 ? width : runs;
                    const float *c0 = col[vp][0], *c1 = col[vp][1], *c2 = col[vp][2];
                    float *dst = row + q * width;
                    for (int64_t m = 0; m < n; m++) {
                        const int64_t j = m * step;
                        float s = l0 * c0[j] + l1 * c1[j];
                        s = s + l2 * c2[j];
                        float t = g0 * c0[j] + g1 * c1[j];
                        t = t + g2 * c2[j];
                        dst[m] = ratio(s, t);
                    }
                }
            }
            v_atan((int)(count * stride), x, x);
            for (int64_t r = 0; r < count; r++) {
                float *row = x + r * stride;
                for (int q = 0; q < 3; q++) {
                    const int vp = q < 2 ? horizontal[q] : (int)vertical;
                    const float a = coef[2 * vp], d = coef[2 * vp + 1];
                    float *dst = row + q * width;
                    const int64_t n = q < 2 ? width : runs;
                    for (int64_t m = 0; m < n; m++) {
                        float y = dst[m] * a + d;
                        dst[m] = y < floor_value ? floor_value : y;
                    }
                }
            }
            v_exp((int)(count * stride), x, x);
            for (int64_t r = 0; r < count; r++) {
                const float *row = x + r * stride;
                float *pr = p + r * width;
                for (int64_t j = 0; j < width; j++) pr[j] = row[2 * width + j / block];  /* the run's vertical */
                for (int64_t j = 0; j < width; j++) {
                    float sum = row[j] + row[width + j];
                    sum = sum + pr[j];
                    pr[j] = sum + background;
                }
            }
            v_ln((int)(count * width), p, p);
            for (int64_t r = 0; r < count; r++) {
                const float f = factor[b * n_seg + i0 + r];
                const float *pr = p + r * width;
                for (int64_t j = 0; j < width; j++) acc[j] += (double)round_even(pr[j] * f);
            }
        }
        for (int64_t j = 0; j < width; j++) out[b * hyp + h0 + j] = acc[j] / scale[b];
    }
}

#include <stdlib.h>

/* fixed_point_scale (fr_torch/core/exact.py) of a float32 bound: 2^(30 - e) with bound < 2^e,
 * e clamped below at -90; a non-finite bound is returned as the scale. */
static double fixed_point_scale(float bound) {
    double b = (double)bound;
    if (!isfinite(b)) return b;
    int e;
    frexp(b, &e);
    if (e < -90) e = -90;
    return ldexp(1.0, 30 - e);
}

/* torch.sign of a float: +1, -1 or 0 (+0 for +-0 and NaN) */
static inline float sign_of(float x) {
    const float negative = x < 0.0f ? -1.0f : 0.0f;
    return x > 0.0f ? 1.0f : negative;
}

/* the bits of a float's magnitude: ordered as the magnitudes, NaN above infinity */
static inline uint32_t magnitude_bits(float x) {
    union { float f; uint32_t u; } v = {x};
    return v.u & 0x7fffffffu;
}

/* Buffers of the gradient pass for up to `hyp` hypotheses of an image with `n_seg` segments: one
 * block of floats (grad_floats) carved into the arrays below. */
typedef struct {
    int64_t rows;               /* segments per MKL call */
    float *s, *t, *x, *e;       /* (rows, 3H): incidence s, t; atan; exp */
    float *a, *d;               /* (3H): each column's -1/lambda and log(prior/lambda) */
    float *gs, *gt;             /* (3H): a segment's d obj / d s and d obj / d t */
    float *p, *g;               /* (rows, H): p_i then log p_i; w_i / p_i * grad_out */
    float *terms;               /* (3, N, 3H): each coordinate's gradient terms */
    double *acc;                /* (H) the objective's exact sum; NULL: the gradient alone */
} grad_work;

static int64_t grad_rows(int64_t hyp) { return CALL / (3 * hyp) > 1 ? CALL / (3 * hyp) : 1; }

static size_t grad_floats(int64_t n_seg, int64_t hyp) {
    const int64_t width = 3 * hyp, cells = grad_rows(hyp) * width;
    return (size_t)(4 * cells + 4 * width + 2 * grad_rows(hyp) * hyp + 3 * n_seg * width + 1);
}

static void grad_work_carve(grad_work *w, float *block, double *acc, int64_t hyp) {
    const int64_t width = 3 * hyp;
    w->rows = grad_rows(hyp);
    const int64_t cells = w->rows * width;
    w->s = block; w->t = w->s + cells; w->x = w->t + cells; w->e = w->x + cells;
    w->a = w->e + cells; w->d = w->a + width; w->gs = w->d + width; w->gt = w->gs + width;
    w->p = w->gt + width; w->g = w->p + w->rows * hyp; w->terms = w->g + w->rows * hyp;
    w->acc = acc;
}

/* Pass 1 of one image's objective and gradient for its `hyp` hypotheses: measure_b_forward and the
 * terms of measure_b_backward (fr_torch/core/likelihood/objective.py) bit for bit.
 *
 * fb (3, 3H) VP-major vanishing points; lines / alongs (N, 3); weight_b, factor_b (N); go (H)
 * the upstream gradient.  Leaves sum_i round(log p_i * factor_i) in w->acc (H) (nothing without
 * w->acc; factor_b is then not read), every gradient term in w->terms and raises largest[c] to the
 * magnitude bits of coordinate c's largest |term|.
 *
 * line_grad (2N, 3), or NULL: measure_b_backward with the vanishing points, d obj / d line_along
 * (the N line rows, then the N along rows; each row's sum over the 3H columns left to right), after
 * that pass has dropped the terms below float's normal range (|common| < FLT_MIN -> 0). */
static void grad_terms(const grad_work *w, int64_t n_seg, int64_t hyp, int64_t vertical,
                       const float *lines, const float *alongs, const float *weight_b, const float *factor_b,
                       const float *fb, const float *coef, float background, float floor_value, const float *go,
                       vml_fn v_atan, vml_fn v_exp, vml_fn v_ln, uint32_t largest[3], float *line_grad) {
    const int64_t width = 3 * hyp, rows = w->rows;
    float *s = w->s, *t = w->t, *x = w->x, *e = w->e, *a = w->a, *d = w->d, *gs = w->gs, *gt = w->gt;
    float *p = w->p, *g = w->g, *terms = w->terms;
    double *acc = w->acc;
    for (int k = 0; k < 3; k++)
        for (int64_t h = 0; h < hyp; h++) { a[k * hyp + h] = coef[2 * k]; d[k * hyp + h] = coef[2 * k + 1]; }
    int horizontal[2], q = 0;
    for (int k = 0; k < 3; k++) if (k != vertical) horizontal[q++] = k;
    if (acc != NULL)
        for (int64_t h = 0; h < hyp; h++) acc[h] = 0.0;
    for (int64_t i0 = 0; i0 < n_seg; i0 += rows) {
        const int64_t count = n_seg - i0 < rows ? n_seg - i0 : rows;
        for (int64_t r = 0; r < count; r++) {
            const float *l = lines + 3 * (i0 + r), *m = alongs + 3 * (i0 + r);
            for (int64_t j = 0; j < width; j++) {
                float sj = l[0] * fb[j] + l[1] * fb[width + j];
                sj = sj + l[2] * fb[2 * width + j];
                float tj = m[0] * fb[j] + m[1] * fb[width + j];
                tj = tj + m[2] * fb[2 * width + j];
                s[r * width + j] = sj;
                t[r * width + j] = tj;
                x[r * width + j] = ratio(sj, tj);
            }
        }
        v_atan((int)(count * width), x, x);
        for (int64_t r = 0; r < count; r++)
            for (int64_t j = 0; j < width; j++) {
                float y = x[r * width + j] * a[j] + d[j];
                e[r * width + j] = y < floor_value ? floor_value : y;
            }
        v_exp((int)(count * width), e, e);
        for (int64_t r = 0; r < count; r++) {
            const float *er = e + r * width;
            const float wi = weight_b[i0 + r];
            for (int64_t h = 0; h < hyp; h++) {
                float sum = er[horizontal[0] * hyp + h] + er[horizontal[1] * hyp + h];
                sum = sum + er[vertical * hyp + h];
                sum = sum + background;
                p[r * hyp + h] = sum;
                g[r * hyp + h] = (wi / sum) * go[h];
            }
        }
        if (acc != NULL) {
            v_ln((int)(count * hyp), p, p);  /* p is log p from here on */
            for (int64_t r = 0; r < count; r++) {
                const float f = factor_b[i0 + r];
                for (int64_t h = 0; h < hyp; h++) acc[h] += (double)round_even(p[r * hyp + h] * f);
            }
        }
        for (int64_t r = 0; r < count; r++) {
            const int64_t i = i0 + r;
            const float *l = lines + 3 * i, *m = alongs + 3 * i;
            const float *sr = s + r * width, *tr = t + r * width, *er = e + r * width;
            for (int k = 0; k < 3; k++)  /* each VP's block of columns takes the hypothesis' g */
                for (int64_t h = 0; h < hyp; h++) gs[k * hyp + h] = g[r * hyp + h];
            for (int64_t j = 0; j < width; j++) {
                const float sj = sr[j], tj = tr[j];
                float r2 = sj * sj + tj * tj;
                r2 = r2 < FLT_MIN ? FLT_MIN : r2;  /* clamp_min_(tiny); NaN stays NaN */
                float common = er[j] * a[j];
                common = common * gs[j];
                common = common * sign_of(sj * tj);
                common = common / r2;
                if (line_grad != NULL && fabsf(common) < FLT_MIN) common = 0.0f;  /* masked_fill_; NaN stays */
                gs[j] = common * tj;
                gt[j] = -(common * sj);
            }
            for (int c = 0; c < 3; c++) {
                float *row = terms + (c * n_seg + i) * width;
                const float lc = l[c], mc = m[c];
                uint32_t top = largest[c];
                for (int64_t j = 0; j < width; j++) {
                    const float term = lc * gs[j] + mc * gt[j];
                    row[j] = term;
                    const uint32_t bits = magnitude_bits(term);
                    top = bits > top ? bits : top;
                }
                largest[c] = top;
            }
            if (line_grad != NULL)
                for (int c = 0; c < 3; c++) {
                    const float *column = fb + c * width;
                    float line_c = gs[0] * column[0], along_c = gt[0] * column[0];
                    for (int64_t j = 1; j < width; j++) {
                        line_c = line_c + gs[j] * column[j];
                        along_c = along_c + gt[j] * column[j];
                    }
                    line_grad[3 * i + c] = line_c;
                    line_grad[3 * (n_seg + i) + c] = along_c;
                }
        }
    }
}

/* Column sums of terms (rows, width) into out (width) double, exact on the grid set by the largest
 * |term| (`largest`, its magnitude bits): fr_torch/core/exact.py, exact_sum with that bound. */
static void exact_columns(const float *terms, int64_t rows, int64_t width, uint32_t largest, double *out) {
    union { uint32_t u; float f; } top = {largest};
    const double grid = fixed_point_scale(top.f);  /* NaN when a term is NaN, as torch's amax */
    const float grid32 = (float)grid;
    for (int64_t j = 0; j < width; j++) out[j] = 0.0;
    for (int64_t i = 0; i < rows; i++) {
        const float *row = terms + i * width;
        for (int64_t j = 0; j < width; j++) out[j] += (double)round_even(row[j] * grid32);
    }
    for (int64_t j = 0; j < width; j++) out[j] = out[j] / grid;
}

/* Pass 2: d objective / d fb (3, 3H) double into out, each coordinate's sum over segments exact on
 * the grid set by the image's largest |term| of that coordinate (`largest`, over every hypothesis
 * of the image). */
static void grad_sums(const grad_work *w, int64_t n_seg, int64_t hyp, const uint32_t largest[3], double *out) {
    const int64_t width = 3 * hyp;
    for (int c = 0; c < 3; c++) exact_columns(w->terms + c * n_seg * width, n_seg, width, largest[c], out + c * width);
}

/* The refinement's objective and its gradient with respect to the vanishing points, per image:
 * measure_b_forward followed by measure_b_backward (fr_torch/core/likelihood/objective.py) bit for bit.
 *
 * Images [first, last) of the batch; hyp hypotheses each (columns k * hyp + h of flat (B, 3, 3H));
 * weight (B, N), factor (B, N) and scale (B,) as for fr_measure_b_scores; grad_out (B, H) float32.
 * objective (B, H) double; grad (B, 3, 3H) double: d objective / d flat, each coordinate's sum over
 * segments exact on the grid set by the image's largest |term| of that coordinate. */
int fr_measure_b_grad(int64_t first, int64_t last, int64_t n_seg, int64_t hyp, int64_t vertical,
                      const float *line_along, const float *weight, const float *factor, const double *scale,
                      const float *flat, const float *coef, float background, float floor_value,
                      const float *grad_out, vml_fn v_atan, vml_fn v_exp, vml_fn v_ln,
                      double *objective, double *grad) {
    float *block = malloc(sizeof(float) * grad_floats(n_seg, hyp));
    double *acc = malloc(sizeof(double) * (size_t)(hyp + 1));
    if (block == NULL || acc == NULL) { free(block); free(acc); return 1; }
    grad_work w;
    grad_work_carve(&w, block, acc, hyp);
    for (int64_t b = first; b < last; b++) {
        const float *lines = line_along + b * 2 * n_seg * 3;
        uint32_t largest[3] = {0, 0, 0};
        grad_terms(&w, n_seg, hyp, vertical, lines, lines + n_seg * 3, weight + b * n_seg, factor + b * n_seg,
                   flat + b * 9 * hyp, coef, background, floor_value, grad_out + b * hyp, v_atan, v_exp, v_ln,
                   largest, NULL);
        for (int64_t h = 0; h < hyp; h++) objective[b * hyp + h] = acc[h] / scale[b];
        grad_sums(&w, n_seg, hyp, largest, grad + b * 9 * hyp);
    }
    free(block);
    free(acc);
    return 0;
}

/* ---- The refinement loop (fr_measure_b_refine) ------------------------------------------------ */


#define DEG2RAD 0.017453292519943295f   /* (float)(pi / 180): torch.deg2rad of a float tensor */

/* The division model's segments at one k: SegmentGeometry.features(k, derivative=True)
 * (fr_torch/core/search/lens.py) of one image, bit for bit.
 *
 * centre (2) the distortion centre, pixels; offset (2N, 2) the endpoints' offsets from it (the N
 * first endpoints, then the N second ones), rho (2N) their r^2 in units of the normalising radius^2
 * (SegmentGeometry.offsets).  rows (2N, 3): the undistorted segments' line then along rows
 * (SegmentFeatures.line_along); d_rows (2N, 3) their derivative with respect to k; scratch: 7N floats. */
static void undistorted_rows(int64_t n_seg, float k, const float *centre, const float *offset, const float *rho,
                             vml_fn v_sqrt, float *scratch, float *rows, float *d_rows) {
    const float min_length = (float)1e-12;  /* clamp_min(1e-12) of a float tensor */
    float *factor = scratch, *q = factor + 2 * n_seg, *length = q + 4 * n_seg;
    for (int64_t i = 0; i < 2 * n_seg; i++) {  /* undistorted = centre + factor * offset */
        const float f = 1.0f / (1.0f + k * rho[i]);
        factor[i] = f;
        q[2 * i] = offset[2 * i] * f;
        q[2 * i + 1] = offset[2 * i + 1] * f;
    }
    for (int64_t i = 0; i < n_seg; i++) {
        const float *qa = q + 2 * i, *qb = q + 2 * (n_seg + i);
        const float dx = qb[0] - qa[0], dy = qb[1] - qa[1];
        length[i] = dx * dx + dy * dy;
    }
    v_sqrt((int)n_seg, length, length);  /* torch's sqrt of float32: MKL's */
    for (int64_t i = 0; i < n_seg; i++) {
        const int64_t a = i, b = n_seg + i;
        const float *qa = q + 2 * a, *qb = q + 2 * b, *oa = offset + 2 * a, *ob = offset + 2 * b;
        const float delta_x = qb[0] - qa[0], delta_y = qb[1] - qa[1];
        const float inv_length = 1.0f / (length[i] < min_length ? min_length : length[i]);  /* NaN stays NaN */
        const float dx = delta_x * inv_length, dy = delta_y * inv_length;
        const float mx = centre[0] + (qa[0] + qb[0]) * 0.5f, my = centre[1] + (qa[1] + qb[1]) * 0.5f;
        float *line = rows + 3 * a, *along = rows + 3 * b;
        line[0] = -dy; line[1] = dx; line[2] = dy * mx - dx * my;
        along[0] = dx; along[1] = dy; along[2] = -(dx * mx + dy * my);
        const float ca = (-rho[a] * factor[a]) * factor[a], cb = (-rho[b] * factor[b]) * factor[b];  /* dq / dk */
        const float dqa_x = oa[0] * ca, dqa_y = oa[1] * ca, dqb_x = ob[0] * cb, dqb_y = ob[1] * cb;
        const float dd_x = dqb_x - dqa_x, dd_y = dqb_y - dqa_y;
        const float along_dd = dx * dd_x + dy * dd_y;
        const float ddx = (dd_x - dx * along_dd) * inv_length, ddy = (dd_y - dy * along_dd) * inv_length;
        const float dmx = (dqa_x + dqb_x) * 0.5f, dmy = (dqa_y + dqb_y) * 0.5f;
        float *d_line = d_rows + 3 * a, *d_along = d_rows + 3 * b;
        float x = ddy * mx + dy * dmx;
        x = x - ddx * my;
        d_line[0] = -ddy; d_line[1] = ddx; d_line[2] = x - dx * dmy;
        x = ddx * mx + dx * dmx;
        x = x + ddy * my;
        d_along[0] = ddx; d_along[1] = ddy; d_along[2] = -(x + dy * dmy);
    }
}

/* What every work item of fr_measure_b_refine shares: its arguments. */
typedef struct {
    int64_t n_seg, hyp, vertical, iterations, params;
    const float *line_along, *weight, *coef;
    float background, floor_value;
    const float *grad_out, *pp, *lower, *span, *prior;
    float prior_centre, prior_flat;
    const float *steps;
    float beta1, one_minus_beta1, beta2, one_minus_beta2, eps, grad_bound;
    int64_t periodic_pan;
    const float *offset, *rho, *k_slope;  /* the division model; offset NULL without it */
    vml_fn v_atan, v_exp, v_ln, v_sin, v_cos, v_sqrt;
} refine_setup;

/* fr_measure_b_refine's workspace for a work item of up to H hypotheses (refine_work_carve). */
typedef struct {
    double *grad;                         /* (3, 3H) d obj / d V, VP-major */
    double *grad_k, *one;                 /* (H) d obj / dk; (3, 3) one hypothesis' d obj / d V */
    grad_work pass;                       /* the gradient pass: all H hypotheses, or one (division) */
    float *rad, *cosv, *sinv;             /* (H, 3) */
    float *focal, *logf, *logr, *k, *go;  /* (H) */
    float *flat, *rot;                    /* (3, 3H) VP-major; (H, 9) */
    float *m1, *m2, *root;                /* (H, P) Adam's moments, sqrt of the second */
    float *fb;                            /* (3, 3) one hypothesis' VPs */
    float *rows, *d_rows, *line_grad;     /* (2N, 3) one hypothesis' segments, d / dk, d obj / d rows */
    float *k_terms, *scratch;             /* (2N); 7N */
} refine_work;

/* Carves `block` (may be NULL: sizes only) into w for items of up to `hyp` hypotheses with
 * `params` parameters (5: the division model's buffers too); returns the floats used (doubles first,
 * two floats each). */
static int64_t refine_work_carve(refine_work *w, float *block, int64_t n_seg, int64_t hyp, int64_t params) {
    const int lens = params == 5;
    int64_t at = 0;
#define TAKE_DOUBLES(ptr, n) do { (ptr) = block != NULL ? (double *)(block + at) : NULL; at += 2 * (n); } while (0)
#define TAKE(ptr, n) do { (ptr) = block != NULL ? block + at : NULL; at += (n); } while (0)
    TAKE_DOUBLES(w->grad, 9 * hyp);
    TAKE_DOUBLES(w->grad_k, hyp);
    TAKE_DOUBLES(w->one, 9);
    const int64_t pass_hyp = lens ? 1 : hyp;
    if (block != NULL) grad_work_carve(&w->pass, block + at, NULL, pass_hyp);
    at += (int64_t)grad_floats(n_seg, pass_hyp);
    TAKE(w->rad, 3 * hyp); TAKE(w->cosv, 3 * hyp); TAKE(w->sinv, 3 * hyp);
    TAKE(w->focal, hyp); TAKE(w->logf, hyp); TAKE(w->logr, hyp); TAKE(w->k, hyp); TAKE(w->go, hyp);
    TAKE(w->flat, 9 * hyp); TAKE(w->rot, 9 * hyp);
    TAKE(w->m1, params * hyp); TAKE(w->m2, params * hyp); TAKE(w->root, params * hyp);
    TAKE(w->fb, 9);
    const int64_t lens_rows = lens ? 2 * n_seg : 0;
    TAKE(w->rows, 3 * lens_rows); TAKE(w->d_rows, 3 * lens_rows); TAKE(w->line_grad, 3 * lens_rows);
    TAKE(w->k_terms, lens_rows); TAKE(w->scratch, lens ? 7 * n_seg : 0);
#undef TAKE
#undef TAKE_DOUBLES
    return at;
}

/* Floats of the workspace fr_measure_b_refine needs per thread for work items of up to `hyp`
 * hypotheses with `params` (4 or 5) parameters. */
int64_t fr_refine_work_floats(int64_t n_seg, int64_t hyp, int64_t params) {
    refine_work w;
    return refine_work_carve(&w, NULL, n_seg, hyp, params);
}

/* Hypothesis h's gradient under the division model (fr_torch/core/search/refine.py,
 * objective_and_grad with a geometry): its segments undistorted with its k (undistorted_rows), d obj
 * / d V (one virtual image: the exact sums' grids its own) into column h of w->grad, and d obj / dk
 * = exact sum over rows of (d obj / d row) . (d row / dk), plus the prior on k's share, into
 * w->grad_k[h] (double, as torch's float64 sum). */
static void division_gradient(const refine_setup *s, const refine_work *w, int64_t b, int64_t h, int64_t count) {
    const int64_t n_seg = s->n_seg, width = 3 * count;
    undistorted_rows(n_seg, w->k[h], s->pp + 2 * b, s->offset + 4 * b * n_seg, s->rho + 2 * b * n_seg, s->v_sqrt,
                     w->scratch, w->rows, w->d_rows);
    for (int c = 0; c < 3; c++)
        for (int j = 0; j < 3; j++) w->fb[3 * c + j] = w->flat[c * width + j * count + h];
    uint32_t largest[3] = {0, 0, 0};
    grad_terms(&w->pass, n_seg, 1, s->vertical, w->rows, w->rows + 3 * n_seg, s->weight + b * n_seg, NULL, w->fb,
               s->coef, s->background, s->floor_value, w->go + h, s->v_atan, s->v_exp, s->v_ln, largest, w->line_grad);
    grad_sums(&w->pass, n_seg, 1, largest, w->one);
    for (int c = 0; c < 3; c++)
        for (int j = 0; j < 3; j++) w->grad[c * width + j * count + h] = w->one[3 * c + j];
    uint32_t top = 0;
    for (int64_t i = 0; i < 2 * n_seg; i++) {
        const float *gl = w->line_grad + 3 * i, *dl = w->d_rows + 3 * i;
        float term = gl[0] * dl[0] + gl[1] * dl[1];
        term = term + gl[2] * dl[2];
        w->k_terms[i] = term;
        const uint32_t bits = magnitude_bits(term);
        top = bits > top ? bits : top;
    }
    double grad_k;
    exact_columns(w->k_terms, 2 * n_seg, 1, top, &grad_k);
    if (s->k_slope != NULL) grad_k = grad_k + (double)(w->go[h] * (s->k_slope[b] * w->k[h]));
    w->grad_k[h] = grad_k;
}

/* Every step of one work item: hypotheses ub (count, P) of image b, stepped in place (the module
 * comment of fr_measure_b_refine). */
static void refine_hypotheses(const refine_setup *s, const refine_work *w, int64_t b, int64_t count, float *ub) {
    const int64_t n_seg = s->n_seg, P = s->params, width = 3 * count;
    const int lens = s->offset != NULL;
    const float *lines = s->line_along + b * 2 * n_seg * 3, *lo = s->lower + P * b, *sp_ = s->span + P * b;
    const float *pp = s->pp + 2 * b, *prior = s->prior;
    double *grad = w->grad;
    float *rad = w->rad, *cosv = w->cosv, *sinv = w->sinv, *focal = w->focal, *logf = w->logf, *logr = w->logr;
    float *flat = w->flat, *rot = w->rot, *m1 = w->m1, *m2 = w->m2, *root = w->root, *go = w->go;
    for (int64_t j = 0; j < P * count; j++) { m1[j] = 0.0f; m2[j] = 0.0f; }
    for (int64_t h = 0; h < count; h++) go[h] = s->grad_out[b];
    for (int64_t step = 0; step < s->iterations; step++) {
        for (int64_t h = 0; h < count; h++) {
            const float *uh = ub + P * h;
            for (int k = 0; k < 3; k++) rad[3 * h + k] = (lo[k] + uh[k] * sp_[k]) * DEG2RAD;
            logf[h] = lo[3] + uh[3] * sp_[3];
            if (lens) w->k[h] = lo[4] + uh[4] * sp_[4];
        }
        s->v_cos((int)(3 * count), rad, cosv);
        s->v_sin((int)(3 * count), rad, sinv);
        s->v_exp((int)count, logf, focal);
        for (int64_t h = 0; h < count; h++) {
            const float cp = cosv[3 * h], ct = cosv[3 * h + 1], cr = cosv[3 * h + 2];
            const float sp = sinv[3 * h], st = sinv[3 * h + 1], sr = sinv[3 * h + 2];
            const float spst = sp * st, cpst = cp * st;
            float *r = rot + 9 * h;  /* rotation_from_cos_sin: row i of R */
            r[0] = cp * cr + spst * sr; r[1] = ct * sr; r[2] = cpst * sr - sp * cr;
            r[3] = spst * cr - cp * sr; r[4] = ct * cr; r[5] = sp * sr + cpst * cr;
            r[6] = sp * ct; r[7] = -st; r[8] = cp * ct;
            for (int j = 0; j < 3; j++) {
                flat[0 * width + j * count + h] = focal[h] * r[j] + pp[0] * r[6 + j];
                flat[1 * width + j * count + h] = focal[h] * r[3 + j] + pp[1] * r[6 + j];
                flat[2 * width + j * count + h] = r[6 + j];
            }
        }
        if (lens) {
            for (int64_t h = 0; h < count; h++) division_gradient(s, w, b, h, count);
        } else {  /* the image's hypotheses share the sums' grids */
            uint32_t largest[3] = {0, 0, 0};
            grad_terms(&w->pass, n_seg, count, s->vertical, lines, lines + n_seg * 3, s->weight + b * n_seg, NULL,
                       flat, s->coef, s->background, s->floor_value, go, s->v_atan, s->v_exp, s->v_ln, largest, NULL);
            grad_sums(&w->pass, n_seg, count, largest, grad);
        }
        if (prior != NULL) {
            for (int64_t h = 0; h < count; h++) logr[h] = focal[h] / prior[2 * b + 1];
            s->v_ln((int)count, logr, logr);
        }
        const float step_bias = s->steps[2 * step], step_lr = s->steps[2 * step + 1];
        for (int64_t h = 0; h < count; h++) {
            const float cp = cosv[3 * h], sp = sinv[3 * h];
            const float *r = rot + 9 * h;
            float v[9], g[9];  /* V = K R and d obj / d V, [coordinate][VP] */
            for (int c = 0; c < 3; c++)
                for (int j = 0; j < 3; j++) {
                    v[3 * c + j] = flat[c * width + j * count + h];
                    g[3 * c + j] = (float)grad[c * width + j * count + h];
                }
            float row0 = g[0] * r[0] + g[1] * r[1];
            row0 = row0 + g[2] * r[2];
            float row1 = g[3] * r[3] + g[4] * r[4];
            row1 = row1 + g[5] * r[5];
            float grad_f = row0 + row1;
            if (prior != NULL) {
                float offset = logr[h] - s->prior_centre;
                if (s->prior_flat != 0.0f) {
                    float excess = fabsf(offset) - s->prior_flat;
                    excess = excess < 0.0f ? 0.0f : excess;  /* clamp_min(0); NaN stays NaN */
                    offset = sign_of(offset) * excess;
                }
                const float d_prior = (-prior[2 * b] * offset) / focal[h];
                grad_f = grad_f + go[h] * d_prior;
            }
            float m[9];  /* V.T G */
            for (int i = 0; i < 3; i++)
                for (int k = 0; k < 3; k++) {
                    float x = v[i] * g[k] + v[3 + i] * g[3 + k];
                    m[3 * i + k] = x + v[6 + i] * g[6 + k];
                }
            const float axial0 = m[7] - m[5], axial1 = m[2] - m[6], axial2 = m[3] - m[1];
            const float grad_pitch = cp * axial0 - sp * axial2;
            float grad_roll = r[6] * axial0 + r[7] * axial1;
            grad_roll = grad_roll + r[8] * axial2;
            const float NEG_DEG = -DEG2RAD;
            const float gp[4] = {axial1 * NEG_DEG, grad_pitch * NEG_DEG, grad_roll * NEG_DEG, grad_f * focal[h]};
            float gu[5];  /* the gradient in box units; k's product in double, as torch's float64 column */
            for (int k = 0; k < 4; k++) gu[k] = gp[k] * sp_[k];
            if (lens) gu[4] = (float)(w->grad_k[h] * (double)sp_[4]);
            float *m1h = m1 + P * h, *m2h = m2 + P * h;
            for (int k = 0; k < P; k++) {
                float gk = gu[k];
                if (!(sp_[k] > 0.0f)) gk = 0.0f;                       /* a fixed side */
                if (gk != gk || gk > FLT_MAX || gk < -FLT_MAX) gk = 0.0f; /* nan_to_num(0, 0, 0) */
                gk = gk < -s->grad_bound ? -s->grad_bound : (gk > s->grad_bound ? s->grad_bound : gk);
                m1h[k] = m1h[k] * s->beta1 + gk * s->one_minus_beta1;
                m2h[k] = m2h[k] * s->beta2 + (gk * gk) * s->one_minus_beta2;
            }
        }
        s->v_sqrt((int)(P * count), m2, root);  /* torch's sqrt of float32: MKL's, not always IEEE-rounded */
        for (int64_t h = 0; h < count; h++) {
            float *uh = ub + P * h;
            for (int k = 0; k < P; k++) {
                const float denom = root[P * h + k] / step_bias + s->eps;
                uh[k] = uh[k] - (m1[P * h + k] / denom) * step_lr;
            }
            if (s->periodic_pan) {  /* torch.remainder(u, 1) */
                float mod = fmodf(uh[0], 1.0f);
                uh[0] = (mod != 0.0f && mod < 0.0f) ? mod + 1.0f : mod;
            }
            for (int k = 0; k < P; k++) {  /* clamp_(0, 1); NaN stays NaN */
                const float x = uh[k];
                uh[k] = x < 0.0f ? 0.0f : (x > 1.0f ? 1.0f : x);
            }
        }
    }
}

/* fR's refinement (fr_torch/core/search/refine.py: _refine_slice with the analytic gradient,
 * adam_in_box, Adam, objective_and_grad, camera_vps, chain_to_params, the focal prior of
 * fr_torch/core/likelihood/mixture.py) for `iterations` steps in one call, bit for bit.
 *
 * u (B, H, P) float32: the hypotheses in box units [pan, pitch, roll, log f] (P = 4), or [pan,
 * pitch, roll, log f, k] (P = 5: the division model, with offset), stepped in place.
 * lower, span (B, P): the box (log f); a side with span <= 0 stays fixed.  pp (B, 2) principal
 * points (the distortion centres), grad_out (B,) the loss's weight of each image's objective (-1 /
 * its total length).  prior (B, 2): the focal prior's curvature weight and the image's long side, or
 * NULL without one; prior_centre, prior_flat its centre (log f / long side) and flat half-width.
 * steps (iterations, 2): Adam's sqrt(1 - beta2^t) and lr_t / (1 - beta1^t) of step t, as float32.
 * line_along (B, 2N, 3) the segments' rows (P = 4; not read for P = 5), weight (B, N), coef,
 * background, floor_value as for fr_measure_b_grad.
 *
 * The division model (SegmentGeometry of fr_torch/core/search/lens.py): offset (B, 2N, 2) and rho
 * (B, 2N) as for undistorted_rows; k_slope (B,) the prior on k's -gamma W (d log p(k) / dk =
 * k_slope k), or NULL without it.  Each hypothesis is scored on its own undistorted segments, so
 * hypotheses are independent: a work item is any run of an image's hypotheses.  Without it the
 * image's hypotheses share the gradient's exact sums: a work item is a whole image.
 *
 * Work items [first, last): item = b * tiles + tile index, hypotheses [index * tile, + tile) of
 * image b (tiles = 1 and tile = H without the division model); work: fr_refine_work_floats(n_seg,
 * tile, P) floats. */
void fr_measure_b_refine(int64_t first, int64_t last, int64_t tiles, int64_t tile, int64_t n_seg, int64_t hyp,
                         int64_t vertical, int64_t iterations,
                         const float *line_along, const float *weight, const float *coef,
                         float background, float floor_value, const float *grad_out,
                         const float *pp, const float *lower, const float *span, const float *prior,
                         float prior_centre, float prior_flat, const float *steps,
                         float beta1, float one_minus_beta1, float beta2, float one_minus_beta2, float eps,
                         float grad_bound, int64_t periodic_pan,
                         const float *offset, const float *rho, const float *k_slope,
                         vml_fn v_atan, vml_fn v_exp, vml_fn v_ln, vml_fn v_sin, vml_fn v_cos, vml_fn v_sqrt,
                         float *work, float *u) {
    const int64_t params = offset != NULL ? 5 : 4;
    const refine_setup s = {n_seg, hyp, vertical, iterations, params, line_along, weight, coef, background,
                            floor_value, grad_out, pp, lower, span, prior, prior_centre, prior_flat, steps, beta1,
                            one_minus_beta1, beta2, one_minus_beta2, eps, grad_bound, periodic_pan, offset, rho,
                            k_slope, v_atan, v_exp, v_ln, v_sin, v_cos, v_sqrt};
    refine_work w;
    refine_work_carve(&w, work, n_seg, tile, params);
    for (int64_t item = first; item < last; item++) {
        const int64_t b = item / tiles, h0 = (item % tiles) * tile;
        const int64_t count = hyp - h0 < tile ? hyp - h0 : tile;
        if (count > 0) refine_hypotheses(&s, &w, b, count, u + (b * hyp + h0) * params);
    }
}
