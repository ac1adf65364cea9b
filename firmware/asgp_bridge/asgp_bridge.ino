/*
 * asgp_bridge: Arduino Mega 2560 joystick interface for a powered wheelchair.
 *
 * Reads the user's analog joystick (A0 forward, A1 turn) at ASGP_SAMPLE_RATE_HZ from a
 * Timer1 interrupt, sends every sample to the host, and writes the chair's analog input
 * through an MCP4922 dual DAC: the user's joystick (passthrough) or the host's override,
 * under the safety rules of safety.h. Protocol, safety logic and link handling are plain C
 * (protocol.c, safety.c, board.c) shared with the host unit tests; this file only binds
 * them to the hardware. Specification: docs/serial_protocol.md.
 */
#include <Arduino.h>
#include <SPI.h>
#include <avr/wdt.h>

#include "board.h"
#include "config.h"

static asgp_board_t board;
static volatile uint8_t tick_pending = 0;

ISR(TIMER1_COMPA_vect) { tick_pending = 1; }

static void uart_write(const uint8_t *data, size_t len, void *ctx)
{
    (void)ctx;
    /* HardwareSerial buffers 64 bytes; a SAMPLE is 16 bytes, so this never blocks long */
    Serial.write(data, len);
}

static void dac_write(uint8_t channel, uint16_t code)
{
    /* MCP4922 command word: A/B | BUF=1 | GA=1 (1x gain) | SHDN=1 (active) | 12-bit data */
    uint16_t word = (uint16_t)((channel ? 0x8000u : 0u) | 0x7000u | (code & 0x0FFFu));
    SPI.beginTransaction(SPISettings(8000000, MSBFIRST, SPI_MODE0));
    digitalWrite(ASGP_PIN_DAC_CS, LOW);
    SPI.transfer16(word);
    digitalWrite(ASGP_PIN_DAC_CS, HIGH);
    SPI.endTransaction();
}

static void start_sample_timer(void)
{
    /* Timer1 CTC: 16 MHz / 64 / (OCR1A + 1) = ASGP_SAMPLE_RATE_HZ */
    noInterrupts();
    TCCR1A = 0;
    TCCR1B = _BV(WGM12) | _BV(CS11) | _BV(CS10);
    OCR1A = (uint16_t)(F_CPU / 64UL / ASGP_SAMPLE_RATE_HZ - 1UL);
    TCNT1 = 0;
    TIMSK1 = _BV(OCIE1A);
    interrupts();
}

void setup()
{
    wdt_disable();
    pinMode(ASGP_PIN_DAC_CS, OUTPUT);
    digitalWrite(ASGP_PIN_DAC_CS, HIGH);
    pinMode(ASGP_PIN_DAC_SHDN, OUTPUT);
    digitalWrite(ASGP_PIN_DAC_SHDN, LOW); /* outputs off until they hold neutral */
    pinMode(ASGP_PIN_LED, OUTPUT);
    SPI.begin();

    asgp_board_init(&board, uart_write, NULL);
    dac_write(0, (uint16_t)board.cal[0].dac_neutral);
    dac_write(1, (uint16_t)board.cal[1].dac_neutral);
    digitalWrite(ASGP_PIN_DAC_SHDN, HIGH);

    analogReference(DEFAULT); /* AVCC */
    Serial.begin(ASGP_BAUD);
    start_sample_timer();
    wdt_enable(WDTO_120MS); /* a hung loop resets the board; setup() writes neutral first */
}

void loop()
{
    wdt_reset();
    /* bounded: a host that floods the link cannot keep the tick (and wdt_reset) waiting */
    for (uint8_t i = 0; i < ASGP_RX_PER_PASS && Serial.available() > 0; ++i) {
        asgp_board_rx(&board, (uint8_t)Serial.read(), millis());
    }
    if (!tick_pending) {
        return;
    }
    tick_pending = 0;
    int16_t raw[2];
    raw[0] = (int16_t)analogRead(ASGP_PIN_JOY_FWD);
    raw[1] = (int16_t)analogRead(ASGP_PIN_JOY_TURN);
    const asgp_output_t *out = asgp_board_tick(&board, raw, millis());
    dac_write(0, out->out_code[0]);
    dac_write(1, out->out_code[1]);
    digitalWrite(ASGP_PIN_LED, (out->status & ASGP_ST_OVERRIDE_ACTIVE) ? HIGH : LOW);
}
