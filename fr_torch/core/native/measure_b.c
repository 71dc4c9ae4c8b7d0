/* Fused measure-b scoring: fr_torch/core/native.py builds, checks and calls this file.
 *
 * Every value is the torch path's (fr_torch/core/likelihood.py, objective_b_nograd) bit for bit:
 * the same IEEE float32 operations in the same order (compiled with -ffp-contract=off, no fast
 * math), and atan / exp / log through the same MKL VML routines torch's CPU kernels call (their
 * addresses are passed in by the caller).  Only the sum over segments is done differently: each
 * term is rounded to the image's fixed-point grid (fr_torch/core/exact.py, exact_sum) and the
 * integers are added in double, where every order gives the same sum.  The per-segment deviations
 * are never stored: a tile of hypotheses is scored one segment at a time in small buffers.
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
    float a = fabsf(x);
    return a < 0x1p23f ? copysignf((a + 0x1p23f) - 0x1p23f, x) : x;
}

static inline float ratio(float s, float t) {
    float r = fabsf(s / t);
    if (r != r) return 0.0f;
    if (r > FLT_MAX) return FLT_MAX;
    return r;
}

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
    float col[3][3][TILE];              /* [VP][coordinate][hypothesis in tile] */
    float hx[2][TILE], vx[TILE], p[TILE];
    double acc[TILE];
    int horizontal[2], k = 0;
    for (int vp = 0; vp < 3; vp++) if (vp != vertical) horizontal[k++] = vp;
    for (int64_t item = first_item; item < last_item; item++) {
        int64_t b = item / tiles_per_image;
        int64_t h0 = (item % tiles_per_image) * tile;
        int64_t width = hyp - h0 < tile ? hyp - h0 : tile;
        int64_t runs = (width + block - 1) / block;   /* vertical VPs in this tile (h0 is a multiple of block) */
        const float *fb = flat + b * 9 * hyp;
        for (int vp = 0; vp < 3; vp++)
            for (int c = 0; c < 3; c++)
                for (int64_t j = 0; j < width; j++) col[vp][c][j] = fb[c * 3 * hyp + vp * hyp + h0 + j];
        for (int64_t j = 0; j < width; j++) acc[j] = 0.0;
        const float *lines = line_along + b * 2 * n_seg * 3;
        const float *alongs = lines + n_seg * 3;
        for (int64_t i = 0; i < n_seg; i++) {
            const float l0 = lines[3 * i], l1 = lines[3 * i + 1], l2 = lines[3 * i + 2];
            const float g0 = alongs[3 * i], g1 = alongs[3 * i + 1], g2 = alongs[3 * i + 2];
            for (int q = 0; q < 2; q++) {
                const float *c0 = col[horizontal[q]][0], *c1 = col[horizontal[q]][1], *c2 = col[horizontal[q]][2];
                for (int64_t j = 0; j < width; j++) {
                    float s = l0 * c0[j] + l1 * c1[j];
                    s = s + l2 * c2[j];
                    float t = g0 * c0[j] + g1 * c1[j];
                    t = t + g2 * c2[j];
                    hx[q][j] = ratio(s, t);
                }
            }
            {
                const float *c0 = col[vertical][0], *c1 = col[vertical][1], *c2 = col[vertical][2];
                for (int64_t r = 0; r < runs; r++) {
                    int64_t j = r * block;
                    float s = l0 * c0[j] + l1 * c1[j];
                    s = s + l2 * c2[j];
                    float t = g0 * c0[j] + g1 * c1[j];
                    t = t + g2 * c2[j];
                    vx[r] = ratio(s, t);
                }
            }
            v_atan((int)width, hx[0], hx[0]);
            v_atan((int)width, hx[1], hx[1]);
            v_atan((int)runs, vx, vx);
            for (int q = 0; q < 2; q++) {
                const float a = coef[2 * horizontal[q]], d = coef[2 * horizontal[q] + 1];
                for (int64_t j = 0; j < width; j++) {
                    float x = hx[q][j] * a + d;
                    hx[q][j] = x < floor_value ? floor_value : x;
                }
            }
            {
                const float a = coef[2 * vertical], d = coef[2 * vertical + 1];
                for (int64_t r = 0; r < runs; r++) {
                    float x = vx[r] * a + d;
                    vx[r] = x < floor_value ? floor_value : x;
                }
            }
            v_exp((int)width, hx[0], hx[0]);
            v_exp((int)width, hx[1], hx[1]);
            v_exp((int)runs, vx, vx);
            for (int64_t j = 0; j < width; j++) {
                float sum = hx[0][j] + hx[1][j];
                sum = sum + vx[j / block];
                p[j] = sum + background;
            }
            v_ln((int)width, p, p);
            const float f = factor[b * n_seg + i];
            for (int64_t j = 0; j < width; j++) acc[j] += (double)round_even(p[j] * f);
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

/* torch.sign of a float: +1, -1 or 0 (0 for +-0 and NaN) */
static inline float sign_of(float x) { return (float)((0.0f < x) - (x < 0.0f)); }

/* The refinement's objective and its gradient with respect to the vanishing points, per image:
 * measure_b_forward followed by measure_b_backward (fr_torch/core/likelihood.py) bit for bit.
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
    const int64_t width = 3 * hyp;
    float *work = malloc(sizeof(float) * (size_t)(6 * width + 2 * hyp + 3 * n_seg * width + 1));
    double *acc = malloc(sizeof(double) * (size_t)(hyp + 1));
    if (work == NULL || acc == NULL) { free(work); free(acc); return 1; }
    float *s = work, *t = s + width, *x = t + width, *e = x + width, *a = e + width, *d = a + width;
    float *p = d + width, *g = p + hyp, *terms = g + hyp; /* terms: (3, N, 3H) */
    for (int k = 0; k < 3; k++)
        for (int64_t h = 0; h < hyp; h++) { a[k * hyp + h] = coef[2 * k]; d[k * hyp + h] = coef[2 * k + 1]; }
    int horizontal[2], q = 0;
    for (int k = 0; k < 3; k++) if (k != vertical) horizontal[q++] = k;
    for (int64_t b = first; b < last; b++) {
        const float *fb = flat + b * 3 * width;
        const float *lines = line_along + b * 2 * n_seg * 3, *alongs = lines + n_seg * 3;
        const float *go = grad_out + b * hyp;
        float largest[3] = {0.0f, 0.0f, 0.0f};
        int nan_seen[3] = {0, 0, 0};
        for (int64_t h = 0; h < hyp; h++) acc[h] = 0.0;
        for (int64_t i = 0; i < n_seg; i++) {
            const float l[3] = {lines[3 * i], lines[3 * i + 1], lines[3 * i + 2]};
            const float m[3] = {alongs[3 * i], alongs[3 * i + 1], alongs[3 * i + 2]};
            for (int64_t j = 0; j < width; j++) {
                float sj = l[0] * fb[j] + l[1] * fb[width + j];
                sj = sj + l[2] * fb[2 * width + j];
                float tj = m[0] * fb[j] + m[1] * fb[width + j];
                tj = tj + m[2] * fb[2 * width + j];
                s[j] = sj;
                t[j] = tj;
                x[j] = ratio(sj, tj);
            }
            v_atan((int)width, x, x);
            for (int64_t j = 0; j < width; j++) {
                float y = x[j] * a[j] + d[j];
                e[j] = y < floor_value ? floor_value : y;
            }
            v_exp((int)width, e, e);
            for (int64_t h = 0; h < hyp; h++) {
                float sum = e[horizontal[0] * hyp + h] + e[horizontal[1] * hyp + h];
                sum = sum + e[vertical * hyp + h];
                p[h] = sum + background;
            }
            const float w = weight[b * n_seg + i];
            for (int64_t h = 0; h < hyp; h++) g[h] = (w / p[h]) * go[h];
            v_ln((int)hyp, p, p);  /* p is log p from here on */
            const float f = factor[b * n_seg + i];
            for (int64_t h = 0; h < hyp; h++) acc[h] += (double)round_even(p[h] * f);
            for (int64_t j = 0; j < width; j++) {
                const float sj = s[j], tj = t[j];
                float r2 = sj * sj + tj * tj;
                r2 = r2 < FLT_MIN ? FLT_MIN : r2;  /* clamp_min_(tiny); NaN stays NaN */
                float common = e[j] * a[j];
                common = common * g[j % hyp];
                common = common * sign_of(sj * tj);
                common = common / r2;
                const float gs = common * tj, gt = -(common * sj);
                for (int c = 0; c < 3; c++) {
                    float term = l[c] * gs + m[c] * gt;
                    terms[(c * n_seg + i) * width + j] = term;
                    float size = fabsf(term);
                    if (size != size) nan_seen[c] = 1;
                    else if (size > largest[c]) largest[c] = size;
                }
            }
        }
        for (int64_t h = 0; h < hyp; h++) objective[b * hyp + h] = acc[h] / scale[b];
        for (int c = 0; c < 3; c++) {
            const double grid = fixed_point_scale(nan_seen[c] ? NAN : largest[c]);
            const float grid32 = (float)grid;
            double *out = grad + (b * 3 + c) * width;
            for (int64_t j = 0; j < width; j++) {
                double total = 0.0;
                for (int64_t i = 0; i < n_seg; i++)
                    total += (double)round_even(terms[(c * n_seg + i) * width + j] * grid32);
                out[j] = total / grid;
            }
        }
    }
    free(work);
    free(acc);
    return 0;
}
