/* The simulated robot's RK4 step (sim_hal/plant.py's SimRobot._step) in C, for `ddrt sim` speed.
 *
 * It carries every option of the plant: the battery, the gyro's bias model (warm-up, drift,
 * step), the driver's deadband, the gearboxes' backlash, the encoders' slip and the floor
 * patches (payloads: the caller stops the kernel at each and updates c[]). Same formulas in
 * the same order as the Python step, compiled without FMA contraction or
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

/* Indices into the state array s[] (plant.py's _S). */
enum { X, Y, TH, V, W, PHL, PHR, PH3, DL, DR, WEM, WFR, WSLIP, GF, TL, TR,
       SOC, CHG, SRC, INTL, ARM, FREE, CUR, VT, C3, CL, CR, OU3, OUL, OUR,
       SDL, SDR, GPL, GPR, GRL, GRR, NSTATE };  /* backlash: side (+-1 on a flank, 0 free), gap, gap rate */

/* c[]: plant.py's _Consts (NC of them), then the options' constants from index NC (plant.py's
 * _kernel_constants), then the battery's OCV table (n_ocv (soc, volts) pairs) and the floor
 * patches (n_floor of x_min, y_min, x_max, y_max, friction scale). */
#define NC 40
enum { BAT = NC, RI, KL, RL, KR, RR, SOC0, CAP, OCV_MUL, COUNTS, SPN, OU3_M, OU3_A, OU3_K, OUL_M, OUL_A,
       OUL_K, OUR_M, OUR_A, OUR_K, HALF, JM, VL, VR, N_OCV, N_FLOOR, TABLES };

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
    double *ring_phl, *ring_phr;  /* the drive wheels' counted angles, for their encoders */
    rng_t *real;  /* the options' own draws (the encoders' wandering scales) */
} plant_t;

static double dead(double d, double db) { return fabs(d) < db ? 0.0 : d; }

/* ddrt/config/sim_truth.py's _interp: piecewise linear through (x, y) pairs, flat beyond. */
static double interp(const double *tab, int64_t n, double x) {
    if (x <= tab[0]) return tab[1];
    for (int64_t i = 0; i + 1 < n; i++) {
        double x0 = tab[2 * i], y0 = tab[2 * i + 1], x1 = tab[2 * i + 2], y1 = tab[2 * i + 3];
        if (x <= x1) return y0 + (y1 - y0) * (x - x0) / (x1 - x0);
    }
    return tab[2 * n - 1];
}

/* plant.py's _pack_v: the pack's terminal voltage with duties (dl, dr) on motors at (ml, mr). */
static double pack_v(const double *c, double ocv, double dl, double dr, double ml, double mr) {
    double num = ocv, den = 1.0;
    num += c[RI] * dl * c[KL] * ml / c[RL];
    den += c[RI] * dl * dl / c[RL];
    num += c[RI] * dr * c[KR] * mr / c[RR];
    den += c[RI] * dr * dr / c[RR];
    return num / den;
}

void plant_run(int64_t n_steps, plant_t *p) {
    int64_t *kp = p->kp, *q = p->q;
    double *s = p->s, *ring_phi3 = p->ring_phi3, *ring_gyro = p->ring_gyro;
    double *ring_phl = p->ring_phl, *ring_phr = p->ring_phr;
    const double *c = p->c, *q_duty = p->q_duty;
    const int64_t *q_step = p->q_step, n_ring = p->n_ring;
    rng_t *slip = p->slip, *gyro = p->gyro, *real = p->real;
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
    const int battery = c[BAT] != 0.0, counts = c[COUNTS] != 0.0;
    const double half = c[HALF];
    const int64_t n_ocv = (int64_t)c[N_OCV], n_floor = (int64_t)c[N_FLOOR];
    const double *ocv_tab = c + TABLES, *floor_tab = c + TABLES + 2 * n_ocv;
    double x = s[X], y = s[Y], th = s[TH], v = s[V], w = s[W];
    double phi_l = s[PHL], phi_r = s[PHR], phi_3 = s[PH3];
    double dl = s[DL], dr = s[DR];
    double ddl = dead(dl, db), ddr = dead(dr, db);
    double cdl = cl * ddl, cdr = cr * ddr;
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
            ddl = dead(dl, db);
            ddr = dead(dr, db);
            cdl = cl * ddl;
            cdr = cr * ddr;
        }
        double fs = 1.0;  /* _floor_scale: the first patch A is in */
        for (int64_t i = 0; i < n_floor; i++) {
            const double *f = floor_tab + 5 * i;
            if (f[0] <= x && x <= f[2] && f[1] <= y && y <= f[3]) {
                fs = f[4];
                break;
            }
        }
        const double ocv = battery ? c[OCV_MUL] * interp(ocv_tab, n_ocv, s[SOC]) : s[VT];
        if (half > 0.0) {  /* _release: a motor whose torque turns away from its flank leaves it */
            double wl = (v - big_l * w) * irl, wr = (v + big_r * w) * irr;
            double vt = battery ? pack_v(c, ocv, ddl, ddr, wl, wr) : 0.0;
            if (s[SDL] != 0.0) {
                double em = c[KL] * (ddl * (battery ? vt : c[VL]) - c[KL] * wl) / c[RL];
                if (s[SDL] * em <= 0.0) { s[SDL] = 0.0; s[GRL] = 0.0; }
            }
            if (s[SDR] != 0.0) {
                double em = c[KR] * (ddr * (battery ? vt : c[VR]) - c[KR] * wr) / c[RR];
                if (s[SDR] * em <= 0.0) { s[SDR] = 0.0; s[GRR] = 0.0; }
            }
        }
        const double side_l = s[SDL], side_r = s[SDR], gr_l = s[GRL], gr_r = s[GRR];
        /* Four stages: _wheel_torques, slip fixed at stage 1, _accel. */
        double vk = v, wk = w, thk = th;
        double dvs[4], dws[4], vs[4], ws[4], ths[4], pem[4], pfr[4], psrc[4], pint[4], parm[4], pfree[4], pib[4];
        double sl = 0.0, sr = 0.0;
        for (int st = 0; st < 4; st++) {
            if (st > 0) {
                double hh = st < 3 ? h2 : h;
                vk = v + hh * dvs[st - 1];
                wk = w + hh * dws[st - 1];
                thk = th + hh * ws[st - 1];
            }
            double wl = (vk - big_l * wk) * irl, wr = (vk + big_r * wk) * irr;
            double fl = fs * (bl * wl + tcl * tanh(wl * iwsl)), fr = fs * (br * wr + tcr * tanh(wr * iwsr));
            double tl0, tr0;
            psrc[st] = pint[st] = parm[st] = pfree[st] = pib[st] = 0.0;
            if (!battery && side_l != 0.0 && side_r != 0.0) {  /* the seed's motors, both driving */
                double eml = cdl - el * wl, emr = cdr - er * wr;
                tl0 = eml - fl;
                tr0 = emr - fr;
                pem[st] = eml * wl + emr * wr;
            } else {  /* the pack's voltage, or a motor free in the play */
                double ml = side_l != 0.0 ? wl : wl + gr_l, mr = side_r != 0.0 ? wr : wr + gr_r;
                double eml, emr, cur_l, cur_r;
                if (!battery) {
                    eml = cl * ddl - el * ml;
                    emr = cr * ddr - er * mr;
                    cur_l = (ddl * c[VL] - c[KL] * ml) / c[RL];
                    cur_r = (ddr * c[VR] - c[KR] * mr) / c[RR];
                } else {
                    double vt = pack_v(c, ocv, ddl, ddr, ml, mr);
                    cur_l = (ddl * vt - c[KL] * ml) / c[RL];
                    cur_r = (ddr * vt - c[KR] * mr) / c[RR];
                    eml = c[KL] * cur_l;
                    emr = c[KR] * cur_r;
                }
                double pe = 0.0, pf = 0.0;
                if (side_l != 0.0) { tl0 = eml - fl; pe = eml * wl; } else { tl0 = -fl; pf = eml * ml; }
                if (side_r != 0.0) { tr0 = emr - fr; pe = pe + emr * wr; } else { tr0 = -fr; pf = pf + emr * mr; }
                double ib = ddl * cur_l + ddr * cur_r;
                pem[st] = pe;
                pfree[st] = pf;
                parm[st] = c[RL] * cur_l * cur_l + c[RR] * cur_r * cur_r;
                psrc[st] = ocv * ib;
                pint[st] = c[RI] * ib * ib;
                pib[st] = ib;
            }
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
            pfr[st] = fl * wl + fr * wr;
            vs[st] = vk; ws[st] = wk; ths[st] = thk;
        }
#define RK(a) (h6 * ((a)[0] + 2.0 * ((a)[1] + (a)[2]) + (a)[3]))
        double v2 = vs[1], v3 = vs[2], v4 = vs[3], w2 = ws[1], w3 = ws[2], w4 = ws[3];
        double th2 = ths[1], th3 = ths[2], th4 = ths[3];
        double ds = h6 * (v + 2.0 * (v2 + v3) + v4);
        double dth = h6 * (w + 2.0 * (w2 + w3) + w4);
        x += h6 * (v * cos(th) + 2.0 * (v2 * cos(th2) + v3 * cos(th3)) + v4 * cos(th4));
        y += h6 * (v * sin(th) + 2.0 * (v2 * sin(th2) + v3 * sin(th3)) + v4 * sin(th4));
        th = th + dth;
        const double v_new = v + RK(dvs), w_new = w + RK(dws);
        if (half > 0.0) {  /* _free_motors: exact for the step's voltage, inelastic at the flank */
            double wl_old = (v - big_l * w) * irl, wr_old = (v + big_r * w) * irr;
            double ww_new[2] = {(v_new - big_l * w_new) * irl, (v_new + big_r * w_new) * irr};
            double wm[2] = {wl_old + s[GRL], wr_old + s[GRR]};
            double vt = battery ? pack_v(c, ocv, ddl, ddr, wm[0], wm[1]) : 0.0;
            const int sides[2] = {SDL, SDR}, gaps[2] = {GPL, GPR}, rates[2] = {GRL, GRR}, ks[2] = {KL, KR};
            const int rs[2] = {RL, RR}, vs_[2] = {VL, VR};
            const double ds_[2] = {ddl, ddr};
            for (int i = 0; i < 2; i++) {
                if (s[sides[i]] != 0.0) continue;
                double supply = battery ? vt : c[vs_[i]];
                double rate = pow(c[ks[i]], 2.0) / (c[rs[i]] * c[JM]);
                double settled = ds_[i] * supply / c[ks[i]];
                double nw = settled + (wm[i] - settled) * exp(-rate * h);
                s[rates[i]] = nw - ww_new[i];
                s[gaps[i]] += h * s[rates[i]];
                if (fabs(s[gaps[i]]) >= half) {
                    s[sides[i]] = s[gaps[i]] > 0 ? 1.0 : -1.0;
                    s[gaps[i]] = copysign(half, s[gaps[i]]);
                    s[rates[i]] = 0.0;
                }
            }
        }
        v = v_new;
        w = w_new;
        double dphi_l = (ds - big_l * dth) * irl, dphi_r = (ds + big_r * dth) * irr, dphi_3 = ds * ir3;
        phi_l += dphi_l;
        phi_r += dphi_r;
        phi_3 += dphi_3;
        w_em += RK(pem);
        w_fr += RK(pfr);
        w_slip += sl * dphi_l + sr * dphi_r;
        if (battery || half > 0.0) {
            s[SRC] += RK(psrc);
            s[INTL] += RK(pint);
            s[ARM] += RK(parm);
            s[FREE] += RK(pfree);
            s[CHG] += RK(pib);
        }
        if (battery) {
            double soc = c[SOC0] - s[CHG] / (3600.0 * c[CAP]);
            soc = soc > 0.0 ? soc : 0.0;
            s[SOC] = soc < 1.0 ? soc : 1.0;
            double wl = (v - big_l * w) * irl + (s[SDL] != 0.0 ? 0.0 : s[GRL]);
            double wr = (v + big_r * w) * irr + (s[SDR] != 0.0 ? 0.0 : s[GRR]);
            double vt = pack_v(c, c[OCV_MUL] * interp(ocv_tab, n_ocv, s[SOC]), ddl, ddr, wl, wr);
            s[VT] = vt;
            s[CUR] = ddl * (ddl * vt - c[KL] * wl) / c[RL] + ddr * (ddr * vt - c[KR] * wr) / c[RR];
        }
#undef RK
        k += 1;
        /* _sense: the counted angles, then the gyro's low-pass at the plant rate, its bias as
         * gyro_bias_dps_at. */
        double c3 = phi_3, cnt_l = phi_l, cnt_r = phi_r;
        if (counts) {
            s[C3] += dphi_3 * (1.0 + c[OU3_M] + s[OU3]);
            s[CL] += dphi_l * (1.0 + c[OUL_M] + s[OUL]) + c[SPN] * tl * fabs(dphi_l);
            s[CR] += dphi_r * (1.0 + c[OUR_M] + s[OUR]) + c[SPN] * tr * fabs(dphi_r);
            if (c[OU3_K] != 0.0) s[OU3] = c[OU3_A] * s[OU3] + c[OU3_K] * (0.0 + gauss_z(real, two_pi) * 1.0);
            if (c[OUL_K] != 0.0) s[OUL] = c[OUL_A] * s[OUL] + c[OUL_K] * (0.0 + gauss_z(real, two_pi) * 1.0);
            if (c[OUR_K] != 0.0) s[OUR] = c[OUR_A] * s[OUR] + c[OUR_K] * (0.0 + gauss_z(real, two_pi) * 1.0);
            c3 = s[C3];
            cnt_l = s[CL];
            cnt_r = s[CR];
        }
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
        ring_phi3[i] = c3;
        ring_gyro[i] = gf;
        ring_phl[i] = cnt_l;
        ring_phr[i] = cnt_r;
    }
    s[X] = x; s[Y] = y; s[TH] = th; s[V] = v; s[W] = w;
    s[PHL] = phi_l; s[PHR] = phi_r; s[PH3] = phi_3;
    s[DL] = dl; s[DR] = dr;
    q[0] = head;
    s[WEM] = w_em; s[WFR] = w_fr; s[WSLIP] = w_slip; s[GF] = gf; s[TL] = tl; s[TR] = tr;
    *kp = k;
}
