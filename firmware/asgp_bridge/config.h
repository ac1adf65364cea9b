/*
 * Board configuration: timing, safety constants and the calibration of the analog path.
 * The simulated board (asgp_ros/sim/board.py, via asgp_ros/serial/safety.py) uses the same
 * values; test/test_firmware.py parses this header and fails if they drift apart.
 * Hardware and wiring: docs/serial_protocol.md, section "Board and analog shield".
 */
#ifndef ASGP_CONFIG_H
#define ASGP_CONFIG_H

#define ASGP_FW_MAJOR 1
#define ASGP_FW_MINOR 0
#define ASGP_FW_PATCH 0

#define ASGP_BAUD 115200UL
#define ASGP_SAMPLE_RATE_HZ 100   /* joystick sampling and SAMPLE frames (Timer1) */
#define ASGP_HEARTBEAT_EVERY 20   /* board HEARTBEAT every N samples (5 Hz at 100 Hz) */
#define ASGP_WATCHDOG_MS 200      /* an override older than this is ignored */
#define ASGP_HOST_TIMEOUT_MS 1000 /* no valid frame from the host: mode -> passthrough */
#define ASGP_RX_IDLE_MS 20   /* a partial frame with no byte for this long is given up */
#define ASGP_RX_PER_PASS 64  /* bytes taken from the UART per loop pass, at most */

/* Joystick input (ATmega2560 ADC, 10 bit, AVCC = 5 V reference): an inductive wheelchair
 * joystick centred at 2.5 V with +-1.0 V full deflection. */
#define ASGP_ADC_NEUTRAL 512
#define ASGP_ADC_SPAN 205     /* counts from neutral to full deflection (1.0 V) */
#define ASGP_ADC_DEADBAND 8   /* counts around neutral treated as neutral (~40 mV) */
#define ASGP_ADC_FAULT_LOW 41   /* below 0.2 V: open wire or short: fault */
#define ASGP_ADC_FAULT_HIGH 982 /* above 4.8 V: fault */

/* Output (MCP4922 12-bit DAC, VREF = 5 V): 2.5 V neutral, +-1.0 V full deflection. */
#define ASGP_DAC_NEUTRAL 2048
#define ASGP_DAC_SPAN 819 /* codes from neutral to full deflection (1.0 V) */
#define ASGP_DAC_MIN 1229 /* safe window: never below 1.5 V ... */
#define ASGP_DAC_MAX 2867 /* ... nor above 3.5 V, whatever the command */

/* Per-axis command limits in per mille of full deflection, applied to every output. */
#define ASGP_FWD_LIMIT_POS 1000 /* forward */
#define ASGP_FWD_LIMIT_NEG 1000 /* reverse */
#define ASGP_TURN_LIMIT_POS 1000 /* left */
#define ASGP_TURN_LIMIT_NEG 1000 /* right */

/* Pins (Arduino Mega 2560) */
#define ASGP_PIN_JOY_FWD A0   /* joystick forward/reverse signal */
#define ASGP_PIN_JOY_TURN A1  /* joystick left/right signal */
#define ASGP_PIN_DAC_CS 53    /* MCP4922 CS (SPI SS); SCK 52, MOSI 51 */
#define ASGP_PIN_DAC_SHDN 49  /* MCP4922 SHDN, 10k pull-down: outputs off until set up */
#define ASGP_PIN_LED 13       /* on while an override drives the chair */

#endif /* ASGP_CONFIG_H */
