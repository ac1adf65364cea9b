/*
 * Runs the compiled firmware (build/asgp_bridge.elf) in simavr as an ATmega2560 at 16 MHz,
 * paced to real time, with:
 *   - UART0 on a pseudo-terminal (simavr's uart_pty): the host talks to it like a board;
 *   - the joystick on ADC0/ADC1, in millivolts, settable at run time from stdin:
 *       "joy <forward_mV> <turn_mV>"
 *   - the MCP4922 DAC decoded from the SPI bus (CS on PB0 = D53): every change of an output
 *     code is printed to stdout as "dac <A|B> <code> <sim_ms>".
 * Prints "pty <path>" once the UART is connected. Usage:
 *   asgp_simavr firmware.elf [forward_mV turn_mV]
 */
#include <errno.h>
#include <pthread.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include <unistd.h>

#include <simavr/avr_adc.h>
#include <simavr/avr_ioport.h>
#include <simavr/avr_spi.h>
#include <simavr/parts/uart_pty.h>
#include <simavr/sim_avr.h>
#include <simavr/sim_elf.h>

static uart_pty_t uart;
static avr_t *avr;
static volatile int joy_mv[2] = {2500, 2500};
static int applied_mv[2] = {-1, -1};
static volatile int running = 1;

static int cs_low = 0;
static int spi_bytes = 0;
static uint16_t spi_word = 0;
static int dac_code[2] = {-1, -1};

static double sim_ms(void) { return (double)avr->cycle * 1000.0 / (double)avr->frequency; }

static void cs_hook(struct avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    cs_low = value == 0;
    spi_bytes = 0;
    spi_word = 0;
}

static void spi_hook(struct avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    if (!cs_low) {
        return;
    }
    spi_word = (uint16_t)((spi_word << 8) | (value & 0xFF));
    if (++spi_bytes == 2) {
        int channel = (spi_word & 0x8000) ? 1 : 0;
        int code = spi_word & 0x0FFF;
        if (code != dac_code[channel]) {
            dac_code[channel] = code;
            printf("dac %c %d %.1f\n", channel ? 'B' : 'A', code, sim_ms());
            fflush(stdout);
        }
        spi_bytes = 0;
    }
}

static void *stdin_reader(void *arg)
{
    (void)arg;
    char line[128];
    while (fgets(line, sizeof(line), stdin)) {
        int f, t;
        if (sscanf(line, "joy %d %d", &f, &t) == 2) {
            joy_mv[0] = f;
            joy_mv[1] = t;
        } else if (strncmp(line, "quit", 4) == 0) {
            break;
        }
    }
    running = 0;
    return NULL;
}

static double wall_ms(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return ts.tv_sec * 1000.0 + ts.tv_nsec / 1e6;
}

int main(int argc, char **argv)
{
    elf_firmware_t fw;
    if (argc < 2) {
        fprintf(stderr, "usage: %s firmware.elf [forward_mV turn_mV]\n", argv[0]);
        return 2;
    }
    if (argc >= 4) {
        joy_mv[0] = atoi(argv[2]);
        joy_mv[1] = atoi(argv[3]);
    }
    memset(&fw, 0, sizeof(fw));
    if (elf_read_firmware(argv[1], &fw) != 0) {
        fprintf(stderr, "cannot read %s\n", argv[1]);
        return 1;
    }
    avr = avr_make_mcu_by_name("atmega2560");
    if (!avr) {
        fprintf(stderr, "simavr has no atmega2560 core\n");
        return 1;
    }
    avr_init(avr);
    avr->frequency = 16000000;
    avr_load_firmware(avr, &fw);
    avr->frequency = 16000000;
    avr->aref = avr->avcc = avr->vcc = 5000; /* mV: AVCC is the ADC reference */

    uart_pty_init(avr, &uart);
    uart_pty_connect(&uart, '0');
    printf("pty %s\n", uart.pty.slavename);
    fflush(stdout);

    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_SPI_GETIRQ(0), SPI_IRQ_OUTPUT),
                            spi_hook, NULL);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('B'), 0), cs_hook,
                            NULL);

    pthread_t reader;
    pthread_create(&reader, NULL, stdin_reader, NULL);

    double t0 = wall_ms();
    long iter = 0;
    while (running) {
        if (joy_mv[0] != applied_mv[0] || joy_mv[1] != applied_mv[1]) {
            applied_mv[0] = joy_mv[0];
            applied_mv[1] = joy_mv[1];
            avr_raise_irq(avr_io_getirq(avr, AVR_IOCTL_ADC_GETIRQ, ADC_IRQ_ADC0), applied_mv[0]);
            avr_raise_irq(avr_io_getirq(avr, AVR_IOCTL_ADC_GETIRQ, ADC_IRQ_ADC1), applied_mv[1]);
        }
        int state = avr_run(avr);
        if (state == cpu_Done || state == cpu_Crashed) {
            fprintf(stderr, "firmware stopped (state %d) at %.1f ms\n", state, sim_ms());
            break;
        }
        if (++iter % 2000 == 0) { /* pace the simulation to real time */
            double ahead = sim_ms() - (wall_ms() - t0);
            if (ahead > 1.0) {
                usleep((useconds_t)(ahead * 1000.0));
            }
        }
    }
    uart_pty_stop(&uart);
    return 0;
}
