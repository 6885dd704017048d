/* main.c: the ddrt motor/encoder bridge, protocol v2 (docs/protocol.md), ATmega328P.
 *
 * Interrupts do the least:
 *   INT0/INT1      front quadrature: one table lookup on the new A/B state, count += -1/0/+1
 *   PCINT1         the drive wheels' quadrature (port C), the same for each wheel
 *   TIMER0_COMPA   10 kHz tick: the clock, the DRIVE watchdog, the estop input, the STATE
 *                  schedule
 *   USART_RX       byte into the RX ring
 *   USART_UDRE     byte out of the TX ring
 * The main loop decodes frames, acts on packets, filters the battery's ADC readings, builds
 * STATE frames, feeds the hardware watchdog, and sleeps (idle) until the next interrupt. No
 * dynamic memory.
 */
#include <avr/interrupt.h>
#include <avr/io.h>
#include <avr/sleep.h>
#include <avr/wdt.h>
#include <stdint.h>
#include <util/atomic.h>

#include "board.h"
#include "proto.h"

/* ---------------------------------------------------------------- encoder */

/* index = previous state << 2 | new state, state = A | B << 1. Counting up, (A, B) runs
 * 00 -> 10 -> 11 -> 01 -> 00 (A leads B): states 0 -> 1 -> 3 -> 2 -> 0. Two bits changing
 * at once (a missed edge) count nothing. */
static const int8_t enc_table[16] = {
    /* from 0 */ 0, +1, -1, 0,
    /* from 1 */ -1, 0, 0, +1,
    /* from 2 */ +1, 0, 0, -1,
    /* from 3 */ 0, -1, +1, 0,
};
/* The edge ISR touches two bytes only (a short ISR is what keeps up with fast edges): the
 * previous state, and a signed 8-bit sum the tick folds into the 32-bit count every 100 us
 * (it overflows only past 1.27 million counts/s). */
static uint8_t enc_prev4; /* previous state << 2 */
static volatile int8_t enc_acc;
static int32_t enc_count; /* the tick ISR's own */

static inline uint8_t enc_read_state(void)
{
    return (uint8_t)((ENC_PIN >> ENC_A_BIT) & 0x03u); /* A = bit 0, B = bit 1 (A and B adjacent) */
}

ISR(INT0_vect)
{
    uint8_t s = enc_read_state();
    uint8_t idx = (uint8_t)(enc_prev4 | s);
    enc_prev4 = (uint8_t)(s << 2);
    enc_acc += enc_table[idx];
}
ISR_ALIAS(INT1_vect, INT0_vect);

#if WHEEL_CPR > 0
/* The drive wheels: both on port C's pin-change interrupt; each wheel as the front one. */
static uint8_t whl_prev4, whr_prev4;
static volatile int8_t whl_acc, whr_acc;
static int32_t whl_count, whr_count; /* the tick ISR's own */

ISR(PCINT1_vect)
{
    uint8_t pins = PC_PIN;
    uint8_t l = (uint8_t)((pins >> WHL_A_BIT) & 0x03u);
    uint8_t r = (uint8_t)((pins >> WHR_A_BIT) & 0x03u);
    whl_acc += enc_table[whl_prev4 | l];
    whl_prev4 = (uint8_t)(l << 2);
    whr_acc += enc_table[whr_prev4 | r];
    whr_prev4 = (uint8_t)(r << 2);
}
#endif

/* ---------------------------------------------------------------- estop input, battery */

#if ESTOP
/* A normally-closed loop to GND holds the pin low; pressed (or a cut wire) the pull-up
 * takes it high: open is the safe reading. */
static inline uint8_t estop_open(void) { return (uint8_t)((PC_PIN >> ESTOP_BIT) & 1u); }
#else
static inline uint8_t estop_open(void) { return 0; }
#endif

#if BATTERY
#if BATT_FULL_MV > 65535UL
#error "BATT_FULL_MV must be at most 65535 (battery_mv is a u16)"
#endif
/* 64 x the ADC reading, low-passed in the main loop (time constant 64 conversions, about
 * 10 ms); the first conversions after the reference switches on are skipped. */
static uint16_t batt_acc;
static uint8_t batt_skip = 4;

static void battery_init(void)
{
    ADMUX = (uint8_t)((1u << REFS1) | (1u << REFS0) | BATT_ADC_CH); /* internal 1.1 V */
    DIDR0 = (uint8_t)(1u << ADC0D);
    ADCSRA = (uint8_t)((1u << ADEN) | (1u << ADSC) | (1u << ADPS2) | (1u << ADPS1) | (1u << ADPS0));
}

static void battery_poll(void)
{
    if (ADCSRA & (1u << ADSC))
        return; /* converting */
    uint16_t v = ADC;
    ADCSRA |= (uint8_t)(1u << ADSC);
    if (batt_skip) {
        if (--batt_skip == 0)
            batt_acc = (uint16_t)(v << 6);
        return;
    }
    batt_acc = (uint16_t)(batt_acc - (batt_acc >> 6) + v);
}

static uint16_t battery_mv(void)
{
    return (uint16_t)(((uint32_t)batt_acc * BATT_FULL_MV) >> 16); /* acc / 64 / 1024 * full */
}
#endif

/* ---------------------------------------------------------------- outputs */

static volatile int16_t out_l, out_r; /* the applied duties, -10000..10000 */

/* What the output registers get for one pair of duties; computed outside any critical
 * section (the divisions are slow), written inside one. */
typedef struct {
    uint16_t ocr_l, ocr_r;
    uint8_t tccr1a;
    uint8_t dir;
    int16_t l, r;
} outputs_t;

#define DIR_MASK ((1u << L_IN1_BIT) | (1u << L_IN2_BIT) | (1u << R_IN1_BIT) | (1u << R_IN2_BIT))

static uint16_t duty_to_ocr(int16_t duty)
{
    uint16_t mag = (uint16_t)(duty < 0 ? -duty : duty);
    /* round(mag * PWM_TOP / 10000); PWM_TOP = 400: round(mag / 25) */
    return (uint16_t)(((uint32_t)mag * PWM_TOP + PROTO_DUTY_FULL / 2) / PROTO_DUTY_FULL);
}

#if DRIVER == DRIVER_DIR2
/* TB6612FNG / L298N: PWM on the enable input (PWMA/ENA), IN1/IN2 the direction. */
static uint8_t dir_bits(int16_t duty, uint8_t in1, uint8_t in2)
{
    if (duty > 0)
        return (uint8_t)(1u << in1);
    if (duty < 0)
        return (uint8_t)(1u << in2);
    return 0;
}
#define COM_INVERT(duty) 0u
#elif DRIVER == DRIVER_DRV8871
/* DRV8871: the PWM pin drives IN1, the direction pin IN2. Forward: IN2 low, IN1 = PWM
 * (drive / coast). Reverse: IN2 high, IN1 = inverted PWM (drive / brake). */
static uint8_t dir_bits(int16_t duty, uint8_t in1, uint8_t in2)
{
    (void)in1;
    return duty < 0 ? (uint8_t)(1u << in2) : 0;
}
#define COM_INVERT(duty) ((duty) < 0)
#else
#error "unknown DRIVER"
#endif

static void outputs_compute(int16_t l, int16_t r, outputs_t *o)
{
    /* A zero output disconnects its compare unit: the pin falls to its PORT bit (low) at
     * once instead of at the next TOP, when the double-buffered OCR1x would take effect. */
    uint8_t a = 0;
    if (l)
        a |= (uint8_t)((1u << COM1A1) | (COM_INVERT(l) ? (1u << COM1A0) : 0u));
    if (r)
        a |= (uint8_t)((1u << COM1B1) | (COM_INVERT(r) ? (1u << COM1B0) : 0u));
    o->tccr1a = (uint8_t)(a | (1u << WGM11));
    o->dir = (uint8_t)(dir_bits(l, L_IN1_BIT, L_IN2_BIT) | dir_bits(r, R_IN1_BIT, R_IN2_BIT));
    o->ocr_l = l ? duty_to_ocr(l) : 0;
    o->ocr_r = r ? duty_to_ocr(r) : 0;
    o->l = l;
    o->r = r;
}

/* Called with interrupts off (an ISR, or an ATOMIC_BLOCK): the tick ISR may zero the outputs
 * at any time, and 16-bit timer registers share one TEMP byte. */
static void outputs_write_locked(const outputs_t *o)
{
    OCR1A = o->ocr_l;
    OCR1B = o->ocr_r;
    TCCR1A = o->tccr1a;
    DIR_PORT = (uint8_t)((DIR_PORT & (uint8_t)~DIR_MASK) | o->dir);
    out_l = o->l;
    out_r = o->r;
    if (o->l || o->r)
        PWM_PORT |= (uint8_t)(1u << LED_BIT);
    else
        PWM_PORT &= (uint8_t)~(1u << LED_BIT);
}

static void outputs_zero_locked(void)
{
    TCCR1A = (uint8_t)(1u << WGM11); /* both compare units off: pins low now */
    DIR_PORT &= (uint8_t)~DIR_MASK;
    OCR1A = 0;
    OCR1B = 0;
    out_l = 0;
    out_r = 0;
    PWM_PORT &= (uint8_t)~(1u << LED_BIT);
}

static void outputs_init(void)
{
    DIR_PORT &= (uint8_t)~DIR_MASK;
    DIR_DDR |= DIR_MASK;
    PWM_PORT &= (uint8_t)~((1u << PWM_L_BIT) | (1u << PWM_R_BIT) | (1u << STBY_BIT) | (1u << LED_BIT));
    PWM_DDR |= (uint8_t)((1u << PWM_L_BIT) | (1u << PWM_R_BIT) | (1u << STBY_BIT) | (1u << LED_BIT));
    /* Timer1: mode 10 (phase-correct PWM, TOP = ICR1), clk/1: 16e6 / (2 * 400) = 20 kHz */
    ICR1 = PWM_TOP;
    TCNT1 = 0;
    outputs_zero_locked();
    TCCR1B = (uint8_t)((1u << WGM13) | (1u << CS10));
    PWM_PORT |= (uint8_t)(1u << STBY_BIT); /* outputs are zero: enable the driver */
}

/* ---------------------------------------------------------------- time base, watchdog */

static volatile uint32_t now_us;         /* microseconds since boot at the last tick, wraps */
static volatile uint8_t tick_alive;      /* changes every tick: the main loop feeds the wdt on it */
static volatile uint8_t drive_armed;     /* a DRIVE's timeout is running */
static volatile uint32_t drive_deadline; /* now_us at which the outputs go to zero */
static volatile uint8_t wd_tripped;      /* zeroed by the DRIVE watchdog since the last STATE */
static volatile uint8_t state_due;
static volatile uint8_t estop_seen;  /* the estop input was open at a tick since the last STATE */
static volatile uint32_t state_t_us; /* the STATE snapshot: time and counts taken together */
static volatile int32_t state_count;
#if WHEEL_CPR > 0
static volatile int32_t state_left, state_right;
#endif
static uint8_t state_phase;

/* Interrupts stay enabled in here (ISR_NOBLOCK), so an encoder edge never waits for the tick;
 * nothing else it shares with an ISR. Main's ATOMIC_BLOCKs keep it out while they change the
 * deadline or the outputs. */
ISR(TIMER0_COMPA_vect, ISR_NOBLOCK)
{
    cli();
    int8_t d = enc_acc;
    enc_acc = 0;
#if WHEEL_CPR > 0
    int8_t dl = whl_acc, dr = whr_acc;
    whl_acc = 0;
    whr_acc = 0;
#endif
    sei();
    enc_count += d;
#if WHEEL_CPR > 0
    whl_count += dl;
    whr_count += dr;
#endif
    uint32_t t = now_us + TICK_US;
    now_us = t;
    tick_alive++;
    if (drive_armed && (int32_t)(t - drive_deadline) >= 0) {
        drive_armed = 0;
        outputs_zero_locked();
        wd_tripped = 1;
    }
    if (estop_open()) {
        estop_seen = 1;
        if (drive_armed || out_l || out_r) {
            drive_armed = 0;
            outputs_zero_locked();
        }
    }
    if (++state_phase >= STATE_TICKS) {
        state_phase = 0;
        state_t_us = t;
        state_count = enc_count;
#if WHEEL_CPR > 0
        state_left = whl_count;
        state_right = whr_count;
#endif
        state_due = 1;
    }
}

static void timebase_init(void)
{
    TCCR0A = (uint8_t)(1u << WGM01); /* CTC, TOP = OCR0A */
    OCR0A = TIMER0_TOP;
    TCNT0 = 0;
    TIFR0 = (uint8_t)(1u << OCF0A);
    TIMSK0 = (uint8_t)(1u << OCIE0A);
    TCCR0B = (uint8_t)(1u << CS01); /* clk/8 */
}

/* ---------------------------------------------------------------- UART */

#define RX_SIZE 64u  /* powers of two */
#define TX_SIZE 128u
static volatile uint8_t rx_buf[RX_SIZE];
static volatile uint8_t rx_head, rx_tail; /* head: ISR, tail: main */
static volatile uint8_t rx_dropped;
static volatile uint8_t tx_buf[TX_SIZE];
static volatile uint8_t tx_head, tx_tail; /* head: main, tail: ISR */

ISR(USART_RX_vect)
{
    uint8_t b = UDR0;
    uint8_t h = rx_head;
    uint8_t n = (uint8_t)((h + 1u) & (RX_SIZE - 1u));
    if (n == rx_tail) {
        rx_dropped++; /* ring full: the byte is lost, its frame fails the CRC */
        return;
    }
    rx_buf[h] = b;
    rx_head = n;
}

ISR(USART_UDRE_vect)
{
    uint8_t t = tx_tail;
    if (t == tx_head) {
        UCSR0B &= (uint8_t)~(1u << UDRIE0);
        return;
    }
    UDR0 = tx_buf[t];
    tx_tail = (uint8_t)((t + 1u) & (TX_SIZE - 1u));
}

static void uart_init(void)
{
    UCSR0A = (uint8_t)(1u << U2X0);
    UBRR0 = (uint16_t)((F_CPU + 4UL * BAUD) / (8UL * BAUD) - 1UL);
    UCSR0C = (uint8_t)((1u << UCSZ01) | (1u << UCSZ00)); /* 8N1 */
    UCSR0B = (uint8_t)((1u << RXEN0) | (1u << TXEN0) | (1u << RXCIE0));
}

/* Queue a whole frame or nothing: a frame cut short would cost the host the next one too. */
static uint8_t tx_frame(const uint8_t *p, uint8_t n)
{
    uint8_t h = tx_head;
    uint8_t used = (uint8_t)((h - tx_tail) & (TX_SIZE - 1u));
    if ((uint8_t)(TX_SIZE - 1u - used) < n)
        return 0;
    for (uint8_t i = 0; i < n; i++) {
        tx_buf[h] = p[i];
        h = (uint8_t)((h + 1u) & (TX_SIZE - 1u));
    }
    tx_head = h;
    ATOMIC_BLOCK(ATOMIC_RESTORESTATE) { UCSR0B |= (uint8_t)(1u << UDRIE0); }
    return 1;
}

/* ---------------------------------------------------------------- protocol */

static proto_decoder_t dec;
static uint8_t tx_seq;
static uint8_t ack_seq;
static uint8_t bad_frame;
static uint16_t errors_seen;
static uint8_t hello_pending;
static uint8_t frame[PROTO_MAX_WIRE];

static uint8_t send_packet(uint8_t type, const uint8_t *payload, uint8_t n)
{
    uint8_t len = proto_encode_frame(type, tx_seq, payload, n, frame);
    if (!len || !tx_frame(frame, len))
        return 0; /* no room: not sent, and its seq not used */
    tx_seq++;
    return 1;
}

static void send_hello_reply(void)
{
    uint8_t p[PL_HELLO_REPLY];
    p[0] = PROTO_VERSION;
    proto_put_u32(&p[1], ENCODER_CPR);
    proto_put_u16(&p[5], (uint16_t)STATE_HZ);
    p[7] = (uint8_t)((BATTERY ? FEATURE_BATTERY : 0u) | (ESTOP ? FEATURE_HW_ESTOP : 0u) |
                     (WHEEL_CPR > 0 ? FEATURE_WHEELS : 0u));
    proto_put_u32(&p[8], WHEEL_CPR);
    if (send_packet(PT_HELLO_REPLY, p, sizeof p))
        hello_pending--;
}

static void send_state(void)
{
    uint32_t t;
    int32_t c, cl = 0, cr = 0;
    uint8_t flags;
    ATOMIC_BLOCK(ATOMIC_RESTORESTATE)
    {
        t = state_t_us;
        c = state_count;
#if WHEEL_CPR > 0
        cl = state_left;
        cr = state_right;
#endif
        state_due = 0;
        flags = wd_tripped ? FLAG_WATCHDOG : 0;
        if (out_l || out_r)
            flags |= FLAG_OUTPUTS_ON;
        if (estop_seen)
            flags |= FLAG_HW_ESTOP;
    }
    if (bad_frame)
        flags |= FLAG_BAD_FRAME;
    uint8_t p[PL_STATE];
    proto_put_u32(&p[0], t);
    proto_put_u32(&p[4], (uint32_t)c);
    p[8] = flags;
    p[9] = ack_seq;
#if BATTERY
    proto_put_u16(&p[10], battery_mv());
#else
    proto_put_u16(&p[10], 0);
#endif
    proto_put_u32(&p[12], (uint32_t)cl);
    proto_put_u32(&p[16], (uint32_t)cr);
    if (send_packet(PT_STATE, p, sizeof p)) {
        /* the flags went out: clear what they reported (a trip after the snapshot stays,
         * and so does the estop while its input is still open) */
        ATOMIC_BLOCK(ATOMIC_RESTORESTATE)
        {
            if (flags & FLAG_WATCHDOG)
                wd_tripped = 0;
            if (flags & FLAG_HW_ESTOP)
                estop_seen = estop_open();
        }
        bad_frame = 0;
    }
}

static void on_packet(void)
{
    const uint8_t type = dec.buf[0];
    const uint8_t seq = dec.buf[1];
    const uint8_t *payload = &dec.buf[2];
    switch (type) {
    case PT_HELLO:
        if (hello_pending < 4u)
            hello_pending++;
        break;
    case PT_DRIVE: {
        proto_drive_t d;
        if (!proto_parse_drive(payload, &d))
            break; /* out of range: ignored entirely, no ack, watchdog not re-armed */
        ack_seq = seq; /* acknowledged even while the estop input is open */
        outputs_t o;
        outputs_compute(d.duty_l, d.duty_r, &o);
        uint32_t span = (uint32_t)d.timeout_ms * 1000u + TICK_US; /* + a tick: never early */
        ATOMIC_BLOCK(ATOMIC_RESTORESTATE)
        {
            if (estop_open()) {
                estop_seen = 1; /* not applied: the outputs stay zero */
            } else {
                drive_deadline = now_us + span;
                drive_armed = 1;
                outputs_write_locked(&o);
            }
        }
        break;
    }
    case PT_STOP:
        ack_seq = seq;
        ATOMIC_BLOCK(ATOMIC_RESTORESTATE)
        {
            drive_armed = 0;
            outputs_zero_locked();
        }
        break;
#ifdef DDRT_TEST_HANG
    case 0x7Eu:
        /* test builds only: the main loop hangs (interrupts stay on, the tick keeps
         * running), so only the hardware watchdog can bring the MCU back */
        for (;;) {
        }
#endif
    default:
        break; /* unknown types and MCU->host types are ignored */
    }
}

/* ---------------------------------------------------------------- boot and main loop */

/* Runs before main, right after the reset vector: a watchdog reset leaves the watchdog on
 * at its shortest period, so it must go off before the C runtime's set-up. */
void early_init(void) __attribute__((naked, used, section(".init3")));
void early_init(void)
{
    MCUSR = 0;
    wdt_disable();
}

int main(void)
{
    outputs_init(); /* outputs zero first: the pins were inputs (high-Z) through reset */
#if ESTOP
    PC_PORT |= (uint8_t)(1u << ESTOP_BIT); /* pull-up: an unwired input reads open */
#endif
#if ENCODER_CPR > 0
    enc_prev4 = (uint8_t)(enc_read_state() << 2);
#if ENCODER_PULLUPS
    ENC_PORT |= (uint8_t)((1u << ENC_A_BIT) | (1u << ENC_B_BIT));
#endif
    EICRA = (uint8_t)((1u << ISC10) | (1u << ISC00)); /* INT0, INT1: any logical change */
    EIFR = (uint8_t)((1u << INTF0) | (1u << INTF1));
    EIMSK = (uint8_t)((1u << INT0) | (1u << INT1));
#endif
#if WHEEL_CPR > 0
#if WHEEL_PULLUPS
    PC_PORT |= (uint8_t)(0x0Fu << WHL_A_BIT);
#endif
    whl_prev4 = (uint8_t)(((PC_PIN >> WHL_A_BIT) & 0x03u) << 2);
    whr_prev4 = (uint8_t)(((PC_PIN >> WHR_A_BIT) & 0x03u) << 2);
    PCMSK1 = (uint8_t)((1u << PCINT10) | (1u << PCINT11) | (1u << PCINT12) | (1u << PCINT13));
    PCIFR = (uint8_t)(1u << PCIF1);
    PCICR = (uint8_t)(1u << PCIE1);
#endif
#if BATTERY
    battery_init();
#endif
    proto_decoder_init(&dec);
    uart_init();
    timebase_init();
    hello_pending = 1; /* the boot announcement */
    wdt_enable(HW_WATCHDOG_TIMEOUT);
    set_sleep_mode(SLEEP_MODE_IDLE);
    sei();

    uint8_t fed = tick_alive;
    for (;;) {
        /* the watchdog is fed here only, and only while the tick interrupt runs */
        uint8_t alive = tick_alive;
        if (alive != fed) {
            fed = alive;
            wdt_reset();
        }
        while (rx_tail != rx_head) {
            uint8_t t = rx_tail;
            uint8_t b = rx_buf[t];
            rx_tail = (uint8_t)((t + 1u) & (RX_SIZE - 1u));
            if (proto_decoder_feed(&dec, b))
                on_packet();
        }
        uint16_t errors = proto_decoder_errors(&dec);
        if (errors != errors_seen) {
            errors_seen = errors;
            bad_frame = 1;
        }
#if BATTERY
        battery_poll();
#endif
        if (hello_pending)
            send_hello_reply();
        if (state_due)
            send_state();

        cli();
        if (rx_tail == rx_head && !state_due) {
            sleep_enable();
            sei(); /* the instruction after sei runs before any interrupt: no lost wake-up */
            sleep_cpu();
            sleep_disable();
        }
        sei();
    }
}
