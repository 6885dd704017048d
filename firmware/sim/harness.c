/* ddrt-simavr: the bridge firmware (an ATmega328P ELF) in simavr, wired to a simulated robot.
 *
 *   ddrt-simavr [--paced] [--pipe] [--driver dir2|drv8871] [--freq HZ] [--batt-full-mv MV] FIRMWARE.elf
 *
 * UART0 goes to a pseudo-terminal (own glue, not the parts library's uart_pty: its thread
 * moves bytes on the wall clock, which a lockstep run must not) or, with --pipe, through
 * the control channel. The encoders' A/B pins (front: PD2/PD3; drive wheels: PC2/PC3 and
 * PC4/PC5) are driven with avr_raise_irq, each from a piecewise-linear count trajectory; the
 * battery divider's voltage goes to ADC0 (PC0) and the estop input is PC1 (low: closed,
 * high: open). The motor outputs are read from Timer1's compare registers and the direction
 * pins, sampled once per PWM period, as the mean drive each H-bridge applies (-1..1). The
 * pin map is firmware/src/board.h's.
 *
 * Control channel: one command per line on stdin, replies on stdout, each ending with an
 * "ok ..." line (or "err ..."). Times are CPU cycles since power-on.
 *
 *   run CYCLE DELTA [SYNC [DL DR [MV]]]
 *                          lockstep: first take SYNC host bytes in total from the pty (the
 *                          host wrote them before this command; "-": none), then simulate up
 *                          to CYCLE with the front encoder moving DELTA counts and the drive
 *                          wheels DL, DR evenly over the interval, the battery at MV mV
 *   enc COUNT RATE [L LRATE R RRATE]
 *                          the encoder heads for COUNT (absolute, since power-on), then goes
 *                          on at RATE counts/s (paced mode: the plant's latest state), and
 *                          the drive wheels likewise; replies as `out`
 *   bat MV                 the battery (mV, before the divider) from now
 *   estop 0|1              the estop input closed (0) or open (1) from now
 *   out                    (paced) outputs now, and the mean since the previous out
 *   send HEX               host bytes into the UART now (queued at the line rate);
 *                          replies "ok CYCLE" with the cycle the last byte is received
 *   reset                  external reset (the RESET pin)
 *   events 0|1             report each change of the sampled outputs as "ev CYCLE L R"
 *   regs                   Timer1 and port registers, for tests
 *   quit
 *
 * The reply to run/enc/out is "ok CYCLE INST_L INST_R MEAN_L MEAN_R ENC_COUNT RESETS TX_TOTAL
 * STATE WHEEL_L WHEEL_R" (drives -1..1 now and averaged since the last report, the count the
 * front A/B lines show, resets so far, MCU -> host bytes delivered so far, the CPU state, the
 * counts the wheels' lines show), after any "ev CYCLE L R",
 * "rst CYCLE MCUSR" (a reset, with the cause the firmware found in MCUSR) and, with --pipe,
 * "tx END BYTE_CYCLES HEX" lines (MCU -> host bytes sent back to back; END is the cycle the
 * first one's stop bit ends, each next one a byte time later).
 *
 * Paced (--paced): simulated time follows the wall clock; the harness runs on its own and
 * serves commands and the pty as they come. Otherwise time moves only on `run`.
 */
#define _GNU_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <getopt.h>
#include <inttypes.h>
#include <math.h>
#include <poll.h>
#include <pty.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#include "avr_adc.h"
#include "avr_extint.h"
#include "avr_ioport.h"
#include "avr_uart.h"
#include "sim_avr.h"
#include "sim_elf.h"
#include "sim_io.h"
#include "sim_irq.h"

/* ATmega328P data-space addresses of the registers read here. */
#define R_PINC 0x26
#define R_DDRC 0x27
#define R_PORTC 0x28
#define R_PIND 0x29
#define R_DDRD 0x2A
#define R_PORTD 0x2B
#define R_DDRB 0x24
#define R_PORTB 0x25
#define R_MCUSR 0x54
#define R_TCCR1A 0x80
#define R_TCCR1B 0x81
#define R_ICR1L 0x86
#define R_OCR1AL 0x88
#define R_OCR1BL 0x8A
#define R_UCSR0A 0xC0
#define R_UBRR0L 0xC4
#define R_UBRR0H 0xC5
#define EXTRF_BIT 1

/* The pin map of firmware/src/board.h. */
#define ENC_A_PIN 2 /* PD2 INT0 */
#define ENC_B_PIN 3 /* PD3 INT1 */
#define L_IN1 4     /* PD4 */
#define L_IN2 5     /* PD5 */
#define R_IN1 6     /* PD6 */
#define R_IN2 7     /* PD7 */
#define PWM_L 1     /* PB1 OC1A */
#define PWM_R 2     /* PB2 OC1B */
#define ESTOP_PIN 1 /* PC1 */
#define WHL_A_PIN 2 /* PC2, B = PC3 */
#define WHR_A_PIN 4 /* PC4, B = PC5 */

enum { DRIVER_DIR2, DRIVER_DRV8871 };

static avr_t *avr;
static int driver = DRIVER_DIR2;
static int paced;
static int pipe_mode;
static int events_on;
static int pty_master = -1, pty_slave = -1;
static char pty_name[256];
static void (*core_reset)(struct avr_t *);

/* ------------------------------------------------------------------ output helpers */

static char outbuf[1 << 16];
static size_t outlen;

static void emit(const char *fmt, ...) __attribute__((format(printf, 1, 2)));
static void emit(const char *fmt, ...)
{
    va_list ap;
    va_start(ap, fmt);
    int n = vsnprintf(outbuf + outlen, sizeof outbuf - outlen, fmt, ap);
    va_end(ap);
    if (n < 0)
        return;
    if ((size_t)n >= sizeof outbuf - outlen) { /* flush and retry */
        fwrite(outbuf, 1, outlen, stdout);
        outlen = 0;
        va_start(ap, fmt);
        n = vsnprintf(outbuf, sizeof outbuf, fmt, ap);
        va_end(ap);
        if (n < 0)
            return;
        if ((size_t)n >= sizeof outbuf)
            n = sizeof outbuf - 1;
    }
    outlen += (size_t)n;
}

static void flush_out(void)
{
    if (outlen)
        fwrite(outbuf, 1, outlen, stdout);
    outlen = 0;
    fflush(stdout);
}

/* ------------------------------------------------------------------ outputs */

static double drive_now[2];      /* the last sample */
static double drive_sum[2];      /* sum of samples since the last report */
static uint64_t drive_n;
static avr_cycle_count_t pwm_period = 800;

static uint16_t reg16(int lo) { return (uint16_t)(avr->data[lo] | (avr->data[lo + 1] << 8)); }

/* Mean level of an OC1x pin over a PWM period: 0..1. A pin that is an input reads 0 (the
 * drivers' inputs have pull-downs; docs/hardware.md). */
static double oc_level(int pin, int com_shift, int ocr_reg)
{
    if (!(avr->data[R_DDRB] & (1 << pin)))
        return 0.0;
    int com = (avr->data[R_TCCR1A] >> com_shift) & 3;
    if (com < 2 || !(avr->data[R_TCCR1B] & 7))
        return (avr->data[R_PORTB] >> pin) & 1; /* compare unit off (or timer stopped) */
    double top = reg16(R_ICR1L);
    double ocr = reg16(ocr_reg);
    double p = top > 0 ? (ocr >= top ? 1.0 : ocr / top) : 0.0;
    return com == 3 ? 1.0 - p : p;
}

static int dpin(int bit)
{
    return (avr->data[R_DDRD] & (1 << bit)) ? (avr->data[R_PORTD] >> bit) & 1 : 0;
}

static double bridge_drive(double pwm, int in1, int in2)
{
    if (driver == DRIVER_DRV8871) /* IN1 = PWM pin, IN2 = direction pin */
        return in2 ? -(1.0 - pwm) : pwm;
    if (in1 && !in2)
        return pwm;
    if (in2 && !in1)
        return -pwm;
    return 0.0;
}

static void sample_outputs(double out[2])
{
    if (avr->state == cpu_Crashed || avr->state == cpu_Done) {
        out[0] = out[1] = 0.0; /* a dead CPU: its pins are whatever; count it as off */
        return;
    }
    double pl = oc_level(PWM_L, 6, R_OCR1AL);
    double pr = oc_level(PWM_R, 4, R_OCR1BL);
    out[0] = bridge_drive(pl, dpin(L_IN1), dpin(L_IN2));
    out[1] = bridge_drive(pr, dpin(R_IN1), dpin(R_IN2));
}

static avr_cycle_count_t sampler(struct avr_t *a, avr_cycle_count_t when, void *param)
{
    (void)a;
    (void)param;
    double d[2];
    sample_outputs(d);
    if (events_on && (d[0] != drive_now[0] || d[1] != drive_now[1]))
        emit("ev %" PRIu64 " %.6f %.6f\n", (uint64_t)when, d[0], d[1]);
    drive_now[0] = d[0];
    drive_now[1] = d[1];
    drive_sum[0] += d[0];
    drive_sum[1] += d[1];
    drive_n++;
    return when + pwm_period;
}

/* ------------------------------------------------------------------ encoders */

/* One quadrature channel: its A/B lines and the count trajectory they follow. The target is
 * linear from (c0, v0) to (c1, v1), then v1 + rate * (t - c1); the lines show
 * floor(target + 0.5), one transition at a time, at least ENC_MIN_GAP apart. */
typedef struct {
    avr_irq_t *a, *b;
    int pin_reg, a_pin; /* data-space PINx and the A bit (B is the next one) */
    int64_t emitted;        /* the count the lines show, since power-on */
    avr_cycle_count_t last; /* cycle of the last transition */
    double c0, v0, c1, v1, rate;
} enc_ch_t;

enum { CH_FRONT, CH_LEFT, CH_RIGHT, N_CH };
static enc_ch_t ch[N_CH];
static const avr_cycle_count_t ENC_MIN_GAP = 16; /* 1 us: far faster than any encoder here */
static const uint8_t a_of[4] = {0, 1, 1, 0}, b_of[4] = {0, 0, 1, 1}; /* counting up: A leads */

static double target_at(const enc_ch_t *e, double c)
{
    if (c <= e->c0)
        return e->v0;
    if (c < e->c1)
        return e->v0 + (e->v1 - e->v0) * (c - e->c0) / (e->c1 - e->c0);
    return e->v1 + e->rate * (c - e->c1) / avr->frequency;
}

static int64_t goal_at(const enc_ch_t *e, double c) { return (int64_t)floor(target_at(e, c) + 0.5); }

/* The earliest cycle >= from at which goal_at() differs from n (approximately: the timer
 * re-checks), or -1 if the trajectory stays. */
static double next_change(const enc_ch_t *e, double from, int64_t n)
{
    if (goal_at(e, from) != n)
        return from;
    double hi = (double)n + 0.5, lo = (double)n - 0.5;
    double v = target_at(e, from);
    if (from < e->c1) {
        double k = (e->c1 - e->c0) / (e->v1 - e->v0);
        if (e->v1 >= hi) {
            double c = e->c0 + (hi - e->v0) * k;
            return c > from ? c : from;
        }
        if (e->v1 < lo) {
            double c = e->c0 + (lo - e->v0) * k;
            return c > from ? c : from;
        }
        from = e->c1;
        v = e->v1;
    }
    if (e->rate > 0)
        return from + (hi - v) / e->rate * avr->frequency;
    if (e->rate < 0)
        return from + (lo - v) / e->rate * avr->frequency;
    return -1;
}

static void set_ab(enc_ch_t *e)
{
    int g = (int)(e->emitted & 3);
    avr_raise_irq(e->a, a_of[g]);
    avr_raise_irq(e->b, b_of[g]);
}

static avr_cycle_count_t enc_timer(struct avr_t *a, avr_cycle_count_t when, void *param)
{
    (void)a;
    enc_ch_t *e = param;
    int64_t m = goal_at(e, (double)when);
    if (m == e->emitted) { /* early by a rounding error, or nothing to do */
        double c = next_change(e, (double)when, e->emitted);
        if (c < 0)
            return 0;
        avr_cycle_count_t at = (avr_cycle_count_t)ceil(c);
        return at > when ? at : when + 1;
    }
    e->emitted += m > e->emitted ? 1 : -1;
    set_ab(e);
    e->last = when;
    double c = next_change(e, (double)when, e->emitted);
    if (c < 0)
        return 0;
    avr_cycle_count_t at = (avr_cycle_count_t)ceil(c);
    return at > when + ENC_MIN_GAP ? at : when + ENC_MIN_GAP;
}

static void enc_schedule(enc_ch_t *e)
{
    avr_cycle_timer_cancel(avr, enc_timer, e);
    double c = next_change(e, (double)avr->cycle, e->emitted);
    if (c < 0)
        return;
    avr_cycle_count_t at = (avr_cycle_count_t)ceil(c);
    if (at < e->last + ENC_MIN_GAP)
        at = e->last + ENC_MIN_GAP;
    if (at <= avr->cycle)
        at = avr->cycle + 1;
    avr_cycle_timer_register(avr, at - avr->cycle, enc_timer, e);
}

/* From now, move the target linearly to v1 at cycle c1, then on at `rate` counts/s. */
static void enc_segment(enc_ch_t *e, double c1, double v1, double rate)
{
    double now = (double)avr->cycle;
    e->v0 = target_at(e, now);
    e->c0 = now;
    e->c1 = c1 > now ? c1 : now;
    e->v1 = v1;
    e->rate = rate;
    if (e->c1 == e->c0)
        e->v0 = v1;
    enc_schedule(e);
}

/* Head for COUNT within a millisecond (no faster than the encoder could), then go on. */
static void enc_head_for(enc_ch_t *e, double count, double rate)
{
    double now = (double)avr->cycle;
    double dist = fabs(count - target_at(e, now));
    double ms = avr->frequency / 1000.0;
    double span = dist * ENC_MIN_GAP * 4 > ms ? dist * ENC_MIN_GAP * 4 : ms;
    enc_segment(e, now + span, count + rate * span / avr->frequency, rate);
}

/* After a reset cleared the PINx registers (or a pull-up moved them): the lines still show
 * what they showed. The pins' IRQs keep the same value, or simavr would drop the next raise
 * of the value they took meanwhile as no change. */
static void enc_restore_pins(struct avr_t *a, const enc_ch_t *e)
{
    int g = (int)(e->emitted & 3);
    e->a->value = a_of[g];
    e->b->value = b_of[g];
    a->data[e->pin_reg] = (uint8_t)((a->data[e->pin_reg] & ~(3 << e->a_pin)) |
                                    (a_of[g] << e->a_pin) | (b_of[g] << (e->a_pin + 1)));
}

static void enc_init(enc_ch_t *e, char port, int pin_reg, int a_pin)
{
    e->a = avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ(port), a_pin);
    e->b = avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ(port), a_pin + 1);
    e->pin_reg = pin_reg;
    e->a_pin = a_pin;
}

/* ------------------------------------------------------------------ battery, estop */

static avr_irq_t *adc0, *estop_irq;
static double batt_full_mv = 20743.0; /* the firmware's BATT_FULL_MV: 1100 mV at the ADC pin */
static uint32_t batt_mv = 12000;
static int estop_is_open;

static void apply_battery(void)
{
    avr_raise_irq(adc0, (uint32_t)floor(batt_mv * 1100.0 / batt_full_mv + 0.5));
}

static void estop_pin(struct avr_t *a)
{
    estop_irq->value = (uint32_t)estop_is_open;
    a->data[R_PINC] = (uint8_t)((a->data[R_PINC] & ~(1 << ESTOP_PIN)) | (estop_is_open << ESTOP_PIN));
}

static void apply_estop(struct avr_t *a)
{
    avr_raise_irq(estop_irq, estop_is_open ? 1 : 0);
    estop_pin(a);
}

/* The firmware turns pull-ups on (PORTx bits of inputs), and simavr then reads those pins
 * high; but the lines here are driven (push-pull encoder outputs, the estop loop to GND),
 * which a pull-up does not move: after each PORTC/PORTD write, the pins read what they are
 * driven to again. */
static void port_write(struct avr_t *a, avr_io_addr_t addr, uint8_t v, void *param)
{
    (void)addr;
    (void)v;
    (void)param;
    for (int i = 0; i < N_CH; i++)
        enc_restore_pins(a, &ch[i]);
    estop_pin(a);
}

/* ------------------------------------------------------------------ UART */

static avr_irq_t *uart_in;
#define RXQ_SIZE 8192
static uint8_t rxq[RXQ_SIZE];
static size_t rxq_head, rxq_tail;   /* host -> MCU bytes waiting for the line */
static avr_cycle_count_t line_free; /* the cycle the host's line is next idle */
static uint64_t host_rx_total;      /* host bytes taken from the pty */

#define TXQ_SIZE 8192
static struct { avr_cycle_count_t at; uint8_t b; } txq[TXQ_SIZE];
static size_t txq_head, txq_tail;   /* MCU -> host bytes until their stop bit ends */
static uint64_t tx_lost;
static uint64_t tx_total; /* MCU -> host bytes delivered (to the pty, or in tx lines) */

/* Cycles per byte as simavr's UART paces them (it counts start + 8 data + a parity bit +
 * stop for 8N1: 11 bits), from the firmware's own UBRR0 and U2X0. */
static avr_cycle_count_t byte_cycles(void)
{
    uint32_t ubrr = (uint32_t)(avr->data[R_UBRR0L] | ((avr->data[R_UBRR0H] & 0x0F) << 8));
    uint32_t per_bit = (ubrr + 1) * ((avr->data[R_UCSR0A] & 0x02) ? 8u : 16u);
    return (avr_cycle_count_t)per_bit * 11u;
}

static avr_cycle_count_t feed_timer(struct avr_t *a, avr_cycle_count_t when, void *param)
{
    (void)a;
    (void)param;
    if (rxq_tail == rxq_head)
        return 0;
    uint8_t b = rxq[rxq_tail];
    rxq_tail = (rxq_tail + 1) % RXQ_SIZE;
    avr_raise_irq(uart_in, b);
    line_free = when + byte_cycles();
    return rxq_tail == rxq_head ? 0 : line_free;
}

static void feed_schedule(void)
{
    if (rxq_tail == rxq_head || avr_cycle_timer_status(avr, feed_timer, NULL))
        return;
    avr_cycle_count_t at = line_free > avr->cycle ? line_free : avr->cycle + 1;
    avr_cycle_timer_register(avr, at - avr->cycle, feed_timer, NULL);
}

/* Queue host bytes; returns the cycle the last one will have been received. */
static avr_cycle_count_t host_bytes(const uint8_t *p, size_t n)
{
    for (size_t i = 0; i < n; i++) {
        size_t next = (rxq_head + 1) % RXQ_SIZE;
        if (next == rxq_tail)
            break; /* a host that floods a 115200 line loses bytes, as it would */
        rxq[rxq_head] = p[i];
        rxq_head = next;
    }
    feed_schedule();
    size_t total = (rxq_head + RXQ_SIZE - rxq_tail) % RXQ_SIZE;
    avr_cycle_count_t start = line_free > avr->cycle ? line_free : avr->cycle + 1;
    return start + (avr_cycle_count_t)total * byte_cycles();
}

static void uart_out(struct avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    size_t next = (txq_head + 1) % TXQ_SIZE;
    if (next == txq_tail) {
        tx_lost++;
        return;
    }
    txq[txq_head].at = avr->cycle + byte_cycles();
    txq[txq_head].b = (uint8_t)value;
    txq_head = next;
}

/* Deliver the MCU's bytes whose stop bit ended by now. With --pipe: "tx END HEX" per run of
 * back-to-back bytes, END the cycle the first one's stop bit ends (the next ones follow at
 * one byte time each). */
static void tx_flush(void)
{
    static uint8_t buf[TXQ_SIZE];
    size_t n = 0;
    avr_cycle_count_t prev = 0, bc = byte_cycles();
    while (txq_tail != txq_head && txq[txq_tail].at <= avr->cycle) {
        avr_cycle_count_t at = txq[txq_tail].at;
        if (pipe_mode) {
            if (n == 0 || at > prev + bc + bc / 2) { /* a gap: a new run */
                if (n)
                    emit("\n");
                emit("tx %" PRIu64 " %" PRIu64 " ", (uint64_t)at, (uint64_t)bc);
            }
            emit("%02x", txq[txq_tail].b);
            prev = at;
            n++;
        } else {
            buf[n++] = txq[txq_tail].b;
        }
        txq_tail = (txq_tail + 1) % TXQ_SIZE;
    }
    if (!n)
        return;
    if (pipe_mode) {
        emit("\n");
        tx_total += n;
        return;
    }
    size_t off = 0;
    while (off < n) {
        ssize_t w = write(pty_master, buf + off, n - off);
        if (w < 0) {
            if (errno == EINTR)
                continue;
            tx_lost += n - off; /* nobody reading, buffer full: a UART's bytes are lost */
            break;
        }
        off += (size_t)w;
        tx_total += (uint64_t)w;
    }
}

static void pty_read(void)
{
    uint8_t buf[4096];
    for (;;) {
        ssize_t r = read(pty_master, buf, sizeof buf);
        if (r <= 0)
            return;
        host_rx_total += (uint64_t)r;
        host_bytes(buf, (size_t)r);
    }
}

/* Wait (bounded) until the host's bytes up to `total` have come through the pty. */
static int pty_sync(uint64_t total)
{
    struct timespec t0;
    clock_gettime(CLOCK_MONOTONIC, &t0);
    while (host_rx_total < total) {
        struct pollfd p = {.fd = pty_master, .events = POLLIN};
        poll(&p, 1, 100);
        pty_read();
        struct timespec t1;
        clock_gettime(CLOCK_MONOTONIC, &t1);
        if (t1.tv_sec - t0.tv_sec > 5)
            return -1;
    }
    return 0;
}

/* ------------------------------------------------------------------ resets */

static unsigned resets;
static int reset_seen;

static void arm_timers(void)
{
    avr_cycle_timer_register(avr, pwm_period, sampler, NULL);
    for (int i = 0; i < N_CH; i++)
        enc_schedule(&ch[i]);
    feed_schedule();
}

/* The core's reset runs inside avr_reset(), which has just cleared every cycle timer. */
static void on_reset(struct avr_t *a)
{
    core_reset(a);
    resets++;
    reset_seen = 1;
    /* the reset cleared PINC, PIND: the encoders' lines, the estop input, the battery stay */
    for (int i = 0; i < N_CH; i++)
        enc_restore_pins(a, &ch[i]);
    apply_estop(a);
    apply_battery();
    arm_timers();
}

/* The firmware clears MCUSR first thing after a reset: that write tells the cause. */
static void mcusr_write(struct avr_t *a, avr_io_addr_t addr, uint8_t v, void *param)
{
    (void)param;
    uint8_t cause = a->data[addr];
    if (cause)
        emit("rst %" PRIu64 " %u\n", (uint64_t)a->cycle, cause);
    a->data[addr] = v;
}

static void no_sleep(struct avr_t *a, avr_cycle_count_t how_long)
{
    (void)a;
    (void)how_long; /* simulated time only: a sleeping CPU skips to its next event */
}

/* ------------------------------------------------------------------ running */

static int stop_hit;

/* simavr polls a low INT0/INT1 pin every cycle in level mode (the reset default) and keeps
 * raising the interrupt while it stays low, whatever mode the firmware sets later: that
 * would both slow the simulation and feed the firmware interrupts a real pin never gives.
 * Its extint reset turns the polling back on, so this follows every reset. */
static void no_level_polling(void)
{
    avr_extint_set_strict_lvl_trig(avr, 0, 0);
    avr_extint_set_strict_lvl_trig(avr, 1, 0);
}

static avr_cycle_count_t stop_timer(struct avr_t *a, avr_cycle_count_t when, void *param)
{
    (void)a;
    (void)when;
    (void)param;
    stop_hit = 1;
    return 0;
}

static void run_until(avr_cycle_count_t target)
{
    if (target <= avr->cycle)
        return;
    stop_hit = 0;
    avr_cycle_timer_register(avr, target - avr->cycle, stop_timer, NULL);
    while (!stop_hit) {
        if (avr->state == cpu_Crashed || avr->state == cpu_Done) {
            avr->cycle = target; /* a dead CPU: time still passes for everyone else */
            avr_cycle_timer_cancel(avr, stop_timer, NULL);
            break;
        }
        avr_run(avr);
        if (reset_seen) {
            reset_seen = 0;
            no_level_polling();
            if (!stop_hit && !avr_cycle_timer_status(avr, stop_timer, NULL) && target > avr->cycle)
                avr_cycle_timer_register(avr, target - avr->cycle, stop_timer, NULL);
        }
    }
    tx_flush();
}

static const char *state_name(void)
{
    switch (avr->state) {
    case cpu_Running: return "running";
    case cpu_Sleeping: return "sleeping";
    case cpu_Crashed: return "crashed";
    case cpu_Done: return "done";
    default: return "other";
    }
}

static void report(void)
{
    double d[2];
    sample_outputs(d);
    double ml = drive_n ? drive_sum[0] / (double)drive_n : d[0];
    double mr = drive_n ? drive_sum[1] / (double)drive_n : d[1];
    drive_sum[0] = drive_sum[1] = 0.0;
    drive_n = 0;
    emit("ok %" PRIu64 " %.6f %.6f %.6f %.6f %" PRId64 " %u %" PRIu64 " %s %" PRId64 " %" PRId64 "\n",
         (uint64_t)avr->cycle, d[0], d[1], ml, mr, ch[CH_FRONT].emitted, resets, tx_total,
         state_name(), ch[CH_LEFT].emitted, ch[CH_RIGHT].emitted);
}

static int hexval(int c)
{
    if (c >= '0' && c <= '9')
        return c - '0';
    if (c >= 'a' && c <= 'f')
        return c - 'a' + 10;
    if (c >= 'A' && c <= 'F')
        return c - 'A' + 10;
    return -1;
}

static int quit;

static void command(char *line)
{
    char *cmd = strtok(line, " \t\r\n");
    if (!cmd)
        return;
    if (!strcmp(cmd, "run")) {
        char *a = strtok(NULL, " \t\r\n"), *b = strtok(NULL, " \t\r\n"), *c = strtok(NULL, " \t\r\n");
        char *dl = strtok(NULL, " \t\r\n"), *dr = strtok(NULL, " \t\r\n"), *mv = strtok(NULL, " \t\r\n");
        if (!a || !b || (dl && !dr)) {
            emit("err run CYCLE DELTA [SYNC|- [DL DR [MV]]]\n");
            return;
        }
        avr_cycle_count_t target = strtoull(a, NULL, 10);
        long long delta[N_CH] = {strtoll(b, NULL, 10), dl ? strtoll(dl, NULL, 10) : 0,
                                 dr ? strtoll(dr, NULL, 10) : 0};
        if (c && strcmp(c, "-") && !pipe_mode && pty_sync(strtoull(c, NULL, 10)) < 0) {
            emit("err host bytes did not come through the pty\n");
            return;
        }
        if (!pipe_mode)
            pty_read();
        if (mv && (uint32_t)strtoul(mv, NULL, 10) != batt_mv) {
            batt_mv = (uint32_t)strtoul(mv, NULL, 10);
            apply_battery();
        }
        if (target > avr->cycle) /* DELTA counts more than the trajectory stands at now */
            for (int i = 0; i < N_CH; i++)
                if (delta[i] || i == CH_FRONT)
                    enc_segment(&ch[i], (double)target,
                                target_at(&ch[i], (double)avr->cycle) + (double)delta[i], 0.0);
        run_until(target);
        report();
    } else if (!strcmp(cmd, "enc")) {
        char *arg[6];
        int n = 0;
        while (n < 6 && (arg[n] = strtok(NULL, " \t\r\n")) != NULL)
            n++;
        if (n < 1 || (n > 2 && n != 6)) {
            emit("err enc COUNT [RATE [L LRATE R RRATE]]\n");
            return;
        }
        enc_head_for(&ch[CH_FRONT], strtod(arg[0], NULL), n > 1 ? strtod(arg[1], NULL) : 0.0);
        if (n == 6) {
            enc_head_for(&ch[CH_LEFT], strtod(arg[2], NULL), strtod(arg[3], NULL));
            enc_head_for(&ch[CH_RIGHT], strtod(arg[4], NULL), strtod(arg[5], NULL));
        }
        report(); /* as `out`: one round trip per plant update */
    } else if (!strcmp(cmd, "bat")) {
        char *a = strtok(NULL, " \t\r\n");
        if (!a) {
            emit("err bat MV\n");
            return;
        }
        batt_mv = (uint32_t)strtoul(a, NULL, 10);
        apply_battery();
        emit("ok %" PRIu64 "\n", (uint64_t)avr->cycle);
    } else if (!strcmp(cmd, "estop")) {
        char *a = strtok(NULL, " \t\r\n");
        if (!a) {
            emit("err estop 0|1\n");
            return;
        }
        estop_is_open = atoi(a) != 0;
        apply_estop(avr);
        emit("ok %" PRIu64 "\n", (uint64_t)avr->cycle);
    } else if (!strcmp(cmd, "out")) {
        report();
    } else if (!strcmp(cmd, "send")) {
        char *h = strtok(NULL, " \t\r\n");
        uint8_t buf[4096];
        size_t n = 0;
        for (; h && h[0] && h[1] && n < sizeof buf; h += 2) {
            int hi = hexval(h[0]), lo = hexval(h[1]);
            if (hi < 0 || lo < 0)
                break;
            buf[n++] = (uint8_t)(hi << 4 | lo);
        }
        avr_cycle_count_t done = host_bytes(buf, n);
        emit("ok %" PRIu64 "\n", (uint64_t)done);
    } else if (!strcmp(cmd, "reset")) {
        avr_reset(avr);
        reset_seen = 0;
        no_level_polling();
        avr->data[R_MCUSR] |= (1 << EXTRF_BIT);
        emit("ok %" PRIu64 "\n", (uint64_t)avr->cycle);
    } else if (!strcmp(cmd, "events")) {
        char *a = strtok(NULL, " \t\r\n");
        events_on = a && atoi(a);
        emit("ok %" PRIu64 "\n", (uint64_t)avr->cycle);
    } else if (!strcmp(cmd, "regs")) {
        emit("ok %" PRIu64 " tccr1a=%u tccr1b=%u icr1=%u ocr1a=%u ocr1b=%u portd=%u ddrd=%u portb=%u "
             "ddrb=%u pind=%u pinc=%u portc=%u ddrc=%u tx_lost=%" PRIu64 " host_rx=%" PRIu64 "\n",
             (uint64_t)avr->cycle, avr->data[R_TCCR1A], avr->data[R_TCCR1B], reg16(R_ICR1L),
             reg16(R_OCR1AL), reg16(R_OCR1BL), avr->data[R_PORTD], avr->data[R_DDRD],
             avr->data[R_PORTB], avr->data[R_DDRB], avr->data[R_PIND], avr->data[R_PINC],
             avr->data[R_PORTC], avr->data[R_DDRC], tx_lost, host_rx_total);
    } else if (!strcmp(cmd, "quit")) {
        quit = 1;
        emit("ok %" PRIu64 "\n", (uint64_t)avr->cycle);
    } else {
        emit("err unknown command %s\n", cmd);
    }
}

/* Lines from stdin, without blocking (paced) or one at a time (lockstep). */
static char inbuf[1 << 16];
static size_t inlen;

static int read_commands(void)
{
    ssize_t r = read(0, inbuf + inlen, sizeof inbuf - 1 - inlen);
    if (r == 0)
        return -1; /* EOF: the controller went away */
    if (r < 0)
        return errno == EAGAIN || errno == EINTR ? 0 : -1;
    inlen += (size_t)r;
    char *start = inbuf;
    char *nl;
    while ((nl = memchr(start, '\n', inlen - (size_t)(start - inbuf))) != NULL) {
        *nl = 0;
        command(start);
        start = nl + 1;
    }
    inlen -= (size_t)(start - inbuf);
    memmove(inbuf, start, inlen);
    flush_out();
    return 0;
}

static double mono_s(void)
{
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (double)t.tv_sec + t.tv_nsec * 1e-9;
}

static void loop_lockstep(void)
{
    while (!quit) {
        struct pollfd p = {.fd = 0, .events = POLLIN};
        if (poll(&p, 1, -1) < 0 && errno != EINTR)
            return;
        if (read_commands() < 0)
            return;
    }
}

static void loop_paced(void)
{
    double wall0 = mono_s();
    avr_cycle_count_t cyc0 = avr->cycle;
    const double f = avr->frequency;
    const avr_cycle_count_t chunk = (avr_cycle_count_t)(f / 2000.0); /* 0.5 ms */
    struct pollfd p[2] = {{.fd = 0, .events = POLLIN}, {.fd = pty_master, .events = POLLIN}};
    nfds_t n = pipe_mode ? 1 : 2;
    while (!quit) {
        avr_cycle_count_t target = cyc0 + (avr_cycle_count_t)((mono_s() - wall0) * f);
        int behind = target > avr->cycle + chunk;
        run_until(behind ? avr->cycle + chunk : target);
        flush_out();
        /* serve the host and the controller; idle up to 0.2 ms when on time */
        struct timespec wait = {0, behind ? 0 : 200000};
        if (ppoll(p, n, &wait, NULL) < 0 && errno != EINTR)
            return;
        if ((p[0].revents & (POLLIN | POLLHUP)) && read_commands() < 0)
            return;
        if (n > 1 && (p[1].revents & POLLIN))
            pty_read();
    }
}

int main(int argc, char **argv)
{
    static const struct option opts[] = {
        {"paced", no_argument, NULL, 'p'}, {"pipe", no_argument, NULL, 'P'},
        {"driver", required_argument, NULL, 'd'}, {"freq", required_argument, NULL, 'f'},
        {"batt-full-mv", required_argument, NULL, 'b'}, {NULL, 0, NULL, 0}};
    uint32_t freq = 16000000;
    int o;
    while ((o = getopt_long(argc, argv, "", opts, NULL)) != -1) {
        switch (o) {
        case 'p': paced = 1; break;
        case 'P': pipe_mode = 1; break;
        case 'd': driver = !strcmp(optarg, "drv8871") ? DRIVER_DRV8871 : DRIVER_DIR2; break;
        case 'f': freq = (uint32_t)strtoul(optarg, NULL, 10); break;
        case 'b': batt_full_mv = strtod(optarg, NULL); break;
        default: fprintf(stderr, "usage: %s [--paced] [--pipe] [--driver dir2|drv8871] [--freq HZ] [--batt-full-mv MV] FIRMWARE.elf\n", argv[0]); return 2;
        }
    }
    if (optind != argc - 1) {
        fprintf(stderr, "usage: %s [--paced] [--pipe] [--driver dir2|drv8871] [--freq HZ] [--batt-full-mv MV] FIRMWARE.elf\n", argv[0]);
        return 2;
    }
    signal(SIGPIPE, SIG_IGN);

    elf_firmware_t fw;
    memset(&fw, 0, sizeof fw);
    if (elf_read_firmware(argv[optind], &fw) != 0) {
        fprintf(stderr, "ddrt-simavr: cannot read %s\n", argv[optind]);
        return 1;
    }
    avr = avr_make_mcu_by_name("atmega328p");
    if (!avr) {
        fprintf(stderr, "ddrt-simavr: simavr has no atmega328p core\n");
        return 1;
    }
    avr_init(avr);
    avr->log = 0;
    avr_load_firmware(avr, &fw);
    avr->frequency = freq;
    avr->sleep = no_sleep;
    pwm_period = freq / 20000; /* sample once per PWM period of the firmware (20 kHz) */

    uint32_t flags = 0; /* no console echo of UART lines, no polling sleeps */
    avr_ioctl(avr, AVR_IOCTL_UART_SET_FLAGS('0'), &flags);
    uart_in = avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_INPUT);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUTPUT), uart_out, NULL);
    enc_init(&ch[CH_FRONT], 'D', R_PIND, ENC_A_PIN);
    enc_init(&ch[CH_LEFT], 'C', R_PINC, WHL_A_PIN);
    enc_init(&ch[CH_RIGHT], 'C', R_PINC, WHR_A_PIN);
    adc0 = avr_io_getirq(avr, AVR_IOCTL_ADC_GETIRQ, ADC_IRQ_ADC0);
    estop_irq = avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('C'), ESTOP_PIN);
    avr_register_io_write(avr, R_MCUSR, mcusr_write, NULL);
    avr_register_io_write(avr, R_PORTC, port_write, NULL); /* after the ioport's own */
    avr_register_io_write(avr, R_PORTD, port_write, NULL);
    core_reset = avr->reset;
    avr->reset = on_reset;
    apply_battery();
    apply_estop(avr);
    no_level_polling(); /* before any pin moves: a low INT0/INT1 pin would start the polling */
    for (int i = 0; i < N_CH; i++)
        set_ab(&ch[i]);
    arm_timers();

    if (!pipe_mode) {
        if (openpty(&pty_master, &pty_slave, pty_name, NULL, NULL) < 0) {
            perror("ddrt-simavr: openpty");
            return 1;
        }
        struct termios t;
        tcgetattr(pty_slave, &t);
        cfmakeraw(&t); /* no echo, no line editing until the host opens it (it sets raw too) */
        tcsetattr(pty_slave, TCSANOW, &t);
        fcntl(pty_master, F_SETFL, fcntl(pty_master, F_GETFL) | O_NONBLOCK);
        /* the slave stays open here, so the host may close and reopen it */
    }
    if (paced)
        fcntl(0, F_SETFL, fcntl(0, F_GETFL) | O_NONBLOCK);
    emit("ready %s %" PRIu32 " %s\n", pipe_mode ? "-" : pty_name, freq, paced ? "paced" : "lockstep");
    flush_out();
    if (paced)
        loop_paced();
    else
        loop_lockstep();
    flush_out();
    return 0;
}
