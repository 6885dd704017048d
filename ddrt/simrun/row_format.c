/* telemetry.csv's rows as text: each double as Python's "%.9g", comma-separated, CRLF-ended.
 *
 * The same text as ddrt/simrun/runner.py's format_rows (the reference and the fallback),
 * several times faster; built and loaded by ddrt/simrun/row_native.py. Simulator only.
 *
 * Fast path for a finite nonzero normal double a = |v| whose decimal exponent X
 * (10^X <= a < 10^(X+1)) lies in [-14, 30]: s = a * 10^(8-X) (or a / 10^(X-8)) with 10^k an
 * exactly representable power of ten (k <= 22), so s is the exact product correctly rounded
 * once: |s - a*10^(8-X)| <= ulp(s)/2 <= 2^-24 because s < 2^30. The 9 digits are s rounded
 * to the nearest integer. That equals the correctly rounded decimal unless a half-integer
 * lies within 2^-24 of s; so when s's fraction is within TIE_MARGIN (2^-20, 16 times that
 * error) of 0.5, and for everything outside the fast path (subnormals, |X| out of range, an
 * exponent that does not settle), the value is formatted by snprintf("%.9g"), which glibc
 * rounds correctly (round-half-even on exact ties, like Python). (Rounding is monotone and
 * half-integers below 2^52 are doubles, so s cannot even cross one: a fraction of exactly 0.5
 * is the only case that strictly needs snprintf; the margin is a second line.) NaNs of either sign or
 * payload are "nan" (C would print "-nan"), infinities "inf"/"-inf", zeros "0"/"-0".
 */
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define TIE_MARGIN (1.0 / 1048576.0) /* 2^-20 */
#define MAX_LEN 24                   /* > the longest "%.9g" of a double, 16: -1.23456789e-308 */

static const double POW10[23] = {
    1e0,  1e1,  1e2,  1e3,  1e4,  1e5,  1e6,  1e7,  1e8,  1e9,  1e10, 1e11,
    1e12, 1e13, 1e14, 1e15, 1e16, 1e17, 1e18, 1e19, 1e20, 1e21, 1e22,
};

static const char DIGITS2[201] =
    "00010203040506070809101112131415161718192021222324252627282930313233343536373839"
    "40414243444546474849505152535455565758596061626364656667686970717273747576777879"
    "8081828384858687888990919293949596979899";

static int slow(double v, char *out)
{
    char buf[64];
    int len = snprintf(buf, sizeof buf, "%.9g", v);
    if (len < 0 || len >= MAX_LEN) /* cannot happen for a double; keep the buffer safe */
        len = 0;
    memcpy(out, buf, (size_t)len);
    return len;
}

/* "%.9g" of v into out (at most MAX_LEN bytes, no terminator); returns the length, or -1
 * when v needs snprintf (nothing is written then). */
int g9_fast(double v, char *out)
{
    uint64_t bits;
    memcpy(&bits, &v, sizeof bits);
    int neg = (int)(bits >> 63);
    uint64_t mag = bits & 0x7fffffffffffffffULL;
    char *p = out;
    if (mag >= 0x7ff0000000000000ULL) {
        if (mag > 0x7ff0000000000000ULL) {
            memcpy(p, "nan", 3);
            return 3;
        }
        if (neg)
            *p++ = '-';
        memcpy(p, "inf", 3);
        return neg + 3;
    }
    if (mag == 0) {
        if (neg)
            *p++ = '-';
        *p = '0';
        return neg + 1;
    }
    int bexp = (int)(mag >> 52);
    if (bexp == 0)
        return -1; /* subnormal */
    double a = fabs(v);
    /* floor(log10(2^(bexp-1023))), or one off: the loop below settles it */
    int x = ((bexp - 1023) * 78913) >> 18;
    double s = 0.0;
    int settled = 0;
    for (int iter = 0; iter < 3; iter++) {
        int k = 8 - x;
        if (k > 22 || k < -22)
            return -1;
        s = k >= 0 ? a * POW10[k] : a / POW10[-k];
        if (s >= 1e9)
            x++;
        else if (s < 1e8)
            x--;
        else {
            settled = 1;
            break;
        }
    }
    if (!settled)
        return -1;
    uint32_t n = (uint32_t)s; /* s in [1e8, 1e9): exact truncation */
    double frac = s - (double)n; /* exact */
    if (fabs(frac - 0.5) < TIE_MARGIN)
        return -1;
    if (frac > 0.5)
        n++;
    if (n == 1000000000u) {
        n = 100000000u;
        x++;
    }
    /* the 9 digits */
    char d[10];
    uint32_t hi = n / 10000000u;   /* first two digits, 10..99 */
    uint32_t lo = n % 10000000u;   /* last seven */
    memcpy(d, DIGITS2 + 2 * hi, 2);
    uint32_t l1 = lo / 100000u, l2 = lo % 100000u;  /* 2 + 5 */
    memcpy(d + 2, DIGITS2 + 2 * l1, 2);
    uint32_t l3 = l2 / 1000u, l4 = l2 % 1000u;      /* 2 + 3 */
    memcpy(d + 4, DIGITS2 + 2 * l3, 2);
    uint32_t l5 = l4 / 10u;
    memcpy(d + 6, DIGITS2 + 2 * l5, 2);
    d[8] = (char)('0' + l4 % 10u);
    int nd = 9; /* significant digits once trailing zeros are stripped */
    while (d[nd - 1] == '0')
        nd--;
    if (neg)
        *p++ = '-';
    if (x >= -4 && x < 9) {
        if (x >= 0) {
            memcpy(p, d, (size_t)(x + 1));
            p += x + 1;
            if (nd > x + 1) {
                *p++ = '.';
                memcpy(p, d + x + 1, (size_t)(nd - x - 1));
                p += nd - x - 1;
            }
        } else {
            *p++ = '0';
            *p++ = '.';
            for (int i = 0; i < -x - 1; i++)
                *p++ = '0';
            memcpy(p, d, (size_t)nd);
            p += nd;
        }
    } else {
        *p++ = d[0];
        if (nd > 1) {
            *p++ = '.';
            memcpy(p, d + 1, (size_t)(nd - 1));
            p += nd - 1;
        }
        *p++ = 'e';
        int ax = x;
        if (ax < 0) {
            *p++ = '-';
            ax = -ax;
        } else {
            *p++ = '+';
        }
        if (ax >= 100) { /* not reached: the fast path stops at 30 */
            *p++ = (char)('0' + ax / 100);
            ax %= 100;
        }
        memcpy(p, DIGITS2 + 2 * ax, 2);
        p += 2;
    }
    return (int)(p - out);
}

/* "%.9g" of v into out (at most MAX_LEN bytes, no terminator); returns the length. */
int g9(double v, char *out)
{
    int len = g9_fast(v, out);
    return len >= 0 ? len : slow(v, out);
}

/* The CSV lines of a C-contiguous (n, ncols) array into out, which holds at least
 * n * (ncols * MAX_LEN + 2) bytes; returns the number of bytes written (-1: no memory).
 * A column that holds one value (bit for bit) over the rows is formatted once. */
int64_t format_rows(const double *arr, int64_t n, int64_t ncols, char *out)
{
    if (n <= 0 || ncols <= 0)
        return 0;
    char *cache = malloc((size_t)ncols * MAX_LEN);
    int *clen = malloc((size_t)ncols * sizeof(int)); /* length if constant, else -1 */
    if (cache == NULL || clen == NULL) {
        free(cache);
        free(clen);
        return -1;
    }
    const uint64_t *bits = (const uint64_t *)arr;
    for (int64_t j = 0; j < ncols; j++) {
        uint64_t b0 = bits[j];
        int same = 1;
        for (int64_t i = 1; i < n; i++) {
            if (bits[i * ncols + j] != b0) {
                same = 0;
                break;
            }
        }
        clen[j] = same ? g9(arr[j], cache + j * MAX_LEN) : -1;
    }
    char *p = out;
    for (int64_t i = 0; i < n; i++) {
        const double *row = arr + i * ncols;
        for (int64_t j = 0; j < ncols; j++) {
            if (j)
                *p++ = ',';
            int len = clen[j];
            if (len >= 0) {
                memcpy(p, cache + j * MAX_LEN, (size_t)len);
                p += len;
            } else {
                p += g9(row[j], p);
            }
        }
        *p++ = '\r';
        *p++ = '\n';
    }
    free(cache);
    free(clen);
    return (int64_t)(p - out);
}
