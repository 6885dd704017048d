/* The simulated robot's RK4 step (sim_hal/plant.py's SimRobot._run) in C, for `ddrt sim` speed.
 *
 * Same formulas in the same order as the Python, compiled without FMA contraction or
 * fast-math and calling the same libm (tanh, sin, cos, log, sqrt) as CPython's math module,
 * so every result is bit-identical. The noise uses CPython's MT19937 (random.random's
 * 53-bit draw) and random.gauss's Box-Muller with its pair cache, on the generators' state
 * copied from Python. Commands reach the motors at the step the caller computed for each.
 */
#include <math.h>
#include <stdint.h>

#define MT_N 624
#define MT_M 397

typedef struct {
    uint32_t mt[MT_N];
    int32_t index;
    int32_t has_next;  /* random.gauss's cached second value */
    double next;
} rng_t;

static uint32_t genrand(rng_t *r) {
    static const uint32_t mag01[2] = {0x0U, 0x9908b0dfU};
    uint32_t y;
    uint32_t *mt = r->mt;
    if (r->index >= MT_N) {
        int kk;
        for (kk = 0; kk < MT_N - MT_M; kk++) {
            y = (mt[kk] & 0x80000000U) | (mt[kk + 1] & 0x7fffffffU);
            mt[kk] = mt[kk + MT_M] ^ (y >> 1) ^ mag01[y & 0x1U];
        }
        for (; kk < MT_N - 1; kk++) {
            y = (mt[kk] & 0x80000000U) | (mt[kk + 1] & 0x7fffffffU);
            mt[kk] = mt[kk + (MT_M - MT_N)] ^ (y >> 1) ^ mag01[y & 0x1U];
        }
        y = (mt[MT_N - 1] & 0x80000000U) | (mt[0] & 0x7fffffffU);
        mt[MT_N - 1] = mt[MT_M - 1] ^ (y >> 1) ^ mag01[y & 0x1U];
        r->index = 0;
    }
    y = mt[r->index++];
    y ^= (y >> 11);
    y ^= (y << 7) & 0x9d2c5680U;
    y ^= (y << 15) & 0xefc60000U;
    y ^= (y >> 18);
    return y;
}

static double rnd(rng_t *r) {
    uint32_t a = genrand(r) >> 5, b = genrand(r) >> 6;
    return (a * 67108864.0 + b) * (1.0 / 9007199254740992.0);
}

static double gauss_z(rng_t *r, double two_pi) {
    if (r->has_next) {
        r->has_next = 0;
        return r->next;
    }
    double x2pi = rnd(r) * two_pi;
    double g2rad = sqrt(-2.0 * log(1.0 - rnd(r)));
    double z = cos(x2pi) * g2rad;
    r->next = sin(x2pi) * g2rad;
    r->has_next = 1;
    return z;
}

/* Indices into the state array s[] and the constants c[] (plant.py: _STATE, _constants). */
enum { X, Y, TH, V, W, PHL, PHR, PH3, DL, DR, WEM, WFR, WSLIP, GF, TL, TR, NSTATE };

/* What plant_run works on, in one struct so a call passes one pointer (ctypes' cost is per
 * argument). Commands waiting for their latency are a ring of (step at which the duties reach
 * the motors, duty_l, duty_r); q = {head, tail, capacity}, entries head..tail-1 (mod capacity). */
typedef struct {
    int64_t *kp;
    double *s;
    const double *c;
    rng_t *slip, *gyro;
    double *ring_phi3, *ring_gyro;
    int64_t n_ring;
    int64_t *q;
    const int64_t *q_step;
    const double *q_duty;
    double *ring_phl, *ring_phr;  /* the drive wheels' angles, for their encoders */
} plant_t;

void plant_run(int64_t n_steps, plant_t *p) {
    int64_t *kp = p->kp, *q = p->q;
    double *s = p->s, *ring_phi3 = p->ring_phi3, *ring_gyro = p->ring_gyro;
    double *ring_phl = p->ring_phl, *ring_phr = p->ring_phr;
    const double *c = p->c, *q_duty = p->q_duty;
    const int64_t *q_step = p->q_step, n_ring = p->n_ring;
    rng_t *slip = p->slip, *gyro = p->gyro;
    const double h = c[0], h2 = c[1], h6 = c[2], a11 = c[3], a12 = c[4], a22 = c[5], mx = c[6];
    const double big_l = c[7], big_r = c[8], irl = c[9], irr = c[10], ir3 = c[11];
    const double cl = c[12], el = c[13], bl = c[14], tcl = c[15], iwsl = c[16];
    const double cr = c[17], er = c[18], br = c[19], tcr = c[20], iwsr = c[21];
    const int slip_on = c[22] != 0.0;
    const double slip_p = c[23], slip_frac = c[24], slip_sig = c[25];
    const double g_a = c[26], g_sig = c[27], g_scale = c[28], g_bias = c[29], two_pi = c[30];
    double x = s[X], y = s[Y], th = s[TH], v = s[V], w = s[W];
    double phi_l = s[PHL], phi_r = s[PHR], phi_3 = s[PH3];
    double dl = s[DL], dr = s[DR];
    double cdl = cl * dl, cdr = cr * dr;
    int64_t head = q[0];
    const int64_t tail = q[1], cap = q[2];
    double w_em = s[WEM], w_fr = s[WFR], w_slip = s[WSLIP], gf = s[GF];
    double tl = s[TL], tr = s[TR];
    int64_t k = *kp;
    for (int64_t step = 0; step < n_steps; step++) {
        if (head < tail && q_step[head % cap] <= k) {
            while (head < tail && q_step[head % cap] <= k) {
                dl = q_duty[2 * (head % cap)];
                dr = q_duty[2 * (head % cap) + 1];
                head++;
            }
            cdl = cl * dl;
            cdr = cr * dr;
        }
        double wl = (v - big_l * w) * irl, wr = (v + big_r * w) * irr;
        double eml = cdl - el * wl, emr = cdr - er * wr;
        double frl = bl * wl + tcl * tanh(wl * iwsl), frr = br * wr + tcr * tanh(wr * iwsr);
        tl = eml - frl;
        tr = emr - frr;
        double sl = 0.0, sr = 0.0;
        if (slip_on) {
            if (rnd(slip) < slip_p) {
                double z = gauss_z(slip, two_pi);
                sl = slip_frac * tl + z * slip_sig;
                if (rnd(slip) < 0.5) sl = -sl;
            }
            if (rnd(slip) < slip_p) {
                double z = gauss_z(slip, two_pi);
                sr = slip_frac * tr + z * slip_sig;
                if (rnd(slip) < 0.5) sr = -sr;
            }
            tl += sl;
            tr += sr;
        }
        double ul = tl * irl, ur = tr * irr;
        double fv = ul + ur + mx * w * w, fw = big_r * ur - big_l * ul - mx * v * w;
        double dv1 = a11 * fv + a12 * fw, dw1 = a12 * fv + a22 * fw;
        double pem = eml * wl + emr * wr, pfr = frl * wl + frr * wr;
        double v1 = v, w1 = w, th1 = th;
        double dv[3], dw[3], vs[3], ws[3], ths[3];
        double dvp = dv1, dwp = dw1, wp = w1;
        for (int st = 0; st < 3; st++) {  /* stages 2, 3, 4 */
            double hh = st < 2 ? h2 : h;
            double vk = v + hh * dvp, wk = w + hh * dwp, thk = th + hh * wp;
            wl = (vk - big_l * wk) * irl;
            wr = (vk + big_r * wk) * irr;
            eml = cdl - el * wl;
            emr = cdr - er * wr;
            frl = bl * wl + tcl * tanh(wl * iwsl);
            frr = br * wr + tcr * tanh(wr * iwsr);
            ul = (eml - frl + sl) * irl;
            ur = (emr - frr + sr) * irr;
            fv = ul + ur + mx * wk * wk;
            fw = big_r * ur - big_l * ul - mx * vk * wk;
            dv[st] = a11 * fv + a12 * fw;
            dw[st] = a12 * fv + a22 * fw;
            if (st < 2) {
                pem += 2.0 * (eml * wl + emr * wr);
                pfr += 2.0 * (frl * wl + frr * wr);
            } else {
                pem += eml * wl + emr * wr;
                pfr += frl * wl + frr * wr;
            }
            vs[st] = vk; ws[st] = wk; ths[st] = thk;
            dvp = dv[st]; dwp = dw[st]; wp = wk;
        }
        double v2 = vs[0], v3 = vs[1], v4 = vs[2], w2 = ws[0], w3 = ws[1], w4 = ws[2];
        double th2 = ths[0], th3 = ths[1], th4 = ths[2];
        double ds = h6 * (v1 + 2.0 * (v2 + v3) + v4);
        double dth = h6 * (w1 + 2.0 * (w2 + w3) + w4);
        x += h6 * (v1 * cos(th1) + 2.0 * (v2 * cos(th2) + v3 * cos(th3)) + v4 * cos(th4));
        y += h6 * (v1 * sin(th1) + 2.0 * (v2 * sin(th2) + v3 * sin(th3)) + v4 * sin(th4));
        th += dth;
        v += h6 * (dv1 + 2.0 * (dv[0] + dv[1]) + dv[2]);
        w += h6 * (dw1 + 2.0 * (dw[0] + dw[1]) + dw[2]);
        double dphi_l = (ds - big_l * dth) * irl, dphi_r = (ds + big_r * dth) * irr;
        phi_l += dphi_l;
        phi_r += dphi_r;
        phi_3 += ds * ir3;
        w_em += h6 * pem;
        w_fr += h6 * pfr;
        w_slip += sl * dphi_l + sr * dphi_r;
        k += 1;
        double z = gauss_z(gyro, two_pi);
        gf += g_a * (g_scale * w + g_bias + (0.0 + z * g_sig) - gf);
        int64_t i = k % n_ring;
        ring_phi3[i] = phi_3;
        ring_gyro[i] = gf;
        ring_phl[i] = phi_l;
        ring_phr[i] = phi_r;
    }
    s[X] = x; s[Y] = y; s[TH] = th; s[V] = v; s[W] = w;
    s[PHL] = phi_l; s[PHR] = phi_r; s[PH3] = phi_3;
    s[DL] = dl; s[DR] = dr;
    q[0] = head;
    s[WEM] = w_em; s[WFR] = w_fr; s[WSLIP] = w_slip; s[GF] = gf; s[TL] = tl; s[TR] = tr;
    *kp = k;
}
