/* Fused measure-b scoring (fr_measure_b_scores), the refinement's objective with its gradient
 * (fr_measure_b_grad) and the refinement loop, with or without the division model's k
 * (fr_measure_b_refine): fr_torch/core/likelihood/native.py builds, checks and calls this file.
 *
 * Every value is the torch path's (fr_torch/core/likelihood/objective.py: objective_b_nograd,
 * measure_b_forward / measure_b_backward; fr_torch/core/search/refine.py and lens.py for the loop)
 * bit for bit:
 * the same IEEE float32 operations in the same order (compiled with -ffp-contract=off, no fast
 * math), and atan / exp / log / sin / cos as fr_torch/core/exact_math.py writes them (the same operations on
 * the same constants, below; no maths library), sqrt as the CPU's correctly rounded one.  Only the sum
 * over segments is done differently: each
 * term is rounded to the image's fixed-point grid (fr_torch/core/exact.py, exact_sum) and the
 * integers are added in double, where every order gives the same sum.  The per-segment deviations
 * are never stored: a tile of hypotheses is scored a few segments at a time in small buffers.
 * `#pragma GCC ivdep` marks loops that write only arrays they do not read: GCC's run-time checks for
 * their many input streams would exceed its limit and leave them unvectorised (the values are the
 * same either way; other compilers ignore the pragma).
 */
#include <float.h>
#include <math.h>
#include <stdint.h>
#include <string.h>


#define TILE 256 /* at most this many hypotheses per tile: buffers of a few KB, in L1 */

/* |s / t| with NaN -> 0 and +inf -> FLT_MAX (torch's div_, abs_, nan_to_num_(nan=0)) */
/* round half to even (torch.round, nearbyint in the default rounding mode) without a libm call:
 * below 2^23 adding and subtracting 2^23 rounds to an integer; from 2^23 on a float is one */
static inline float round_even(float x) {
    const float a = fabsf(x);
    const float rounded = copysignf((a + 0x1p23f) - 0x1p23f, x);
    return a < 0x1p23f ? rounded : x;  /* both sides computed: the loops vectorise */
}

/* ---- Elementary functions: fr_torch/core/exact_math.py's float32 exp, log, atan and (through float64)
 * sin and cos, operation for operation, on the same constants (hexadecimal, so that both read the same
 * bits).  Each is applied to an array by the array_* loops, which GCC vectorises. */

static inline uint32_t float_bits(float x) { uint32_t u; memcpy(&u, &x, 4); return u; }
static inline float bits_float(uint32_t u) { float x; memcpy(&x, &u, 4); return x; }

static const float EXP_32[8] = {0x1p+0f, 0x1p+0f, 0x1p-1f, 0x1.555556p-3f, 0x1.555556p-5f, 0x1.111112p-7f,
                                0x1.6c16c2p-10f, 0x1.a01a02p-13f};
static const float LOG_32[4] = {0x1.555556p-1f, 0x1.99999ap-2f, 0x1.24924ap-2f, 0x1.c71c72p-3f};
static const float ATAN_32[5] = {-0x1.555554p-2f, 0x1.99973ep-3f, -0x1.2421a8p-3f, 0x1.b82b1cp-4f, -0x1.089378p-4f};
static const double SIN_64[8] = {-0x1.5555555555555p-3, 0x1.1111111111111p-7, -0x1.a01a01a01a01ap-13,
                                 0x1.71de3a556c734p-19, -0x1.ae64567f544e4p-26, 0x1.6124613a86d09p-33,
                                 -0x1.ae7f3e733b81fp-41, 0x1.952c77030ad4ap-49};
static const double COS_64[8] = {0x1.5555555555555p-5, -0x1.6c16c16c16c17p-10, 0x1.a01a01a01a01ap-16,
                                 -0x1.27e4fb7789f5cp-22, 0x1.1eed8eff8d898p-29, -0x1.93974a8c07c9dp-37,
                                 0x1.ae7f3e733b81fp-45, -0x1.6827863b97d97p-53};

#define HORNER(acc, x, c, n) do { acc = (c)[(n) - 1]; for (int q_ = (n) - 2; q_ >= 0; q_--) acc = acc * (x) + (c)[q_]; } while (0)

static inline float exp32(float x) {
    float n = round_even(x * 0x1.715476p+0f);
    n = n < -126.0f ? -126.0f : n;
    n = n > 127.0f ? 127.0f : n;
    const float r = (x - n * 0x1.62e4p-1f) - n * 0x1.7f7d1cp-20f;
    float p;
    HORNER(p, r, EXP_32, 8);
    const int32_t e = n == n ? (int32_t)n : 0;  /* NaN: p is NaN already */
    float y = p * bits_float((uint32_t)(e + 127) << 23);
    y = x > 0x1.62e43p+6f ? INFINITY : y;
    return x < -0x1.5d589ep+6f ? 0.0f : y;
}

static inline float log32(float x) {
    const int subnormal = x < 0x1p-126f;
    const uint32_t word = float_bits(subnormal ? x * 0x1p23f : x);
    int32_t e = (int32_t)(word >> 23) - 127 - (subnormal ? 23 : 0);
    float m = bits_float((word & 0x7fffffu) | 0x3f800000u);  /* [1, 2) */
    const int big = m > 0x1.6a09e6p+0f;
    m = big ? m * 0.5f : m;
    e = big ? e + 1 : e;
    const float f = m - 1.0f;
    const float s = f / (f + 2.0f);
    const float z = s * s;
    float h;
    HORNER(h, z, LOG_32, 4);
    const float log_m = s * 2.0f + s * (z * h);
    const float ef = (float)e;
    float y = ef * 0x1.62e4p-1f + (ef * 0x1.7f7d1cp-20f + log_m);
    y = x == 0.0f ? -INFINITY : y;
    y = x == INFINITY ? INFINITY : y;
    return (x < 0.0f || x != x) ? NAN : y;
}

static inline float atan32(float x) {
    const float a = fabsf(x);
    const int middle = a > 0x1.a8279ap-2f, far = a > 0x1.3504f4p+1f;  /* tan(pi/8), tan(3pi/8) */
    float num = middle ? a - 1.0f : a, den = middle ? a + 1.0f : 1.0f;
    num = far ? -1.0f : num;
    den = far ? a : den;
    const float u = num / den;  /* |u| <= tan(pi/8) */
    const float v = fabsf(u) < 0x1p-30f ? 0.0f : u;  /* atan(u) = u there, and no subnormal square (slow) */
    const float z = v * v;
    float h;
    HORNER(h, z, ATAN_32, 5);
    float r = u + u * (z * h);
    r = middle ? r + 0x1.921fb6p-1f : r;
    r = far ? r + 0x1.921fb6p-1f : r;  /* pi/2 - atan(1/a) = pi/4 + pi/4 + atan(-1/a) */
    return copysignf(r, x);
}

/* sin and cos of float64 radians: exact_math's _sin_cos64 */
static inline void sin_cos64(double x, double *sin_out, double *cos_out) {
    if (fabs(x) > 0x1p20) {  /* torch.remainder(x, 2 pi) */
        const double period = 2.0 * 0x1.921fb54442d18p+1;
        double mod = fmod(x, period);
        x = (mod != 0.0 && mod < 0.0) ? mod + period : mod;
    }
    const double k = nearbyint(x * 0x1.45f306dc9c883p-1);
    const double r = ((x - k * 0x1.921fb544p+0) - k * 0x1.0b4611a6p-34) - k * 0x1.3198a2e037073p-69;
    const double z = r * r;
    double hs, hc;
    HORNER(hs, z, SIN_64, 8);
    HORNER(hc, z, COS_64, 8);
    const double sin_r = r + r * (z * hs), cos_r = 1.0 + z * (-0.5 + z * hc);
    int64_t quadrant = k == k && fabs(k) < 0x1p62 ? (int64_t)k % 4 : 0;
    quadrant = quadrant < 0 ? quadrant + 4 : quadrant;
    const int swap = quadrant == 1 || quadrant == 3;
    double s = swap ? cos_r : sin_r, c = swap ? sin_r : cos_r;
    s = quadrant >= 2 ? -s : s;
    c = (quadrant == 1 || quadrant == 2) ? -c : c;
    const int finite = isfinite(x);
    *sin_out = finite ? s : NAN;
    *cos_out = finite ? c : NAN;
}

/* sin and cos of float32 radians, each through sin_cos64 and rounded once */
static inline void sin_cos32(float angle, float *sin_out, float *cos_out) {
    double s, c;
    sin_cos64((double)angle, &s, &c);
    *sin_out = (float)s;
    *cos_out = (float)c;
}

static const double EXP_64[14] = {0x1.0000000000000p+0, 0x1.0000000000000p+0, 0x1.0000000000000p-1, 0x1.5555555555555p-3,
                                  0x1.5555555555555p-5, 0x1.1111111111111p-7, 0x1.6c16c16c16c17p-10, 0x1.a01a01a01a01ap-13,
                                  0x1.a01a01a01a01ap-16, 0x1.71de3a556c734p-19, 0x1.27e4fb7789f5cp-22, 0x1.ae64567f544e4p-26,
                                  0x1.1eed8eff8d898p-29, 0x1.6124613a86d09p-33};
static const double LOG_64[10] = {0x1.5555555555555p-1, 0x1.999999999999ap-2, 0x1.2492492492492p-2, 0x1.c71c71c71c71cp-3,
                                  0x1.745d1745d1746p-3, 0x1.3b13b13b13b14p-3, 0x1.1111111111111p-3, 0x1.e1e1e1e1e1e1ep-4,
                                  0x1.af286bca1af28p-4, 0x1.8618618618618p-4};
static const double ATAN_64[8] = {-0x1.5555555555555p-2, 0x1.999999999999ap-3, -0x1.2492492492492p-3, 0x1.c71c71c71c71cp-4,
                                  -0x1.745d1745d1746p-4, 0x1.3b13b13b13b14p-4, -0x1.1111111111111p-4, 0x1.e1e1e1e1e1e1ep-5};
static const double ATAN_EIGHTHS_64[9] = {0x0.0p+0, 0x1.fd5ba9aac2f6ep-4, 0x1.f5b75f92c80ddp-3, 0x1.6f61941e4def1p-2,
                                          0x1.dac670561bb4fp-2, 0x1.1e00babdefeb4p-1, 0x1.4978fa3269ee1p-1,
                                          0x1.700a7c5784634p-1, 0x1.921fb54442d18p-1};

static inline uint64_t double_bits(double x) { uint64_t u; memcpy(&u, &x, 8); return u; }
static inline double bits_double(uint64_t u) { double x; memcpy(&x, &u, 8); return x; }

/* exp32 and log32 step for step in float64 (exact_math._exp / _log for float64) */
static inline double exp64(double x) {
    double n = nearbyint(x * 0x1.71547652b82fep+0);
    n = n < -1022.0 ? -1022.0 : n;
    n = n > 1023.0 ? 1023.0 : n;
    const double r = (x - n * 0x1.62e42fefa38p-1) - n * 0x1.ef35793c7673p-45;
    double p;
    HORNER(p, r, EXP_64, 14);
    const int64_t e = n == n ? (int64_t)n : 0;
    double y = p * bits_double((uint64_t)(e + 1023) << 52);
    y = x > 0x1.62e42fefa39efp+9 ? INFINITY : y;
    return x < -0x1.6232bdd7abcd2p+9 ? 0.0 : y;
}

static inline double log64(double x) {
    const int subnormal = x < 0x1p-1022;
    const uint64_t word = double_bits(subnormal ? x * 0x1p52 : x);
    int64_t e = (int64_t)(word >> 52) - 1023 - (subnormal ? 52 : 0);
    double m = bits_double((word & 0xfffffffffffffull) | 0x3ff0000000000000ull);
    const int big = m > 0x1.6a09e667f3bcdp+0;
    m = big ? m * 0.5 : m;
    e = big ? e + 1 : e;
    const double f = m - 1.0;
    const double s = f / (f + 2.0);
    const double z = s * s;
    double h;
    HORNER(h, z, LOG_64, 10);
    const double log_m = s * 2.0 + s * (z * h);
    const double ef = (double)e;
    double y = ef * 0x1.62e42fefa38p-1 + (ef * 0x1.ef35793c7673p-45 + log_m);
    y = x == 0.0 ? -INFINITY : y;
    y = x == INFINITY ? INFINITY : y;
    return (x < 0.0 || x != x) ? NAN : y;
}

static inline double atan64(double x) {
    const double a = fabs(x);
    const int inverted = a > 1.0;
    const double t = inverted ? 1.0 / a : a;
    const double j = nearbyint(t * 8.0);
    const double c = j * 0.125;
    const double u = (t - c) / (t * c + 1.0);  /* |u| <= 1/16 */
    const double z = u * u;
    double h;
    HORNER(h, z, ATAN_64, 8);
    double r = u + u * (z * h);
    r = ATAN_EIGHTHS_64[j == j ? (int64_t)j : 0] + r;
    r = inverted ? 0x1.921fb54442d18p+0 - r : r;
    return copysign(r, x);
}

/* exact_math's float64 functions over an array: op 0 atan, 1 exp, 2 log, 3 sqrt (correctly rounded),
 * 4 sin and cos (r: n sines then n cosines), 5 tan (sin / cos). */
void fr_elementary_f64(int64_t op, int64_t n, const double *a, double *r) {
    double s, c;
    if (op == 0) for (int64_t i = 0; i < n; i++) r[i] = atan64(a[i]);
    else if (op == 1) for (int64_t i = 0; i < n; i++) r[i] = exp64(a[i]);
    else if (op == 2) for (int64_t i = 0; i < n; i++) r[i] = log64(a[i]);
    else if (op == 3) for (int64_t i = 0; i < n; i++) r[i] = sqrt(a[i]);
    else if (op == 4) for (int64_t i = 0; i < n; i++) sin_cos64(a[i], r + i, r + n + i);
    else for (int64_t i = 0; i < n; i++) { sin_cos64(a[i], &s, &c); r[i] = s / c; }
}

/* FR_WIDE (set by native.py on a CPU with AVX-512): these loops in 512-bit vectors, about a third faster
 * than in 256-bit ones; the rest of the file stays at the base flags (AVX-512 made the refinement's short
 * loops slower).  The same bits either way. */
#if defined(FR_WIDE) && FR_WIDE
#define WIDE __attribute__((target("avx512f,avx512dq,avx512vl,prefer-vector-width=512")))
#else
#define WIDE
#endif

WIDE static void array_atan(int64_t n, const float *a, float *r) {
    for (int64_t i = 0; i < n; i++) r[i] = atan32(a[i]);
}

WIDE static void array_exp(int64_t n, const float *a, float *r) {
    for (int64_t i = 0; i < n; i++) r[i] = exp32(a[i]);
}

WIDE static void array_ln(int64_t n, const float *a, float *r) {
    for (int64_t i = 0; i < n; i++) r[i] = log32(a[i]);
}

static void array_sqrt(int64_t n, const float *a, float *r) {
    for (int64_t i = 0; i < n; i++) r[i] = sqrtf(a[i]);
}

/* fr_torch/core/exact_math.py's float32 functions over an array (what it calls for CPU tensors once
 * the kernels' check passed): op 0 atan, 1 exp, 2 log, 3 sqrt, 4 sin and cos (r: n sines then n
 * cosines). */
void fr_elementary_f32(int64_t op, int64_t n, const float *a, float *r) {
    if (op == 0) array_atan(n, a, r);
    else if (op == 1) array_exp(n, a, r);
    else if (op == 2) array_ln(n, a, r);
    else if (op == 3) array_sqrt(n, a, r);
    else for (int64_t i = 0; i < n; i++) sin_cos32(a[i], r + i, r + n + i);
}

static inline float ratio(float s, float t) {
    const float r = fabsf(s / t);
    const float finite = r > FLT_MAX ? FLT_MAX : r;
    return r != r ? 0.0f : finite;
}

/* Elements per pass of an elementary function (array_atan, array_exp, array_ln): rows of several
 * segments go through each loop together. */
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
                         double *out) {
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
            array_atan(count * stride, x, x);
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
            array_exp(count * stride, x, x);
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
            array_ln(count * width, p, p);
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
    int64_t rows;               /* segments per pass of an elementary function */
    float *s, *t, *x, *e;       /* (rows, 3H): incidence s, t; atan; exp */
    float *a, *d;               /* (3H): each column's -1/lambda and log(prior/lambda) */
    float *gs, *gt;             /* (3H): a segment's d obj / d s and d obj / d t */
    float *grid;                /* (3H): each column's fixed-point grid (exact_columns) */
    float *p, *g;               /* (rows, H): p_i then log p_i; w_i / p_i * grad_out */
    float *terms;               /* (3, N, 3H): each coordinate's gradient terms */
    double *acc;                /* (H) the objective's exact sum; NULL: the gradient alone */
} grad_work;

static int64_t grad_rows(int64_t hyp) { return CALL / (3 * hyp) > 1 ? CALL / (3 * hyp) : 1; }

static size_t grad_floats(int64_t n_seg, int64_t hyp) {
    const int64_t width = 3 * hyp, cells = grad_rows(hyp) * width;
    return (size_t)(4 * cells + 5 * width + 2 * grad_rows(hyp) * hyp + 3 * n_seg * width + 1);
}

static void grad_work_carve(grad_work *w, float *block, double *acc, int64_t hyp) {
    const int64_t width = 3 * hyp;
    w->rows = grad_rows(hyp);
    const int64_t cells = w->rows * width;
    w->s = block; w->t = w->s + cells; w->x = w->t + cells; w->e = w->x + cells;
    w->a = w->e + cells; w->d = w->a + width; w->gs = w->d + width; w->gt = w->gs + width;
    w->grid = w->gt + width; w->p = w->grid + width; w->g = w->p + w->rows * hyp; w->terms = w->g + w->rows * hyp;
    w->acc = acc;
}

/* Pass 1 of one image's objective and gradient for its `hyp` hypotheses: measure_b_forward and the
 * terms of measure_b_backward (fr_torch/core/likelihood/objective.py) bit for bit.
 *
 * rows: the segments' N line rows then N along rows (SegmentFeatures.line_along), 3 coefficients
 * each, shared by the hypotheses ((2N, 3): coefficient c of row i at rows[3 i + c]) or, with `own`,
 * each hypothesis' own ((2N, 3, H): at rows[(3 i + c) H + h]; the division model's virtual images,
 * one per hypothesis).  fb (3, 3H) VP-major vanishing points; weight_b, factor_b (N); go (H) the
 * upstream gradient.  Leaves sum_i round(log p_i * factor_i) in w->acc (H) (nothing without w->acc;
 * factor_b is then not read), every gradient term in w->terms and raises largest (3, 3H) to the
 * magnitude bits of each coordinate's and column's largest |term|.
 *
 * With `own` also line_grad (2N, 3, H): measure_b_backward with the vanishing points, d obj / d rows
 * (each hypothesis' sum over its 3 columns, VP 0 to 2), after that pass has dropped the terms below
 * float's normal range (|common| < FLT_MIN -> 0).  Inlined twice (grad_terms): a constant `own`
 * leaves each loop contiguous or its coefficients loop-invariant. */
static inline __attribute__((always_inline)) void
grad_terms_of(const grad_work *w, int64_t n_seg, int64_t hyp, int64_t vertical, const float *rows, const int own,
              const float *weight_b, const float *factor_b, const float *fb, const float *coef, float background,
              float floor_value, const float *go, uint32_t *largest,
              float *line_grad) {
    const int64_t width = 3 * hyp, chunk = w->rows, stride = own ? hyp : 1;  /* between coefficients */
    const float *along_rows = rows + 3 * n_seg * stride;
    float *s = w->s, *t = w->t, *x = w->x, *e = w->e, *a = w->a, *d = w->d, *gs = w->gs, *gt = w->gt;
    float *p = w->p, *g = w->g, *terms = w->terms;
    double *acc = w->acc;
    for (int k = 0; k < 3; k++)
        for (int64_t h = 0; h < hyp; h++) { a[k * hyp + h] = coef[2 * k]; d[k * hyp + h] = coef[2 * k + 1]; }
    int horizontal[2], q = 0;
    for (int k = 0; k < 3; k++) if (k != vertical) horizontal[q++] = k;
    if (acc != NULL)
        for (int64_t h = 0; h < hyp; h++) acc[h] = 0.0;
    for (int64_t i0 = 0; i0 < n_seg; i0 += chunk) {
        const int64_t count = n_seg - i0 < chunk ? n_seg - i0 : chunk;
        for (int64_t r = 0; r < count; r++) {
            const float *l = rows + 3 * (i0 + r) * stride, *m = along_rows + 3 * (i0 + r) * stride;
            const float *l1 = l + stride, *l2 = l1 + stride, *m1 = m + stride, *m2 = m1 + stride;
            for (int k = 0; k < 3; k++) {
                const float *f0 = fb + k * hyp, *f1 = f0 + width, *f2 = f1 + width;
                float *sr = s + r * width + k * hyp, *tr = t + r * width + k * hyp, *xr = x + r * width + k * hyp;
#pragma GCC ivdep
                for (int64_t h = 0; h < hyp; h++) {
                    const int64_t o = own ? h : 0;
                    float sj = l[o] * f0[h] + l1[o] * f1[h];
                    sj = sj + l2[o] * f2[h];
                    float tj = m[o] * f0[h] + m1[o] * f1[h];
                    tj = tj + m2[o] * f2[h];
                    sr[h] = sj;
                    tr[h] = tj;
                    xr[h] = ratio(sj, tj);
                }
            }
        }
        array_atan(count * width, x, x);
        for (int64_t r = 0; r < count; r++)
            for (int64_t j = 0; j < width; j++) {
                float y = x[r * width + j] * a[j] + d[j];
                e[r * width + j] = y < floor_value ? floor_value : y;
            }
        array_exp(count * width, e, e);
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
            array_ln(count * hyp, p, p);  /* p is log p from here on */
            for (int64_t r = 0; r < count; r++) {
                const float f = factor_b[i0 + r];
                for (int64_t h = 0; h < hyp; h++) acc[h] += (double)round_even(p[r * hyp + h] * f);
            }
        }
        for (int64_t r = 0; r < count; r++) {
            const int64_t i = i0 + r;
            const float *l = rows + 3 * i * stride, *m = along_rows + 3 * i * stride;
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
                if (own && fabsf(common) < FLT_MIN) common = 0.0f;  /* masked_fill_; NaN stays NaN */
                gs[j] = common * tj;
                gt[j] = -(common * sj);
            }
            for (int c = 0; c < 3; c++) {
                const float *lc = l + c * stride, *mc = m + c * stride;
                float *row = terms + (c * n_seg + i) * width;
                uint32_t *top = largest + c * width;
                for (int k = 0; k < 3; k++)
#pragma GCC ivdep
                    for (int64_t h = 0; h < hyp; h++) {
                        const int64_t j = k * hyp + h, o = own ? h : 0;
                        const float term = lc[o] * gs[j] + mc[o] * gt[j];
                        row[j] = term;
                        const uint32_t bits = magnitude_bits(term);
                        top[j] = bits > top[j] ? bits : top[j];
                    }
            }
            if (own)
                for (int c = 0; c < 3; c++) {
                    const float *f0 = fb + c * width, *f1 = f0 + hyp, *f2 = f1 + hyp;
                    float *line_c = line_grad + (3 * i + c) * hyp, *along_c = line_grad + (3 * (n_seg + i) + c) * hyp;
#pragma GCC ivdep
                    for (int64_t h = 0; h < hyp; h++) {
                        float sum = gs[h] * f0[h] + gs[hyp + h] * f1[h];
                        line_c[h] = sum + gs[2 * hyp + h] * f2[h];
                        sum = gt[h] * f0[h] + gt[hyp + h] * f1[h];
                        along_c[h] = sum + gt[2 * hyp + h] * f2[h];
                    }
                }
        }
    }
}

static void grad_terms(const grad_work *w, int64_t n_seg, int64_t hyp, int64_t vertical, const float *rows, int own,
                       const float *weight_b, const float *factor_b, const float *fb, const float *coef,
                       float background, float floor_value, const float *go, uint32_t *largest, float *line_grad) {
    if (own)
        grad_terms_of(w, n_seg, hyp, vertical, rows, 1, weight_b, factor_b, fb, coef, background, floor_value, go,
                      largest, line_grad);
    else
        grad_terms_of(w, n_seg, hyp, vertical, rows, 0, weight_b, factor_b, fb, coef, background, floor_value, go,
                      largest, NULL);
}

/* Column sums of terms (rows, width) into out (width) double, each exact on the grid set by its
 * largest |term| (`largest` (width), magnitude bits): fr_torch/core/exact.py, exact_sum with that
 * bound.  grid (width): scratch. */
static void exact_columns(const float *terms, int64_t rows, int64_t width, const uint32_t *largest, float *grid,
                          double *out) {
    for (int64_t j = 0; j < width; j++) {
        union { uint32_t u; float f; } top = {largest[j]};
        grid[j] = (float)fixed_point_scale(top.f);  /* a power of two (NaN for a NaN term, as torch's amax) */
        out[j] = 0.0;
    }
    for (int64_t i = 0; i < rows; i++) {
        const float *row = terms + i * width;
        for (int64_t j = 0; j < width; j++) out[j] += (double)round_even(row[j] * grid[j]);
    }
    for (int64_t j = 0; j < width; j++) out[j] = out[j] / (double)grid[j];
}

/* Pass 2: d objective / d fb (3, 3H) double into out, each coordinate's sum over segments exact on
 * the grid set by its largest |term| (largest (3, 3H) from grad_terms, overwritten): over every
 * hypothesis of the image, or with `own` over each hypothesis' 3 columns (one virtual image each). */
static void grad_sums(const grad_work *w, int64_t n_seg, int64_t hyp, int own, uint32_t *largest, double *out) {
    const int64_t width = 3 * hyp;
    for (int c = 0; c < 3; c++) {
        uint32_t *top = largest + c * width;
        if (own)
            for (int64_t h = 0; h < hyp; h++) {
                uint32_t most = top[h] > top[hyp + h] ? top[h] : top[hyp + h];
                most = most > top[2 * hyp + h] ? most : top[2 * hyp + h];
                top[h] = top[hyp + h] = top[2 * hyp + h] = most;
            }
        else {
            uint32_t most = 0;
            for (int64_t j = 0; j < width; j++) most = top[j] > most ? top[j] : most;
            for (int64_t j = 0; j < width; j++) top[j] = most;
        }
        exact_columns(w->terms + c * n_seg * width, n_seg, width, top, w->grid, out + c * width);
    }
}

/* The refinement's objective and its gradient with respect to the vanishing points, per image:
 * measure_b_forward followed by measure_b_backward (fr_torch/core/likelihood/objective.py) bit for bit.
 *
 * Images [first, last) of the batch; hyp hypotheses each (columns k * hyp + h of flat (B, 3, 3H));
 * weight (B, N), factor (B, N) and scale (B,) as for fr_measure_b_scores; grad_out (B, H) float32.
 * objective (B, H) double; grad (B, 3, 3H) double: d objective / d flat, each coordinate's sum over
 * segments exact on the grid set by the image's largest |term| of that coordinate.  Returns 1 when
 * out of memory. */
int fr_measure_b_grad(int64_t first, int64_t last, int64_t n_seg, int64_t hyp, int64_t vertical,
                      const float *line_along, const float *weight, const float *factor, const double *scale,
                      const float *flat, const float *coef, float background, float floor_value,
                      const float *grad_out,
                      double *objective, double *grad) {
    float *block = malloc(sizeof(float) * grad_floats(n_seg, hyp));
    double *acc = malloc(sizeof(double) * (size_t)(hyp + 1));
    uint32_t *largest = malloc(sizeof(uint32_t) * (size_t)(9 * hyp));
    if (block == NULL || acc == NULL || largest == NULL) { free(block); free(acc); free(largest); return 1; }
    grad_work w;
    grad_work_carve(&w, block, acc, hyp);
    for (int64_t b = first; b < last; b++) {
        for (int64_t j = 0; j < 9 * hyp; j++) largest[j] = 0;
        grad_terms(&w, n_seg, hyp, vertical, line_along + b * 2 * n_seg * 3, 0, weight + b * n_seg,
                   factor + b * n_seg, flat + b * 9 * hyp, coef, background, floor_value, grad_out + b * hyp,
                   largest, NULL);
        for (int64_t h = 0; h < hyp; h++) objective[b * hyp + h] = acc[h] / scale[b];
        grad_sums(&w, n_seg, hyp, 0, largest, grad + b * 9 * hyp);
    }
    free(block);
    free(acc);
    free(largest);
    return 0;
}

/* ---- The refinement loop (fr_measure_b_refine) ------------------------------------------------ */


#define DEG2RAD 0.017453292519943295f   /* (float)(pi / 180): torch.deg2rad of a float tensor */

/* The division model's segments of one image at each of `hyp` values of k: SegmentGeometry.features(k,
 * derivative=True) (fr_torch/core/search/lens.py), bit for bit.
 *
 * k (H); centre (2) the distortion centre, pixels; offset (2N, 2) the endpoints' offsets from it (the
 * N first endpoints, then the N second ones), rho (2N) their r^2 in units of the normalising
 * radius^2 (SegmentGeometry.offsets).  rows (2N, 3, H): the undistorted segments' line then along
 * rows (SegmentFeatures.line_along) under each k, coefficient c of row i for k[h] at
 * rows[(3 i + c) H + h]; d_rows (2N, 3, H) their derivatives with respect to k; length: (N, H) scratch. */
static void undistorted_rows(int64_t n_seg, int64_t hyp, const float *k, const float *centre, const float *offset,
                             const float *rho, float *length, float *rows, float *d_rows) {
    const float min_length = (float)1e-12;  /* clamp_min(1e-12) of a float tensor */
    for (int64_t i = 0; i < n_seg; i++) {
        const float *oa = offset + 2 * i, *ob = offset + 2 * (n_seg + i);
        const float ra = rho[i], rb = rho[n_seg + i];
#pragma GCC ivdep
        for (int64_t h = 0; h < hyp; h++) {  /* undistorted = centre + factor * offset */
            const float factor_a = 1.0f / (1.0f + k[h] * ra), factor_b = 1.0f / (1.0f + k[h] * rb);
            const float dx = ob[0] * factor_b - oa[0] * factor_a, dy = ob[1] * factor_b - oa[1] * factor_a;
            length[i * hyp + h] = dx * dx + dy * dy;
        }
    }
    array_sqrt(n_seg * hyp, length, length);
    for (int64_t i = 0; i < n_seg; i++) {
        const int64_t a = i, b = n_seg + i;
        const float *oa = offset + 2 * a, *ob = offset + 2 * b;
        const float ra = rho[a], rb = rho[b];
        float *line = rows + 3 * a * hyp, *along = rows + 3 * b * hyp;
        float *d_line = d_rows + 3 * a * hyp, *d_along = d_rows + 3 * b * hyp;
#pragma GCC ivdep
        for (int64_t h = 0; h < hyp; h++) {
            const float factor_a = 1.0f / (1.0f + k[h] * ra), factor_b = 1.0f / (1.0f + k[h] * rb);
            const float qa_x = oa[0] * factor_a, qa_y = oa[1] * factor_a;
            const float qb_x = ob[0] * factor_b, qb_y = ob[1] * factor_b;
            const float delta_x = qb_x - qa_x, delta_y = qb_y - qa_y;
            const float clamped = length[i * hyp + h] < min_length ? min_length : length[i * hyp + h];
            const float inv_length = 1.0f / clamped;  /* NaN stays NaN */
            const float dx = delta_x * inv_length, dy = delta_y * inv_length;
            const float mx = centre[0] + (qa_x + qb_x) * 0.5f, my = centre[1] + (qa_y + qb_y) * 0.5f;
            line[h] = -dy; line[hyp + h] = dx; line[2 * hyp + h] = dy * mx - dx * my;
            along[h] = dx; along[hyp + h] = dy; along[2 * hyp + h] = -(dx * mx + dy * my);
            const float ca = (-ra * factor_a) * factor_a, cb = (-rb * factor_b) * factor_b;  /* dq / dk = offset * ca */
            const float dqa_x = oa[0] * ca, dqa_y = oa[1] * ca, dqb_x = ob[0] * cb, dqb_y = ob[1] * cb;
            const float dd_x = dqb_x - dqa_x, dd_y = dqb_y - dqa_y;
            const float along_dd = dx * dd_x + dy * dd_y;
            const float ddx = (dd_x - dx * along_dd) * inv_length, ddy = (dd_y - dy * along_dd) * inv_length;
            const float dmx = (dqa_x + dqb_x) * 0.5f, dmy = (dqa_y + dqb_y) * 0.5f;
            float sum = ddy * mx + dy * dmx;
            sum = sum - ddx * my;
            d_line[h] = -ddy; d_line[hyp + h] = ddx; d_line[2 * hyp + h] = sum - dx * dmy;
            sum = ddx * mx + dx * dmx;
            sum = sum + ddy * my;
            d_along[h] = ddx; d_along[hyp + h] = ddy; d_along[2 * hyp + h] = -(sum + dy * dmy);
        }
    }
}

/* What every work item of fr_measure_b_refine shares: its arguments. */
typedef struct {
    int64_t n_seg, vertical, iterations, params;
    const float *line_along, *weight, *coef;
    float background, floor_value;
    const float *grad_out, *pp, *lower, *span, *prior;
    float prior_centre, prior_flat;
    const float *steps;
    float beta1, one_minus_beta1, beta2, one_minus_beta2, eps, grad_bound;
    int64_t periodic_pan;
    const float *offset, *rho, *k_slope;  /* the division model; offset NULL without it */
} refine_setup;

/* fr_measure_b_refine's workspace for an image of H hypotheses (refine_work_carve). */
typedef struct {
    double *grad, *grad_k;                /* (3, 3H) d obj / d V, VP-major; (H) d obj / dk */
    uint32_t *largest;                    /* (3, 3H) the gradient terms' largest magnitudes */
    grad_work pass;                       /* the gradient pass */
    float *rad, *cosv, *sinv;             /* (H, 3) */
    float *focal, *logf, *logr, *k, *go;  /* (H) */
    float *flat, *rot;                    /* (3, 3H) VP-major; (H, 9) */
    float *m1, *m2, *root;                /* (H, P) Adam's moments, sqrt of the second */
    float *rows, *d_rows, *line_grad;     /* (2N, 3, H) each hypothesis' segments, d / dk, d obj / d rows */
    float *k_terms, *length;              /* (2N, H); (N, H) */
} refine_work;

/* Carves `block` (may be NULL: sizes only) into w for images of `hyp` hypotheses with `params`
 * parameters (5: the division model's buffers too); returns the floats used (doubles first, two
 * floats each). */
static int64_t refine_work_carve(refine_work *w, float *block, int64_t n_seg, int64_t hyp, int64_t params) {
    const int64_t lens = params == 5 ? 1 : 0;
    int64_t at = 0;
#define TAKE_AS(type, ptr, n) do { (ptr) = block != NULL ? (type *)(block + at) : NULL; at += (n); } while (0)
    TAKE_AS(double, w->grad, 2 * 9 * hyp);
    TAKE_AS(double, w->grad_k, 2 * hyp);
    TAKE_AS(uint32_t, w->largest, 9 * hyp);
    if (block != NULL) grad_work_carve(&w->pass, block + at, NULL, hyp);
    at += (int64_t)grad_floats(n_seg, hyp);
    TAKE_AS(float, w->rad, 3 * hyp); TAKE_AS(float, w->cosv, 3 * hyp); TAKE_AS(float, w->sinv, 3 * hyp);
    TAKE_AS(float, w->focal, hyp); TAKE_AS(float, w->logf, hyp); TAKE_AS(float, w->logr, hyp);
    TAKE_AS(float, w->k, hyp); TAKE_AS(float, w->go, hyp);
    TAKE_AS(float, w->flat, 9 * hyp); TAKE_AS(float, w->rot, 9 * hyp);
    TAKE_AS(float, w->m1, params * hyp); TAKE_AS(float, w->m2, params * hyp); TAKE_AS(float, w->root, params * hyp);
    TAKE_AS(float, w->rows, lens * 6 * n_seg * hyp); TAKE_AS(float, w->d_rows, lens * 6 * n_seg * hyp);
    TAKE_AS(float, w->line_grad, lens * 6 * n_seg * hyp);
    TAKE_AS(float, w->k_terms, lens * 2 * n_seg * hyp); TAKE_AS(float, w->length, lens * n_seg * hyp);
#undef TAKE_AS
    return at;
}

/* Floats of the workspace fr_measure_b_refine needs per thread for images of `hyp` hypotheses with
 * `params` (4 or 5) parameters. */
int64_t fr_refine_work_floats(int64_t n_seg, int64_t hyp, int64_t params) {
    refine_work w = {0};
    return refine_work_carve(&w, NULL, n_seg, hyp, params);
}

/* d obj / dk of hypotheses [0, count) of image b into w->grad_k (double, as torch's float64 sums),
 * from d obj / d rows (w->line_grad) and d rows / dk (w->d_rows): each hypothesis' exact sum over
 * its 2N rows of their dot products (fr_torch/core/search/refine.py, objective_and_grad with a
 * geometry), plus the prior on k's share. */
static void division_k_gradient(const refine_setup *s, const refine_work *w, int64_t b, int64_t count) {
    uint32_t *top = w->largest;
    for (int64_t h = 0; h < count; h++) top[h] = 0;
    for (int64_t i = 0; i < 2 * s->n_seg; i++) {
        const float *gl = w->line_grad + 3 * i * count, *dl = w->d_rows + 3 * i * count;
        float *terms = w->k_terms + i * count;
#pragma GCC ivdep
        for (int64_t h = 0; h < count; h++) {
            float term = gl[h] * dl[h] + gl[count + h] * dl[count + h];
            term = term + gl[2 * count + h] * dl[2 * count + h];
            terms[h] = term;
            const uint32_t bits = magnitude_bits(term);
            top[h] = bits > top[h] ? bits : top[h];
        }
    }
    exact_columns(w->k_terms, 2 * s->n_seg, count, top, w->pass.grid, w->grad_k);
    if (s->k_slope != NULL)
        for (int64_t h = 0; h < count; h++) {
            const float d_prior = s->k_slope[b] * w->k[h];
            w->grad_k[h] = w->grad_k[h] + (double)(w->go[h] * d_prior);
        }
}

/* Every step of image b's hypotheses ub (count, P), stepped in place (the comment of
 * fr_measure_b_refine). */
static void refine_hypotheses(const refine_setup *s, const refine_work *w, int64_t b, int64_t count, float *ub) {
    const int64_t n_seg = s->n_seg, P = s->params, width = 3 * count;
    const int lens = s->offset != NULL;
    const float *lo = s->lower + P * b, *sp_ = s->span + P * b, *pp = s->pp + 2 * b, *prior = s->prior;
    const float *rows = lens ? w->rows : s->line_along + b * 2 * n_seg * 3;
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
        for (int64_t j = 0; j < 3 * count; j++) sin_cos32(rad[j], sinv + j, cosv + j);
        array_exp(count, logf, focal);
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
        if (lens)  /* each hypothesis' segments undistorted with its k */
            undistorted_rows(n_seg, count, w->k, pp, s->offset + 4 * b * n_seg, s->rho + 2 * b * n_seg,
                             w->length, w->rows, w->d_rows);
        for (int64_t j = 0; j < 9 * count; j++) w->largest[j] = 0;
        grad_terms(&w->pass, n_seg, count, s->vertical, rows, lens, s->weight + b * n_seg, NULL, flat, s->coef,
                   s->background, s->floor_value, go, w->largest, w->line_grad);
        grad_sums(&w->pass, n_seg, count, lens, w->largest, grad);
        if (lens) division_k_gradient(s, w, b, count);
        if (prior != NULL) {
            for (int64_t h = 0; h < count; h++) logr[h] = focal[h] / prior[2 * b + 1];
            array_ln(count, logr, logr);
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
        array_sqrt(P * count, m2, root);
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
 * k_slope k), or NULL without it.  Each hypothesis is scored on its own undistorted segments, its
 * exact sums on its own grids (one virtual image per hypothesis).
 *
 * Images [first, last); work: fr_refine_work_floats(n_seg, hyp, P) floats. */
void fr_measure_b_refine(int64_t first, int64_t last, int64_t n_seg, int64_t hyp, int64_t vertical,
                         int64_t iterations,
                         const float *line_along, const float *weight, const float *coef,
                         float background, float floor_value, const float *grad_out,
                         const float *pp, const float *lower, const float *span, const float *prior,
                         float prior_centre, float prior_flat, const float *steps,
                         float beta1, float one_minus_beta1, float beta2, float one_minus_beta2, float eps,
                         float grad_bound, int64_t periodic_pan,
                         const float *offset, const float *rho, const float *k_slope,
                                                  float *work, float *u) {
    const int64_t params = offset != NULL ? 5 : 4;
    const refine_setup s = {n_seg, vertical, iterations, params, line_along, weight, coef, background, floor_value,
                            grad_out, pp, lower, span, prior, prior_centre, prior_flat, steps, beta1,
                            one_minus_beta1, beta2, one_minus_beta2, eps, grad_bound, periodic_pan, offset, rho,
                            k_slope};
    refine_work w = {0};
    refine_work_carve(&w, work, n_seg, hyp, params);
    for (int64_t b = first; b < last; b++) refine_hypotheses(&s, &w, b, hyp, u + b * hyp * params);
}
