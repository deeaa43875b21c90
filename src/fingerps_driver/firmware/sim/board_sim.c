/*
 * board_sim.c - runs the fingerps LED-board firmware in simavr, its UART0 on a
 * pseudo-terminal: the board_emulator's interface (a pty, --link PATH) with the real
 * firmware behind it.
 *
 *   board_sim [--link PATH] [--vcd FILE] [--mcu NAME] [--freq HZ] [FIRMWARE.elf|.hex]
 *
 * The firmware (default: the one `make firmware` built, BOARD_SIM_FIRMWARE) runs on a
 * simulated ATmega328P at 16 MHz. Bytes the host writes to the pty enter the UART's
 * receiver (simavr clocks them in at the line rate; its XOFF/XON irqs tell when its input
 * FIFO is full); bytes the firmware transmits are written to the pty. No flow control on
 * the pty itself, as on the real board.
 *
 * Time: simavr runs as fast as it can; this loop keeps simulated time from running ahead
 * of the wall clock (it sleeps when more than PACE_AHEAD_NS ahead), so the firmware's
 * timeouts and the UART's byte times are real time. The firmware's idle sleeps cost no
 * host CPU (simavr jumps to the next timer event; its own usleep-based pacing is
 * replaced by this one). If the host is too slow to keep up, simulated time falls behind;
 * a lag over MAX_LAG_NS is forgiven (the clock re-based) rather than caught up at full
 * speed, and the total is reported at exit.
 *
 * --vcd FILE traces the LED, trigger and status pins and the UART bytes (simavr's VCD
 * writer; the pin map is that of fingerps_board.c). simavr drives a pin from its port
 * register on every write to that register, also while a timer's compare output owns the
 * pin, so a trace of an LED at a level 1..254 shows such writes as glitches that the chip
 * does not make; levels 0 and 255 (plain port bits) trace exactly.
 *
 * Known differences between simavr 1.6 and the chip (none matters to the protocol): its
 * fast PWM is high for OCR counts, the chip's for OCR+1 (a traced level L shows a duty of
 * (L-1)/256, the chip's is L/256); its UART hands a transmitted byte to the pty when the
 * firmware writes it to UDR, one byte time before the chip's last stop bit, and counts a
 * parity bit that 8N1 does not send (a byte takes 11 bit times in, 10 on the wire).
 *
 * Signals: SIGINT/SIGTERM stop (the link is removed); SIGUSR1 resets the AVR (the reset
 * button). Exit status 0 after a stop, 1 on an error or a firmware crash.
 */

#define _GNU_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <getopt.h>
#include <poll.h>
#include <signal.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#include "avr_extint.h"
#include "avr_ioport.h"
#include "avr_uart.h"
#include "sim_avr.h"
#include "sim_elf.h"
#include "sim_hex.h"
#include "sim_irq.h"
#include "sim_time.h"
#include "sim_vcd_file.h"

#ifndef BOARD_SIM_FIRMWARE
#define BOARD_SIM_FIRMWARE "build/firmware/fingerps_board.elf"
#endif

#define PROG "board_sim"
#define PACE_AHEAD_NS 250000ull    /* simulated time may lead the wall clock by 0.25 ms */
#define MAX_LAG_NS 20000000ull     /* a lag beyond 20 ms is forgiven, not caught up */
#define SERVICE_NS 100000ull       /* the pty is served every 100 us of simulated time */
#define BUF_BYTES 4096u

typedef struct {
    uint8_t data[BUF_BYTES];
    size_t len;
} buffer_t;

typedef struct {
    avr_t *avr;
    int master, slave;
    char device[128];
    avr_irq_t *uart_in;     /* raise a byte here: it enters the UART's receiver */
    int uart_full;          /* the receiver's FIFO is full (XOFF) */
    buffer_t to_avr, to_host;
    unsigned long dropped_to_host;
} bridge_t;

static volatile sig_atomic_t stop_requested, reset_requested;

static void on_stop(int signum) { (void)signum; stop_requested = 1; }
static void on_reset(int signum) { (void)signum; reset_requested = 1; }

static uint64_t wall_ns(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (uint64_t)ts.tv_sec * 1000000000ull + (uint64_t)ts.tv_nsec;
}

/* simavr's own sleep callback usleeps towards real time on every idle sleep; pacing is
 * done in the main loop instead, in coarser steps. */
static void sleep_noop(avr_t *avr, avr_cycle_count_t how_long)
{
    (void)avr;
    (void)how_long;
}

/* A low INT0/INT1 pin in level-triggered mode (the reset default) makes simavr 1.6 poll
 * it every cycle, its interrupt enabled or not; no poll, INTn flags still raised. A reset
 * turns the polling on again (the firmware also makes INT0/INT1 edge-triggered). */
static void quiet_extint(avr_t *avr)
{
    avr_extint_set_strict_lvl_trig(avr, 0, 0);
    avr_extint_set_strict_lvl_trig(avr, 1, 0);
}

/* ---- UART <-> pty ---------------------------------------------------------------------- */

static void uart_output_hook(avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    bridge_t *b = param;
    if (b->to_host.len < BUF_BYTES)
        b->to_host.data[b->to_host.len++] = (uint8_t)value;
    else
        ++b->dropped_to_host; /* nobody reads the pty: bytes are lost, as on a wire */
}

static void uart_xoff_hook(avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    ((bridge_t *)param)->uart_full = value != 0;
}

static void uart_xon_hook(avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)value;
    ((bridge_t *)param)->uart_full = 0;
}

static void bridge_connect(bridge_t *b)
{
    avr_t *avr = b->avr;
    uint32_t flags = 0;
    avr_ioctl(avr, AVR_IOCTL_UART_GET_FLAGS('0'), &flags);
    flags &= ~(uint32_t)(AVR_UART_FLAG_STDIO | AVR_UART_FLAG_POLL_SLEEP);
    avr_ioctl(avr, AVR_IOCTL_UART_SET_FLAGS('0'), &flags);

    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUTPUT),
                            uart_output_hook, b);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUT_XOFF),
                            uart_xoff_hook, b);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUT_XON),
                            uart_xon_hook, b);
    b->uart_in = avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_INPUT);
    b->uart_full = 1; /* until the firmware enables its receiver (XON) */
}

static int pty_open(bridge_t *b)
{
    b->master = posix_openpt(O_RDWR | O_NOCTTY);
    if (b->master < 0 || grantpt(b->master) || unlockpt(b->master) ||
        ptsname_r(b->master, b->device, sizeof b->device)) {
        fprintf(stderr, PROG ": cannot create a pty: %s\n", strerror(errno));
        return -1;
    }
    /* Hold the slave side open: the pty then survives clients opening and closing it,
     * and the raw mode is set where the line discipline lives. */
    b->slave = open(b->device, O_RDWR | O_NOCTTY);
    struct termios tio;
    if (b->slave < 0 || tcgetattr(b->slave, &tio)) {
        fprintf(stderr, PROG ": cannot open %s: %s\n", b->device, strerror(errno));
        return -1;
    }
    cfmakeraw(&tio);
    cfsetspeed(&tio, B115200);
    tcsetattr(b->slave, TCSANOW, &tio);
    fcntl(b->master, F_SETFL, fcntl(b->master, F_GETFL) | O_NONBLOCK);
    return 0;
}

/* Move bytes pty -> UART receiver and firmware -> pty; never blocks. */
static void bridge_pump(bridge_t *b)
{
    if (b->to_avr.len < BUF_BYTES) {
        ssize_t n = read(b->master, b->to_avr.data + b->to_avr.len, BUF_BYTES - b->to_avr.len);
        if (n > 0)
            b->to_avr.len += (size_t)n;
    }
    size_t fed = 0;
    while (fed < b->to_avr.len && !b->uart_full)
        avr_raise_irq(b->uart_in, b->to_avr.data[fed++]);
    if (fed) {
        memmove(b->to_avr.data, b->to_avr.data + fed, b->to_avr.len - fed);
        b->to_avr.len -= fed;
    }
    if (b->to_host.len) {
        ssize_t n = write(b->master, b->to_host.data, b->to_host.len);
        if (n > 0) {
            memmove(b->to_host.data, b->to_host.data + n, b->to_host.len - (size_t)n);
            b->to_host.len -= (size_t)n;
        }
    }
}

/* ---- link ------------------------------------------------------------------------------ */

static int link_create(const char *path, const char *device)
{
    struct stat st;
    if (lstat(path, &st) == 0 && !S_ISLNK(st.st_mode)) {
        fprintf(stderr, PROG ": %s exists and is not a symlink; remove it or choose another "
                        "--link\n", path);
        return -1;
    }
    char tmp[4096];
    snprintf(tmp, sizeof tmp, "%s.%d.tmp", path, (int)getpid());
    unlink(tmp);
    if (symlink(device, tmp) || rename(tmp, path)) {
        fprintf(stderr, PROG ": cannot link %s to %s: %s\n", path, device, strerror(errno));
        unlink(tmp);
        return -1;
    }
    return 0;
}

static void link_remove(const char *path, const char *device)
{
    char target[256];
    ssize_t n = readlink(path, target, sizeof target - 1);
    if (n > 0) {
        target[n] = '\0';
        if (strcmp(target, device) == 0) /* still ours */
            unlink(path);
    }
}

/* ---- firmware and trace ------------------------------------------------------------------ */

static int load_firmware(avr_t *avr, const char *path)
{
    size_t len = strlen(path);
    if (len > 4 && strcmp(path + len - 4, ".hex") == 0) {
        ihex_chunk_p chunks = NULL;
        int count = read_ihex_chunks(path, &chunks);
        if (count <= 0) {
            fprintf(stderr, PROG ": cannot read %s\n", path);
            return -1;
        }
        for (int i = 0; i < count; ++i)
            if (chunks[i].baseaddr < (1u << 20)) /* flash; higher bases are EEPROM etc. */
                avr_loadcode(avr, chunks[i].data, chunks[i].size, chunks[i].baseaddr);
        free_ihex_chunks(chunks);
        return 0;
    }
    elf_firmware_t fw;
    memset(&fw, 0, sizeof fw);
    if (elf_read_firmware(path, &fw)) {
        fprintf(stderr, PROG ": cannot read %s (an .elf or .hex is expected)\n", path);
        return -1;
    }
    avr_load_firmware(avr, &fw);
    return 0;
}

/* The pins of fingerps_board.c's pin map. */
static const struct {
    char port;
    uint8_t bit;
    const char *name;
} traced_pins[] = {
    {'D', 6, "led0"}, {'D', 5, "led1"}, {'B', 1, "led2"}, {'B', 2, "led3"},
    {'B', 3, "led4"}, {'D', 3, "led5"}, {'B', 0, "led6"}, {'D', 4, "trig"},
    {'B', 5, "status"},
};

static int vcd_start(avr_t *avr, avr_vcd_t *vcd, const char *path)
{
    if (avr_vcd_init(avr, path, vcd, 200 /* us: flush before 6 PWM pins fill its FIFO */)) {
        fprintf(stderr, PROG ": cannot write %s\n", path);
        return -1;
    }
    for (size_t i = 0; i < sizeof traced_pins / sizeof traced_pins[0]; ++i)
        avr_vcd_add_signal(
            vcd, avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ(traced_pins[i].port),
                               traced_pins[i].bit),
            1, traced_pins[i].name);
    avr_vcd_add_signal(vcd, avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUTPUT),
                       8, "uart_tx");
    avr_vcd_add_signal(vcd, avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_INPUT),
                       8, "uart_rx");
    avr_vcd_start(vcd);
    return 0;
}

/* ---- main -------------------------------------------------------------------------------- */

static void usage(FILE *out)
{
    fprintf(out,
            "usage: " PROG " [--link PATH] [--vcd FILE] [--mcu NAME] [--freq HZ] "
            "[FIRMWARE.elf|.hex]\n"
            "Run the fingerps LED-board firmware in simavr with its UART0 on a pty.\n"
            "  --link PATH  symlink to the pty a client opens (removed at exit)\n"
            "  --vcd FILE   trace the LED, trigger and status pins and the UART bytes\n"
            "  --mcu NAME   simavr core (default atmega328p)\n"
            "  --freq HZ    clock (default 16000000)\n"
            "FIRMWARE defaults to %s. SIGUSR1 resets the AVR.\n",
            BOARD_SIM_FIRMWARE);
}

int main(int argc, char **argv)
{
    const char *link_path = NULL, *vcd_path = NULL, *mcu = "atmega328p";
    const char *firmware = BOARD_SIM_FIRMWARE;
    unsigned long freq = 16000000ul;
    static const struct option options[] = {
        {"link", required_argument, NULL, 'l'}, {"vcd", required_argument, NULL, 'v'},
        {"mcu", required_argument, NULL, 'm'},  {"freq", required_argument, NULL, 'f'},
        {"help", no_argument, NULL, 'h'},       {NULL, 0, NULL, 0},
    };
    for (int c; (c = getopt_long(argc, argv, "h", options, NULL)) != -1;) {
        switch (c) {
        case 'l': link_path = optarg; break;
        case 'v': vcd_path = optarg; break;
        case 'm': mcu = optarg; break;
        case 'f': freq = strtoul(optarg, NULL, 10); break;
        case 'h': usage(stdout); return 0;
        default: usage(stderr); return 1;
        }
    }
    if (optind + 1 == argc)
        firmware = argv[optind];
    else if (optind != argc || freq == 0) {
        usage(stderr);
        return 1;
    }

    avr_t *avr = avr_make_mcu_by_name(mcu);
    if (!avr) {
        fprintf(stderr, PROG ": simavr knows no core %s\n", mcu);
        return 1;
    }
    avr_init(avr);
    avr->log = LOG_WARNING;
    if (load_firmware(avr, firmware))
        return 1;
    avr->frequency = (uint32_t)freq;
    avr->sleep = sleep_noop;
    quiet_extint(avr);

    static bridge_t bridge;
    bridge.avr = avr;
    if (pty_open(&bridge))
        return 1;
    bridge_connect(&bridge);
    avr_vcd_t vcd;
    if (vcd_path && vcd_start(avr, &vcd, vcd_path))
        return 1;
    if (link_path && link_create(link_path, bridge.device))
        return 1;

    struct sigaction stop = {.sa_handler = on_stop}, reset = {.sa_handler = on_reset};
    sigaction(SIGINT, &stop, NULL);
    sigaction(SIGTERM, &stop, NULL);
    sigaction(SIGUSR1, &reset, NULL);

    printf(PROG ": %s (%s, %lu Hz) on %s%s%s; Ctrl-C to stop\n", firmware, mcu, freq,
           bridge.device, link_path ? ", link " : "", link_path ? link_path : "");
    fflush(stdout);

    const avr_cycle_count_t service_cycles = freq * SERVICE_NS / 1000000000ull;
    avr_cycle_count_t next_service = 0;
    uint64_t start = wall_ns(), forgiven_ns = 0;
    int status = 0, state = cpu_Running;
    while (!stop_requested) {
        state = avr_run(avr);
        if (state == cpu_Done || state == cpu_Crashed) {
            fprintf(stderr, PROG ": the firmware %s at cycle %llu\n",
                    state == cpu_Done ? "stopped" : "crashed", (unsigned long long)avr->cycle);
            status = 1;
            break;
        }
        if (avr->cycle < next_service)
            continue;
        next_service = avr->cycle + service_cycles;
        if (reset_requested) {
            reset_requested = 0;
            fprintf(stderr, PROG ": reset\n");
            avr_reset(avr);
            quiet_extint(avr);
        }
        bridge_pump(&bridge);
        uint64_t sim = avr_cycles_to_nsec(avr, avr->cycle), wall = wall_ns() - start;
        if (sim > wall + PACE_AHEAD_NS) {
            uint64_t ahead = sim - wall;
            struct timespec ts = {(time_t)(ahead / 1000000000ull), (long)(ahead % 1000000000ull)};
            struct pollfd pfd = {.fd = bridge.master, .events = POLLIN};
            ppoll(&pfd, 1, &ts, NULL); /* input wakes us; it is taken at the next service */
        } else if (wall > sim + MAX_LAG_NS) {
            forgiven_ns += wall - sim;
            start += wall - sim;
        }
    }

    uint64_t wall = wall_ns() - start + forgiven_ns;
    fprintf(stderr,
            PROG ": stopped after %.3f s simulated in %.3f s (%.3f s of lag forgiven)%s\n",
            avr_cycles_to_nsec(avr, avr->cycle) / 1e9, wall / 1e9, forgiven_ns / 1e9,
            bridge.dropped_to_host ? ", output bytes lost: nobody read the pty" : "");
    if (vcd_path)
        avr_vcd_close(&vcd);
    if (link_path)
        link_remove(link_path, bridge.device);
    close(bridge.slave);
    close(bridge.master);
    return status;
}
