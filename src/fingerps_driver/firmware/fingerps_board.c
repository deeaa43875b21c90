/*
 * fingerps_board.c - firmware of the fingerps LED board.
 *
 * Serves the wire protocol of fingerps_driver/board/board_protocol.py (read its module
 * docstring: framing "#seq,CMD,args*CRC\n", CRC-8/SMBUS, seq echo, PING INFO LEDS OFF
 * LEVEL STATE, errors CRC FRAME CMD ARG RANGE) and answers byte for byte as the Python
 * emulator (board/board_emulator.py) does, error texts included, plus one command of its
 * own, TRIG (camera trigger; below).
 *
 * Chip and boards: ATmega328P at 16 MHz, 5 V - Arduino Uno R3, Arduino Nano (ATmega328P),
 * Arduino Pro Mini 5 V/16 MHz and clones. Plain avr-gcc + avr-libc, no Arduino core; the
 * Arduino bootloader (if any) is left alone. Not the Uno R4 / Nano Every (other chips).
 *
 * Pin map (Arduino pin = AVR pin, function):
 *   LED 0  D6  = PD6  OC0A  hardware PWM (Timer0)
 *   LED 1  D5  = PD5  OC0B  hardware PWM (Timer0)
 *   LED 2  D9  = PB1  OC1A  hardware PWM (Timer1, 8-bit fast PWM)
 *   LED 3  D10 = PB2  OC1B  hardware PWM (Timer1)
 *   LED 4  D11 = PB3  OC2A  hardware PWM (Timer2)
 *   LED 5  D3  = PD3  OC2B  hardware PWM (Timer2)
 *   LED 6  D8  = PB0  GPIO  first-order sigma-delta at the PWM period (no 7th PWM unit)
 *   TRIG   D4  = PD4  camera trigger output, active high
 *   STATUS D13 = PB5  on-board "L" LED, lit while any LED is lit
 *   D0/D1 = PD0/PD1 the UART (USB serial on Uno/Nano); D2 (INT0) kept free for a camera
 *   strobe input. An LED output is high = LED on; every driver input needs a pull-down
 *   (10 k) so that the LEDs stay off while the chip is in reset (its pins float then).
 *
 * LED count: 7 by default (-DLED_COUNT=1..7). The 328P has six PWM units, so the six
 * hardware channels plus one sigma-delta output; the pins would allow up to 17 on/off
 * outputs (18 free I/O minus the trigger), far below the protocol's MAX_LEDS = 32.
 *
 * PWM: the three timers run (while a level needs them, below) at clk/1 with an 8-bit
 * period, in step: 16 MHz / 256 = 62.5 kHz (16 us). Level L in 1..254 is a duty of L/256, 255 is steadily on, 0 steadily off (the
 * output compare pin is then disconnected and the port bit drives the pin). Why 62.5 kHz:
 * an exposure of E seconds that starts at an arbitrary phase integrates the duty d with an
 * error of at most d(1-d)T/E of full brightness (T the period): for E >= 1 ms that is
 * <= 0.25 * 16 us / 1 ms = 0.4 %, one grey level of an 8-bit image - and none at all for
 * levels 0 and 255 or for an exposure started by TRIG (it starts at a fixed PWM phase).
 * 62.5 kHz is the fastest 8-bit PWM the chip makes. LED 6 is on or off for whole periods
 * (sigma-delta, duty L/256 on average): its error over any window is under one period, at
 * most 16 us / E = 1.6 % of full brightness for E >= 1 ms, none at 0/255 and repeatable
 * under TRIG (the modulator restarts at every switch).
 *
 * Switching: LEDS, OFF and LEVEL hand the new outputs to the Timer1 overflow interrupt,
 * which applies them at the start of a period (<= 16 us later; PORTB's LEDs then PORTD's,
 * 0.4 us apart); the reply is sent only after that, as the protocol asks. The timers run at clk/1 only while
 * they have work (a lit LED at a level 1..254, or a trigger pulse under way); otherwise
 * Timer1 ticks at clk/64 (1.024 ms) just to keep time and Timer0/2 stop, so an idle board
 * takes no 62.5 kHz interrupt (and a simulator idles with it). A switch from that state
 * ends the slow period at once (<= 4 us) and starts the fast timers with the new outputs.
 *
 * Camera trigger (this firmware's addition to the protocol):
 *   TRIG,<delay_us>,<width_us>  ->  OK
 *   delay and width 0..65535 (decimal, as every number); width 0 switches the trigger off
 *   (the power-up state: TRIG off, delay 0). From then on every acknowledged LEDS request
 *   (any mask, 00 included - an ambient frame) makes TRIG rise delay_us after the LEDs
 *   switched and stay high width_us. Both are rounded up to whole PWM periods of 16 us and
 *   counted from the period start at which the LEDs switched, so the edges come whole
 *   periods after the switch, without jitter (simavr, TRIG,100,50: LED pin -> TRIG rise
 *   114.1 us = 7 x 16 + 2.1 us, high 64.4 us = 4 x 16 us). A new LEDS restarts the pulse, OFF
 *   (and the host-silence switch-off) cancels it, a LEVEL leaves it alone; TRIG itself
 *   lights nothing. Errors as for
 *   LEVEL: ARG for a missing, unparsable or > 65535 number. The LEDs reply is sent right
 *   after the switch; it does not wait for the pulse.
 *
 * Safety: LEDs off at power-up and on any reset (pins are set low before anything else);
 * the watchdog (250 ms) resets a hung firmware; when no request line that gets a reply has
 * arrived for HOST_SILENCE_MS (2 s), every LED goes off (a crashed host must not leave an
 * LED burning; a host that keeps LEDs lit longer sends a PING or STATE now and then).
 * The LEVEL settings survive the switch-off; a reset restores 255.
 *
 * UART: 115200 8N1 with U2X (UBRR 16: 117647 baud, +2.1 %, as the Arduino core does),
 * interrupt driven with ring buffers in both directions.
 */

#include <avr/interrupt.h>
#include <avr/io.h>
#include <avr/pgmspace.h>
#include <avr/sleep.h>
#include <avr/wdt.h>
#include <stdbool.h>
#include <stdint.h>
#include <util/atomic.h>

#define FIRMWARE_NAME "fingerps-avr-0.1"

#ifndef LED_COUNT
#define LED_COUNT 7
#endif
#if LED_COUNT < 1 || LED_COUNT > 7
#error "LED_COUNT must be 1..7 on the ATmega328P"
#endif

#ifndef HOST_SILENCE_MS
#define HOST_SILENCE_MS 2000UL
#endif

#define MAX_LINE_BYTES 255u /* board_protocol.MAX_LINE_BYTES, sigil included */
#define MAX_LEVEL 255u
#define MAX_TRIG_US 65535UL
#define TICK_US 16u /* one PWM period */
#define SILENCE_TICKS (HOST_SILENCE_MS * 1000UL / TICK_US)
#define MSG_LIMIT 60u /* board_protocol.sanitize_text's limit */

/* ---- pins -------------------------------------------------------------------------- */

#define PB_LEDS (_BV(PB0) | _BV(PB1) | _BV(PB2) | _BV(PB3))
#define PD_LEDS (_BV(PD3) | _BV(PD5) | _BV(PD6))
#define TRIG_BIT _BV(PD4)
#define STATUS_BIT _BV(PB5)
#define SD_BIT _BV(PB0) /* LED 6 */

/* The six hardware channels, in LED order: which port bit, which COM bit. */
enum { TCCR0A_REG, TCCR1A_REG, TCCR2A_REG };
static const uint8_t hw_port_b[6] PROGMEM = {0, 0, _BV(PB1), _BV(PB2), _BV(PB3), 0};
static const uint8_t hw_port_d[6] PROGMEM = {_BV(PD6), _BV(PD5), 0, 0, 0, _BV(PD3)};
static const uint8_t hw_tccr[6] PROGMEM = {TCCR0A_REG, TCCR0A_REG, TCCR1A_REG,
                                           TCCR1A_REG, TCCR2A_REG, TCCR2A_REG};
static const uint8_t hw_com[6] PROGMEM = {_BV(COM0A1), _BV(COM0B1), _BV(COM1A1),
                                          _BV(COM1B1), _BV(COM2A1), _BV(COM2B1)};

#define TCCR0A_WGM (_BV(WGM01) | _BV(WGM00)) /* fast PWM, TOP 0xFF */
#define TCCR1A_WGM _BV(WGM10)                /* with WGM12: fast PWM 8-bit */
#define TCCR2A_WGM (_BV(WGM21) | _BV(WGM20))

/* ---- state shared with the Timer1 interrupt ------------------------------------------ */

/* Timer speeds. FAST: clk/1, a 16 us period, the PWM and the trigger's time base. SLOW:
 * Timer1 at clk/64 (1.024 ms) only counting time, Timer0/2 stopped; used while no lit LED
 * has a level of 1..254 and no trigger pulse is under way (then no compare output is
 * connected and nothing needs 16 us), so that the firmware idles instead of spending a
 * quarter of the CPU on 62 500 interrupts a second. */
#define T1_FAST (_BV(WGM12) | _BV(CS10))
#define T1_SLOW (_BV(WGM12) | _BV(CS11) | _BV(CS10))
#define SLOW_PERIOD_TICKS 64u /* a SLOW period in 16 us ticks */

typedef struct {
    uint8_t tccr[3];    /* TCCR0A, TCCR1A, TCCR2A */
    uint8_t ocr[6];     /* OCR0A, OCR0B, OCR1A, OCR1B, OCR2A, OCR2B */
    uint8_t portb;      /* LED and status bits of PORTB */
    uint8_t portd;      /* LED bits of PORTD */
    uint8_t sd_level;   /* LED 6 sigma-delta level, 0 = not modulated */
    uint8_t pwm;        /* 1: some lit LED needs the PWM (FAST timers) */
    uint8_t trigger;    /* TRIG_START, TRIG_CANCEL or TRIG_KEEP a pulse with this switch */
} outputs_t;

enum { TRIG_KEEP, TRIG_START, TRIG_CANCEL };

static volatile outputs_t next_outputs;
static volatile uint8_t switch_pending;
static volatile uint8_t fast;            /* the timers run FAST */
static volatile uint32_t ticks;          /* 16 us units since reset (+-1 ms per switch) */
static volatile uint16_t trig_delay_ticks;
static volatile uint16_t trig_width_ticks; /* 0: trigger off */

/* The interrupt's own state. */
static uint8_t pwm, sd_level, sd_acc;
static uint8_t trig_phase;              /* 0 idle, 1 waiting, 2 high */
static uint16_t trig_count;

static void timers_speed(bool to_fast)
{
    fast = to_fast;
    if (to_fast) {
        TCNT0 = 0; /* the first FAST period starts now, the three timers in step */
        TCNT1 = 0;
        TCNT2 = 0;
        TCCR1B = T1_FAST;
        TCCR0B = _BV(CS00);
        TCCR2B = _BV(CS20);
    } else {
        TCCR1B = T1_SLOW;
        TCCR0B = 0;
        TCCR2B = 0;
    }
}

/* Once a period: the time, a pending switch, LED 6's modulator, the trigger pulse. */
ISR(TIMER1_OVF_vect)
{
    ticks += fast ? 1u : SLOW_PERIOD_TICKS;
    if (switch_pending) {
        if (next_outputs.trigger != TRIG_KEEP) { /* LEDS starts a pulse, OFF cancels it */
            trig_phase = (next_outputs.trigger == TRIG_START && trig_width_ticks) ? 1 : 0;
            trig_count = trig_delay_ticks;
        }
        pwm = next_outputs.pwm;
        if (!fast && (pwm || trig_phase))
            timers_speed(true); /* the first fast period starts with the switch below */
        TCCR0A = next_outputs.tccr[0];
        TCCR1A = next_outputs.tccr[1];
        TCCR2A = next_outputs.tccr[2];
        if (pwm) { /* else no compare output is connected */
            OCR0A = next_outputs.ocr[0];
            OCR0B = next_outputs.ocr[1];
            OCR1A = next_outputs.ocr[2];
            OCR1B = next_outputs.ocr[3];
            OCR2A = next_outputs.ocr[4];
            OCR2B = next_outputs.ocr[5];
        }
        PORTB = (PORTB & (uint8_t)~(PB_LEDS | STATUS_BIT)) | next_outputs.portb;
        PORTD = (PORTD & (uint8_t)~(PD_LEDS | (trig_phase == 2 ? 0 : TRIG_BIT))) |
                next_outputs.portd; /* a LEVEL switch leaves a high trigger high */
        sd_level = next_outputs.sd_level;
        sd_acc = 128;
        switch_pending = 0;
    }
    if (sd_level) {
        uint8_t before = sd_acc;
        sd_acc += sd_level;
        if (sd_acc < before)
            PORTB |= SD_BIT;
        else
            PORTB &= (uint8_t)~SD_BIT;
    }
    if (trig_phase == 1) {
        if (trig_count == 0) {
            PORTD |= TRIG_BIT;
            trig_phase = 2;
            trig_count = trig_width_ticks;
        } else {
            --trig_count;
        }
    } else if (trig_phase == 2 && --trig_count == 0) {
        PORTD &= (uint8_t)~TRIG_BIT;
        trig_phase = 0;
    }
    if (fast && !pwm && !trig_phase)
        timers_speed(false);
}

/* ---- UART ----------------------------------------------------------------------------- */

#define RX_SIZE 128u
#define TX_SIZE 128u
static volatile uint8_t rx_buf[RX_SIZE], tx_buf[TX_SIZE];
static volatile uint8_t rx_head, rx_tail, tx_head, tx_tail;

ISR(USART_RX_vect)
{
    uint8_t byte = UDR0;
    uint8_t head = (uint8_t)((rx_head + 1u) % RX_SIZE);
    if (head != rx_tail) { /* else dropped: the line it belongs to fails its CRC */
        rx_buf[rx_head] = byte;
        rx_head = head;
    }
}

ISR(USART_UDRE_vect)
{
    if (tx_tail == tx_head) {
        UCSR0B &= (uint8_t)~_BV(UDRIE0);
        return;
    }
    UDR0 = tx_buf[tx_tail];
    tx_tail = (uint8_t)((tx_tail + 1u) % TX_SIZE);
}

/* Sleep until an interrupt unless `ready` says there is work; the watchdog is fed. */
static void idle_until_interrupt(volatile uint8_t *a, volatile uint8_t *b)
{
    cli();
    if (*a == *b) {
        sleep_enable();
        sei();
        sleep_cpu();
        sleep_disable();
    }
    sei();
    wdt_reset();
}

static void uart_put(uint8_t byte)
{
    uint8_t head = (uint8_t)((tx_head + 1u) % TX_SIZE);
    while (head == tx_tail) /* full: wait for the UDRE interrupt to take a byte */
        wdt_reset();
    tx_buf[tx_head] = byte;
    tx_head = head;
    UCSR0B |= _BV(UDRIE0);
}

static int16_t uart_get(void)
{
    if (rx_tail == rx_head)
        return -1;
    uint8_t byte = rx_buf[rx_tail];
    rx_tail = (uint8_t)((rx_tail + 1u) % RX_SIZE);
    return byte;
}

/* ---- CRC-8/SMBUS --------------------------------------------------------------------- */

static uint8_t crc8_update(uint8_t crc, uint8_t byte)
{
    crc ^= byte;
    for (uint8_t i = 0; i < 8; ++i)
        crc = (crc & 0x80) ? (uint8_t)((crc << 1) ^ 0x07) : (uint8_t)(crc << 1);
    return crc;
}

/* ---- reply --------------------------------------------------------------------------- */

static uint8_t reply_crc;

static void reply_char(char c)
{
    reply_crc = crc8_update(reply_crc, (uint8_t)c);
    uart_put((uint8_t)c);
}

/* A flash string, and a decimal number, into a sink (the reply or the error message). */
static void put_str_P(void (*put)(char), const char *s)
{
    for (char c; (c = (char)pgm_read_byte(s)) != '\0'; ++s)
        put(c);
}

static void put_uint(void (*put)(char), uint32_t value)
{
    char digits[10];
    uint8_t n = 0;
    do {
        digits[n++] = (char)('0' + value % 10u);
        value /= 10u;
    } while (value);
    while (n)
        put(digits[--n]);
}

static void reply_str_P(const char *s) { put_str_P(reply_char, s); }
static void reply_uint(uint32_t value) { put_uint(reply_char, value); }

static const char hex_digits[] PROGMEM = "0123456789ABCDEF";

/* board_protocol.format_mask: upper case, at least two digits. */
static void reply_mask(uint32_t mask)
{
    uint8_t n = 8;
    while (n > 2 && ((mask >> (4u * (n - 1u))) & 0xFu) == 0)
        --n;
    while (n) {
        --n;
        reply_char((char)pgm_read_byte(&hex_digits[(mask >> (4u * n)) & 0xFu]));
    }
}

static void reply_begin(uint8_t seq)
{
    uart_put('!');
    reply_crc = 0;
    reply_uint(seq);
    reply_str_P(PSTR(",OK"));
}

static void reply_end(void)
{
    uint8_t crc = reply_crc;
    uart_put('*');
    uart_put(pgm_read_byte(&hex_digits[crc >> 4]));
    uart_put(pgm_read_byte(&hex_digits[crc & 0xFu]));
    uart_put('\n');
}

/* ---- error text: what board_protocol.sanitize_text makes of the emulator's message --- */

static char msg[MSG_LIMIT];
static uint8_t msg_len;

static void msg_char(char c)
{
    if (msg_len >= MSG_LIMIT)
        return;
    if (c < 0x20 || c > 0x7E || c == ',' || c == '*' || c == '#' || c == '!')
        c = ' ';
    msg[msg_len++] = c;
}

static void msg_str_P(const char *s) { put_str_P(msg_char, s); }
static void msg_uint(uint32_t value) { put_uint(msg_char, value); }

static void msg_mask(uint32_t mask)
{
    uint8_t n = 8;
    while (n > 2 && ((mask >> (4u * (n - 1u))) & 0xFu) == 0)
        --n;
    while (n) {
        --n;
        msg_char((char)pgm_read_byte(&hex_digits[(mask >> (4u * n)) & 0xFu]));
    }
}

/* Python's repr() of ASCII bytes (with_b) or of an ASCII str: quote choice and escapes. */
static void msg_repr(const uint8_t *s, uint8_t len, bool with_b)
{
    bool single = false, dbl = false;
    for (uint8_t i = 0; i < len; ++i) {
        single |= s[i] == '\'';
        dbl |= s[i] == '"';
    }
    char quote = (single && !dbl) ? '"' : '\'';
    if (with_b)
        msg_char('b');
    msg_char(quote);
    for (uint8_t i = 0; i < len && msg_len < MSG_LIMIT; ++i) {
        uint8_t c = s[i];
        if (c == (uint8_t)quote || c == '\\') {
            msg_char('\\');
            msg_char((char)c);
        } else if (c == '\t') {
            msg_str_P(PSTR("\\t"));
        } else if (c == '\n') {
            msg_str_P(PSTR("\\n"));
        } else if (c == '\r') {
            msg_str_P(PSTR("\\r"));
        } else if (c < 0x20 || c >= 0x7F) {
            msg_str_P(PSTR("\\x"));
            msg_char("0123456789abcdef"[c >> 4]);
            msg_char("0123456789abcdef"[c & 0xFu]);
        } else {
            msg_char((char)c);
        }
    }
    msg_char(quote);
}

static void reply_error(uint8_t seq, const char *code_P)
{
    uart_put('!');
    reply_crc = 0;
    reply_uint(seq);
    reply_str_P(PSTR(",ERR,"));
    reply_str_P(code_P);
    reply_char(',');
    if (msg_len == 0)
        reply_char('-');
    for (uint8_t i = 0; i < msg_len; ++i)
        reply_char(msg[i]);
    reply_end();
}

static const char ERR_CRC[] PROGMEM = "CRC";
static const char ERR_FRAME[] PROGMEM = "FRAME";
static const char ERR_CMD[] PROGMEM = "CMD";
static const char ERR_ARG[] PROGMEM = "ARG";
static const char ERR_RANGE[] PROGMEM = "RANGE";

/* ---- LEDs ----------------------------------------------------------------------------- */

static uint8_t lit_mask;
static uint8_t levels[LED_COUNT];

/* Hand mask and levels to the interrupt and wait until it has switched the pins. */
static void apply_outputs(uint8_t trigger)
{
    outputs_t out = {
        .tccr = {TCCR0A_WGM, TCCR1A_WGM, TCCR2A_WGM},
        .ocr = {0},
        .portb = lit_mask ? STATUS_BIT : 0,
        .portd = 0,
        .sd_level = 0,
        .pwm = 0,
        .trigger = trigger,
    };
    for (uint8_t i = 0; i < LED_COUNT && i < 6; ++i) {
        if (!(lit_mask & (1u << i)) || levels[i] == 0)
            continue;
        if (levels[i] == MAX_LEVEL) {
            out.portb |= pgm_read_byte(&hw_port_b[i]);
            out.portd |= pgm_read_byte(&hw_port_d[i]);
        } else {
            out.tccr[pgm_read_byte(&hw_tccr[i])] |= pgm_read_byte(&hw_com[i]);
            out.ocr[i] = (uint8_t)(levels[i] - 1u); /* duty (OCR+1)/256 = level/256 */
            out.pwm = 1;
        }
    }
#if LED_COUNT > 6
    if ((lit_mask & 0x40u) && levels[6] == MAX_LEVEL)
        out.portb |= SD_BIT;
    else if ((lit_mask & 0x40u) && levels[6] != 0)
        out.sd_level = levels[6], out.pwm = 1;
#endif
    while (switch_pending) /* a previous switch not applied yet */
        ;
    next_outputs = out;
    ATOMIC_BLOCK(ATOMIC_RESTORESTATE) {
        switch_pending = 1;
        if (!fast)
            TCNT1 = 0xFE; /* SLOW: TOP (0xFF, where the overflow interrupt comes) at the
                           * next clk/64 tick, <= 4 us. Not 0xFF: a counter written to TOP
                           * may skip that overflow (simavr 1.6 restarts the whole 1 ms
                           * period then). */
    }
    while (switch_pending)
        ; /* the watchdog resets us if Timer1 ever stopped */
}

/* ---- request parsing ------------------------------------------------------------------ */

static uint8_t line[MAX_LINE_BYTES];
static uint8_t line_len;
static bool in_line;

/* One field of the request: pointer into line and length. */
typedef struct {
    const uint8_t *p;
    uint8_t len;
} field_t;

#define MAX_FIELDS 4u /* command + at most 2 arguments; more is counted, not kept */

static bool is_digit(uint8_t c) { return c >= '0' && c <= '9'; }

static int8_t hex_value(uint8_t c)
{
    if (is_digit(c))
        return (int8_t)(c - '0');
    if (c >= 'a' && c <= 'f')
        return (int8_t)(c - 'a' + 10);
    if (c >= 'A' && c <= 'F')
        return (int8_t)(c - 'A' + 10);
    return -1;
}

static bool field_is(const field_t *f, const char *name_P)
{
    uint8_t i = 0;
    for (; i < f->len; ++i)
        if (pgm_read_byte(name_P + i) != f->p[i])
            return false;
    return pgm_read_byte(name_P + i) == '\0';
}

/* board_protocol.parse_uint: 1..10 digits, value <= maximum; else an ARG text in msg. */
static bool parse_uint(const field_t *f, uint32_t maximum, uint32_t *value)
{
    if (f->len < 1 || f->len > 10) {
        msg_str_P(PSTR("bad number "));
        msg_repr(f->p, f->len, false);
        return false;
    }
    for (uint8_t i = 0; i < f->len; ++i) {
        if (!is_digit(f->p[i])) {
            msg_str_P(PSTR("bad number "));
            msg_repr(f->p, f->len, false);
            return false;
        }
    }
    uint8_t start = 0; /* int(token) prints without leading zeros */
    while (start + 1u < f->len && f->p[start] == '0')
        ++start;
    uint32_t v = 0;
    bool over = (uint8_t)(f->len - start) > 9u; /* 10 significant digits exceed every maximum here */
    for (uint8_t i = start; i < f->len && !over; ++i) {
        v = v * 10u + (uint32_t)(f->p[i] - '0');
        over = v > maximum;
    }
    if (over) {
        for (uint8_t i = start; i < f->len; ++i)
            msg_char((char)f->p[i]);
        msg_str_P(PSTR(" exceeds "));
        msg_uint(maximum);
        return false;
    }
    *value = v;
    return true;
}

/* board_protocol.parse_mask: 1..8 hex digits. */
static bool parse_mask(const field_t *f, uint32_t *mask)
{
    uint32_t m = 0;
    bool ok = f->len >= 1 && f->len <= 8;
    for (uint8_t i = 0; ok && i < f->len; ++i) {
        int8_t d = hex_value(f->p[i]);
        ok = d >= 0;
        m = (m << 4) | (uint8_t)d;
    }
    if (!ok) {
        msg_str_P(PSTR("bad hex mask "));
        msg_repr(f->p, f->len, false);
        return false;
    }
    *mask = m;
    return true;
}

static bool check_arg_count(const field_t *cmd, uint8_t got, uint8_t wanted)
{
    if (got == wanted)
        return true;
    for (uint8_t i = 0; i < cmd->len; ++i)
        msg_char((char)cmd->p[i]);
    msg_str_P(PSTR(" takes "));
    msg_uint(wanted);
    msg_str_P(PSTR(" argument(s), got "));
    msg_uint(got);
    return false;
}

static uint32_t last_request_tick;

static uint32_t now_ticks(void)
{
    uint32_t t;
    ATOMIC_BLOCK(ATOMIC_RESTORESTATE) { t = ticks; }
    return t;
}

/* Execute a framed, checked request; reply. */
static void execute(uint8_t seq, const field_t *fields, uint8_t n_fields)
{
    const field_t *cmd = &fields[0];
    uint8_t n_args = (uint8_t)(n_fields - 1u);
    const char *code = ERR_ARG;

    if (field_is(cmd, PSTR("PING")) || field_is(cmd, PSTR("INFO")) ||
        field_is(cmd, PSTR("OFF")) || field_is(cmd, PSTR("STATE"))) {
        if (!check_arg_count(cmd, n_args, 0))
            goto error;
        if (field_is(cmd, PSTR("OFF"))) {
            lit_mask = 0;
            apply_outputs(TRIG_CANCEL); /* switched before the first byte of the reply */
        }
        reply_begin(seq);
        if (field_is(cmd, PSTR("INFO"))) {
            reply_str_P(PSTR("," FIRMWARE_NAME ","));
            reply_uint(LED_COUNT);
        } else if (field_is(cmd, PSTR("OFF"))) {
            reply_str_P(PSTR(",00"));
        } else if (field_is(cmd, PSTR("STATE"))) {
            reply_char(',');
            reply_mask(lit_mask);
            for (uint8_t i = 0; i < LED_COUNT; ++i) {
                reply_char(',');
                reply_uint(levels[i]);
            }
        }
        reply_end();
        return;
    }
    if (field_is(cmd, PSTR("LEDS"))) {
        uint32_t mask;
        if (!check_arg_count(cmd, n_args, 1) || !parse_mask(&fields[1], &mask))
            goto error;
        if (mask >> LED_COUNT) {
            code = ERR_RANGE;
            msg_str_P(PSTR("mask "));
            msg_mask(mask);
            msg_str_P(PSTR(" names LEDs beyond "));
            msg_uint(LED_COUNT - 1u);
            goto error;
        }
        lit_mask = (uint8_t)mask;
        apply_outputs(TRIG_START);
        reply_begin(seq);
        reply_char(',');
        reply_mask(lit_mask);
        reply_end();
        return;
    }
    if (field_is(cmd, PSTR("LEVEL"))) {
        uint32_t index, level;
        if (!check_arg_count(cmd, n_args, 2) || !parse_uint(&fields[1], MAX_LEVEL, &index) ||
            !parse_uint(&fields[2], MAX_LEVEL, &level))
            goto error;
        if (index >= LED_COUNT) {
            code = ERR_RANGE;
            msg_str_P(PSTR("LED "));
            msg_uint(index);
            msg_str_P(PSTR(" does not exist (0.."));
            msg_uint(LED_COUNT - 1u);
            msg_char(')');
            goto error;
        }
        levels[index] = (uint8_t)level;
        if (lit_mask & (1u << index))
            apply_outputs(TRIG_KEEP); /* a pulse under way goes on */
        reply_begin(seq);
        reply_end();
        return;
    }
    if (field_is(cmd, PSTR("TRIG"))) {
        uint32_t delay_us, width_us;
        if (!check_arg_count(cmd, n_args, 2) ||
            !parse_uint(&fields[1], MAX_TRIG_US, &delay_us) ||
            !parse_uint(&fields[2], MAX_TRIG_US, &width_us))
            goto error;
        ATOMIC_BLOCK(ATOMIC_RESTORESTATE) {
            trig_delay_ticks = (uint16_t)((delay_us + TICK_US - 1u) / TICK_US);
            trig_width_ticks = (uint16_t)((width_us + TICK_US - 1u) / TICK_US);
        }
        reply_begin(seq);
        reply_end();
        return;
    }
    code = ERR_CMD;
    msg_str_P(PSTR("unknown command "));
    msg_repr(cmd->p, cmd->len, false);
error:
    reply_error(seq, code);
}

/* The request in line[0..len) (sigil included, newline excluded): reply or stay silent,
 * exactly as board_protocol.decode_request and the emulator do. */
static void handle_line(uint8_t len)
{
    if (len && line[len - 1u] == '\r')
        --len;
    for (uint8_t i = 0; i < len; ++i)
        if (line[i] & 0x80u)
            return; /* not ASCII: no seq can be read, no reply */
    const uint8_t *text = line + 1;
    uint8_t text_len = (uint8_t)(len - 1u);
    int16_t star = -1;
    for (uint8_t i = 0; i < text_len; ++i)
        if (text[i] == '*')
            star = i;
    uint8_t body_len = star < 0 ? 0 : (uint8_t)star;

    /* seq: the body up to its first comma */
    uint8_t seq_len = 0;
    while (seq_len < body_len && text[seq_len] != ',')
        ++seq_len;
    int16_t seq = -1;
    if (seq_len >= 1 && seq_len <= 3) {
        uint16_t v = 0;
        uint8_t i = 0;
        for (; i < seq_len && is_digit(text[i]); ++i)
            v = (uint16_t)(v * 10u + (text[i] - '0'));
        if (i == seq_len && v < 256u)
            seq = (int16_t)v;
    }
    if (seq < 0)
        return; /* every error of a line without a readable seq goes unanswered */
    last_request_tick = now_ticks();
    msg_len = 0;

    uint8_t crc_len = (uint8_t)(text_len - body_len - 1u);
    const uint8_t *crc_text = text + body_len + 1;
    if (star < 0 || crc_len != 2 || hex_value(crc_text[0]) < 0 || hex_value(crc_text[1]) < 0) {
        msg_str_P(PSTR("no *<crc> at the end of "));
        msg_repr(line, len, true);
        reply_error((uint8_t)seq, ERR_FRAME);
        return;
    }
    uint8_t crc = 0;
    for (uint8_t i = 0; i < body_len; ++i)
        crc = crc8_update(crc, text[i]);
    if ((uint8_t)((hex_value(crc_text[0]) << 4) | hex_value(crc_text[1])) != crc) {
        msg_str_P(PSTR("checksum mismatch in "));
        msg_repr(line, len, true);
        reply_error((uint8_t)seq, ERR_CRC);
        return;
    }

    /* the fields after the seq */
    field_t fields[MAX_FIELDS];
    uint8_t n_fields = 0;
    for (uint8_t pos = seq_len; pos < body_len;) {
        uint8_t start = (uint8_t)(pos + 1u), end = start;
        while (end < body_len && text[end] != ',')
            ++end;
        field_t f = {text + start, (uint8_t)(end - start)};
        bool bad = f.len == 0;
        for (uint8_t i = 0; i < f.len && !bad; ++i)
            bad = f.p[i] < 0x20 || f.p[i] > 0x7E || f.p[i] == '*' || f.p[i] == '!';
        if (bad) {
            msg_str_P(PSTR("field "));
            msg_repr(f.p, f.len, false);
            msg_str_P(PSTR(" is empty or holds a character not allowed on the wire in "));
            msg_repr(line, len, true);
            reply_error((uint8_t)seq, ERR_FRAME);
            return;
        }
        if (n_fields < MAX_FIELDS)
            fields[n_fields] = f;
        ++n_fields;
        pos = end;
    }
    if (n_fields == 0) {
        msg_str_P(PSTR("request without a command"));
        reply_error((uint8_t)seq, ERR_FRAME);
        return;
    }
    execute((uint8_t)seq, fields, n_fields);
}

/* board_protocol.LineFramer for one byte. */
static void framer_feed(uint8_t byte)
{
    if (byte == '#') {
        line[0] = byte;
        line_len = 1;
        in_line = true;
    } else if (!in_line) {
        /* dropped: bytes before a sigil */
    } else if (byte == '\n') {
        in_line = false;
        handle_line(line_len);
    } else if (line_len >= MAX_LINE_BYTES) {
        in_line = false; /* overlong: dropped, up to the next sigil */
    } else {
        line[line_len++] = byte;
    }
}

/* ---- start-up ------------------------------------------------------------------------- */

/* Before main and before .data is set up: the watchdog stays enabled after a watchdog
 * reset (with its shortest timeout), so stop it first; then every output low. */
void early_init(void) __attribute__((naked, used, section(".init3")));
void early_init(void)
{
    MCUSR = 0;
    wdt_disable();
    /* INT0/INT1 (PD2, PD3 = LED 5) edge- instead of level-triggered; their interrupts stay
     * disabled, so the chip does not care, but simavr 1.6 polls a low INT pin every cycle
     * in the default low-level mode, interrupt enabled or not (100x slower simulation). */
    EICRA = _BV(ISC11) | _BV(ISC10) | _BV(ISC01) | _BV(ISC00);
    PORTB = 0;
    PORTD = 0;
    DDRB = PB_LEDS | STATUS_BIT;
    DDRD = PD_LEDS | TRIG_BIT;
}

static void timers_init(void)
{
    TCCR0A = TCCR0A_WGM;
    TCCR1A = TCCR1A_WGM;
    TCCR2A = TCCR2A_WGM;
    timers_speed(false);
    TCNT1 = 0;
    TIMSK1 = _BV(TOIE1);
}

static void uart_init(void)
{
    UCSR0A = _BV(U2X0);
    UCSR0C = _BV(UCSZ01) | _BV(UCSZ00); /* 8N1 */
    UBRR0 = 16; /* 16 MHz / (8 * 17) = 117647 baud with U2X; written last because simavr
                 * takes the byte time from U2X and the frame format when UBRR is written */
    UCSR0B = _BV(RXEN0) | _BV(TXEN0) | _BV(RXCIE0);
}

int main(void)
{
    for (uint8_t i = 0; i < LED_COUNT; ++i)
        levels[i] = MAX_LEVEL;
    timers_init();
    uart_init();
    set_sleep_mode(SLEEP_MODE_IDLE);
    wdt_enable(WDTO_250MS);
    sei();
    apply_outputs(TRIG_CANCEL); /* all off, through the same path as every switch */
    last_request_tick = now_ticks();

    for (;;) {
        int16_t byte = uart_get();
        if (byte >= 0) {
            framer_feed((uint8_t)byte);
            wdt_reset();
            continue;
        }
        if (lit_mask && now_ticks() - last_request_tick >= SILENCE_TICKS) {
            lit_mask = 0; /* the host went silent: nothing may stay lit */
            apply_outputs(TRIG_CANCEL);
        }
        idle_until_interrupt(&rx_head, &rx_tail);
    }
}
