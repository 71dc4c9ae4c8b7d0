/* Fused measure-b scoring (fr_measure_b_scores) and the refinement's objective with its gradient
 * (fr_measure_b_grad): fr_torch/core/native.py builds, checks and calls this file.
 *
 * Every value is the torch path's (fr_torch/core/likelihood/objective.py: objective_b_nograd,
 * measure_b_forward / measure_b_backward) bit for bit:
 * the same IEEE float32 operations in the same order (compiled with -ffp-contract=off, no fast
 * math), and atan / exp / log through the same MKL VML routines torch's CPU kernels call (their
 * addresses are passed in by the caller).  Only the sum over segments is done differently: each
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
    const int64_t width = 3 * hyp;
    const int64_t rows = CALL / width > 1 ? CALL / width : 1;  /* segments per MKL call */
    const int64_t cells = rows * width;
    float *work = malloc(sizeof(float) * (size_t)(4 * cells + 4 * width + 2 * rows * hyp + 3 * n_seg * width + 1));
    double *acc = malloc(sizeof(double) * (size_t)(hyp + 1));
    if (work == NULL || acc == NULL) { free(work); free(acc); return 1; }
    float *s = work, *t = s + cells, *x = t + cells, *e = x + cells, *a = e + cells, *d = a + width;
    float *gs = d + width, *gt = gs + width;  /* a segment's d obj / d s and d obj / d t */
    float *p = gt + width, *g = p + rows * hyp, *terms = g + rows * hyp; /* terms: (3, N, 3H) */
    for (int k = 0; k < 3; k++)
        for (int64_t h = 0; h < hyp; h++) { a[k * hyp + h] = coef[2 * k]; d[k * hyp + h] = coef[2 * k + 1]; }
    int horizontal[2], q = 0;
    for (int k = 0; k < 3; k++) if (k != vertical) horizontal[q++] = k;
    for (int64_t b = first; b < last; b++) {
        const float *fb = flat + b * 3 * width;
        const float *lines = line_along + b * 2 * n_seg * 3, *alongs = lines + n_seg * 3;
        const float *go = grad_out + b * hyp;
        uint32_t largest[3] = {0, 0, 0};  /* magnitude_bits of each coordinate's largest |term| */
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
                const float w = weight[b * n_seg + i0 + r];
                for (int64_t h = 0; h < hyp; h++) {
                    float sum = er[horizontal[0] * hyp + h] + er[horizontal[1] * hyp + h];
                    sum = sum + er[vertical * hyp + h];
                    sum = sum + background;
                    p[r * hyp + h] = sum;
                    g[r * hyp + h] = (w / sum) * go[h];
                }
            }
            v_ln((int)(count * hyp), p, p);  /* p is log p from here on */
            for (int64_t r = 0; r < count; r++) {
                const float f = factor[b * n_seg + i0 + r];
                for (int64_t h = 0; h < hyp; h++) acc[h] += (double)round_even(p[r * hyp + h] * f);
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
            }
        }
        for (int64_t h = 0; h < hyp; h++) objective[b * hyp + h] = acc[h] / scale[b];
        for (int c = 0; c < 3; c++) {
            union { uint32_t u; float f; } top = {largest[c]};
            const double grid = fixed_point_scale(top.f);  /* NaN when a term is NaN, as torch's amax */
            const float grid32 = (float)grid;
            double *out = grad + (b * 3 + c) * width;
            for (int64_t j = 0; j < width; j++) out[j] = 0.0;
            for (int64_t i = 0; i < n_seg; i++) {
                const float *row = terms + (c * n_seg + i) * width;
                for (int64_t j = 0; j < width; j++) out[j] += (double)round_even(row[j] * grid32);
            }
            for (int64_t j = 0; j < width; j++) out[j] = out[j] / grid;
        }
    }
    free(work);
    free(acc);
    return 0;
}
