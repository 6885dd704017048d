/* The simulated robot's RK4 step (sim_hal/plant.py's SimRobot._step) in C, for `ddrt sim` speed.
 *
 * It carries the options Realism.python_only does not name: the gyro's bias model (warm-up,
 * drift, step) and the driver's deadband. Same formulas in the same order as the Python
 * step, compiled without FMA contraction or
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

/* Indices into the state array s[] (plant.py's _native_setup); c[] is plant.py's _Consts. */
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

static double dead(double d, double db) { return fabs(d) < db ? 0.0 : d; }

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
    const double db = c[31];
    const int bias_varies = c[32] != 0.0;
    const double g_per_c = c[33], g_t0 = c[34], g_rise = c[35], g_tau = c[36], g_drift = c[37];
    const double g_step = c[38], g_step_at = c[39];
    double x = s[X], y = s[Y], th = s[TH], v = s[V], w = s[W];
    double phi_l = s[PHL], phi_r = s[PHR], phi_3 = s[PH3];
    double dl = s[DL], dr = s[DR];
    double cdl = cl * dead(dl, db), cdr = cr * dead(dr, db);
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
            cdl = cl * dead(dl, db);
            cdr = cr * dead(dr, db);
        }
        /* Four stages: _wheel_torques (the seed's motors), slip fixed at stage 1, _accel. */
        double vk = v, wk = w, thk = th;
        double dvs[4], dws[4], vs[4], ws[4], ths[4], pem[4], pfr[4];
        double sl = 0.0, sr = 0.0;
        for (int st = 0; st < 4; st++) {
            if (st > 0) {
                double hh = st < 3 ? h2 : h;
                vk = v + hh * dvs[st - 1];
                wk = w + hh * dws[st - 1];
                thk = th + hh * ws[st - 1];
            }
            double wl = (vk - big_l * wk) * irl, wr = (vk + big_r * wk) * irr;
            double fl = bl * wl + tcl * tanh(wl * iwsl), fr = br * wr + tcr * tanh(wr * iwsr);
            double eml = cdl - el * wl, emr = cdr - er * wr;
            double tl0 = eml - fl, tr0 = emr - fr;
            if (st == 0 && slip_on) {
                if (rnd(slip) < slip_p) {
                    sl = slip_frac * tl0 + gauss_z(slip, two_pi) * slip_sig;
                    if (rnd(slip) < 0.5) sl = -sl;
                }
                if (rnd(slip) < slip_p) {
                    sr = slip_frac * tr0 + gauss_z(slip, two_pi) * slip_sig;
                    if (rnd(slip) < 0.5) sr = -sr;
                }
            }
            double tlk = tl0 + sl, trk = tr0 + sr;
            if (st == 0) {
                tl = tlk;
                tr = trk;
            }
            double ul = tlk * irl, ur = trk * irr;
            double fv = ul + ur + mx * wk * wk, fw = big_r * ur - big_l * ul - mx * vk * wk;
            dvs[st] = a11 * fv + a12 * fw;
            dws[st] = a12 * fv + a22 * fw;
            pem[st] = eml * wl + emr * wr;
            pfr[st] = fl * wl + fr * wr;
            vs[st] = vk; ws[st] = wk; ths[st] = thk;
        }
        double v2 = vs[1], v3 = vs[2], v4 = vs[3], w2 = ws[1], w3 = ws[2], w4 = ws[3];
        double th2 = ths[1], th3 = ths[2], th4 = ths[3];
        double ds = h6 * (v + 2.0 * (v2 + v3) + v4);
        double dth = h6 * (w + 2.0 * (w2 + w3) + w4);
        x += h6 * (v * cos(th) + 2.0 * (v2 * cos(th2) + v3 * cos(th3)) + v4 * cos(th4));
        y += h6 * (v * sin(th) + 2.0 * (v2 * sin(th2) + v3 * sin(th3)) + v4 * sin(th4));
        th = th + dth;
        v = v + h6 * (dvs[0] + 2.0 * (dvs[1] + dvs[2]) + dvs[3]);
        w = w + h6 * (dws[0] + 2.0 * (dws[1] + dws[2]) + dws[3]);
        double dphi_l = (ds - big_l * dth) * irl, dphi_r = (ds + big_r * dth) * irr;
        phi_l += dphi_l;
        phi_r += dphi_r;
        phi_3 += ds * ir3;
        w_em += h6 * (pem[0] + 2.0 * (pem[1] + pem[2]) + pem[3]);
        w_fr += h6 * (pfr[0] + 2.0 * (pfr[1] + pfr[2]) + pfr[3]);
        w_slip += sl * dphi_l + sr * dphi_r;
        k += 1;
        /* _sense: the gyro's low-pass at the plant rate, its bias as gyro_bias_dps_at. */
        double bias = g_bias;
        if (bias_varies) {
            double t = k * h;
            double temp = g_t0 + g_rise * (1.0 - exp(-t / g_tau));
            bias = g_bias + g_per_c * (temp - g_t0) + g_drift * t;
            if (g_step != 0.0 && t >= g_step_at) bias += g_step;
        }
        double z = gauss_z(gyro, two_pi);
        gf += g_a * (g_scale * w + bias + (0.0 + z * g_sig) - gf);
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
