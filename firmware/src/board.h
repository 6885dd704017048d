/* board.h: the clock, the pin map and the build options of the ddrt bridge firmware.
 *
 * Target: ATmega328P at 16 MHz (Arduino Uno / Nano / Pro Mini 5 V). Every pin the firmware
 * touches is named here and nowhere else; docs/hardware.md has the wiring tables.
 *
 *   signal            AVR pin   Arduino   function
 *   UART RX           PD0       D0        RXD (from the host / USB bridge)
 *   UART TX           PD1       D1        TXD
 *   encoder A         PD2       D2        INT0, any edge
 *   encoder B         PD3       D3        INT1, any edge
 *   left  IN1         PD4       D4        direction (TB6612FNG AIN1 / L298N IN1)
 *   left  IN2         PD5       D5        direction (TB6612FNG AIN2 / L298N IN2 / DRV8871 IN2)
 *   right IN1         PD6       D6        direction (TB6612FNG BIN1 / L298N IN3)
 *   right IN2         PD7       D7        direction (TB6612FNG BIN2 / L298N IN4 / DRV8871 IN2)
 *   driver enable     PB0       D8        TB6612FNG STBY (high once the outputs are zero)
 *   left  PWM         PB1       D9        OC1A, Timer1 phase-correct PWM, 20 kHz
 *   right PWM         PB2       D10       OC1B, Timer1 phase-correct PWM, 20 kHz
 *   status LED        PB5       D13       on while an output is non-zero
 *   battery divider   PC0       A0        ADC0, internal 1.1 V reference (BATTERY=1)
 *   estop input       PC1       A1        pull-up; high = the estop loop is open (ESTOP=1)
 *   left wheel  A/B   PC2/PC3   A2/A3     PCINT10/11, any edge (WHEEL_CPR > 0)
 *   right wheel A/B   PC4/PC5   A4/A5     PCINT12/13, any edge (WHEEL_CPR > 0)
 *
 * Build options (make VAR=value):
 *   BAUD         UART speed, default 115200 (U2X mode; 250000, 500000, 1000000 are exact)
 *   STATE_HZ     STATE stream rate, default 250; must divide TICK_HZ (10000); a v2 STATE
 *                is 26 bytes on the wire: 250 Hz keeps a 115200 line 56 % busy
 *   ENCODER_CPR  front encoder counts/rev, default 8192; 0: no front encoder (count 0)
 *   WHEEL_CPR    drive-wheel encoder counts per wheel revolution, default 0 (not counted)
 *   BATTERY      1 (default): measure the supply on A0; 0: not measured (battery_mv 0)
 *   BATT_FULL_MV supply voltage (mV) that reads full scale (ADC 1024): the divider's
 *                1100 mV * (R1 + R2) / R2, default 20743 for 100k over 5.6k
 *   ESTOP        1 (default): the estop input on A1 is wired; 0: none
 *   DRIVER       DRIVER_DIR2 (default: PWM + IN1/IN2, TB6612FNG and L298N) or
 *                DRIVER_DRV8871 (PWM on IN1, direction on IN2, PWM inverted in reverse)
 *   DDRT_TEST_HANG  test builds only: a packet of type 0x7E hangs the main loop, so the
 *                hardware watchdog must reset the MCU (tests/test_mcu_conformance.py)
 */
#ifndef DDRT_BOARD_H
#define DDRT_BOARD_H

#ifndef F_CPU
#define F_CPU 16000000UL
#endif

#ifndef BAUD
#define BAUD 115200UL
#endif

/* The time base: Timer0 in CTC mode, prescaler 8 (0.5 us per count), 200 counts per tick. */
#define TICK_HZ 10000UL
#define TICK_US (1000000UL / TICK_HZ)
#define TIMER0_PRESCALE 8UL
#define TIMER0_TOP ((uint8_t)(F_CPU / TIMER0_PRESCALE / TICK_HZ - 1))

#ifndef STATE_HZ
#define STATE_HZ 250UL
#endif
#define STATE_TICKS (TICK_HZ / STATE_HZ)
#if (TICK_HZ % STATE_HZ) != 0
#error "STATE_HZ must divide TICK_HZ"
#endif

/* PWM: Timer1, mode 10 (phase-correct, TOP = ICR1), no prescaler: f = F_CPU / (2 * TOP). */
#define PWM_HZ 20000UL
#define PWM_TOP ((uint16_t)(F_CPU / (2UL * PWM_HZ)))

#ifndef ENCODER_CPR
#define ENCODER_CPR 8192UL
#endif
#ifndef WHEEL_CPR
#define WHEEL_CPR 0UL
#endif
#ifndef BATTERY
#define BATTERY 1
#endif
#ifndef BATT_FULL_MV
#define BATT_FULL_MV 20743UL
#endif
#ifndef ESTOP
#define ESTOP 1
#endif

/* Port C: the battery divider (ADC0), the estop input, the drive wheels' encoders. */
#define PC_PIN PINC
#define PC_PORT PORTC
#define PC_DDR DDRC
#define BATT_ADC_CH 0
#define ESTOP_BIT 1
#define WHL_A_BIT 2 /* left A, B = PC2, PC3; right A, B = PC4, PC5 */
#define WHR_A_BIT 4
#ifndef WHEEL_PULLUPS
#define WHEEL_PULLUPS 1 /* most gearmotor encoders (Hall, open collector) need them */
#endif

/* The AVR hardware watchdog: reset if the main loop stops feeding it for this long. */
#define HW_WATCHDOG_TIMEOUT WDTO_60MS

#define DRIVER_DIR2 1
#define DRIVER_DRV8871 2
#ifndef DRIVER
#define DRIVER DRIVER_DIR2
#endif

/* Encoder: A and B on PD2/PD3 (INT0/INT1). No pull-ups: the AMT112S has push-pull outputs;
 * an open-collector encoder needs external pull-ups (or build with ENCODER_PULLUPS=1). */
#define ENC_PIN PIND
#define ENC_PORT PORTD
#define ENC_A_BIT 2
#define ENC_B_BIT 3
#ifndef ENCODER_PULLUPS
#define ENCODER_PULLUPS 0
#endif

/* Direction pins, all on PORTD. */
#define DIR_PORT PORTD
#define DIR_DDR DDRD
#define L_IN1_BIT 4
#define L_IN2_BIT 5
#define R_IN1_BIT 6
#define R_IN2_BIT 7

/* PWM pins and the driver enable, on PORTB. */
#define PWM_DDR DDRB
#define PWM_PORT PORTB
#define PWM_L_BIT 1 /* OC1A */
#define PWM_R_BIT 2 /* OC1B */
#define STBY_BIT 0
#define LED_BIT 5

#endif
