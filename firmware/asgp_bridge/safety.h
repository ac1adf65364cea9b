/*
 * Safety logic of the board: override watchdog, neutral rule, clamping, ADC plausibility.
 * Plain C99 without the Arduino API, so the host unit test (firmware/test/) exercises the
 * very code the board runs. The rules (docs/serial_protocol.md, "Safety rules"):
 *  1. ADC fault (a reading outside [ADC_FAULT_LOW, ADC_FAULT_HIGH]) -> neutral output.
 *  2. The user's joystick inside the dead band on both axes -> neutral output, in every
 *     mode: letting go of the joystick is a stop request that no override can overrule.
 *  3. Mode override and an override received less than ASGP_WATCHDOG_MS ago -> the
 *     override is the output; otherwise the user's joystick is passed through.
 *  4. Every output is limited per axis and clamped to the DAC's safe window.
 *  5. No valid frame from the host for ASGP_HOST_TIMEOUT_MS -> mode passthrough.
 */
#ifndef ASGP_SAFETY_H
#define ASGP_SAFETY_H

#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

typedef struct {
    int16_t adc_neutral;
    int16_t adc_span;
    int16_t adc_deadband;
    int16_t adc_fault_low;
    int16_t adc_fault_high;
    int16_t limit_pos; /* per mille */
    int16_t limit_neg; /* per mille, magnitude */
    int16_t dac_neutral;
    int16_t dac_span;
    int16_t dac_min;
    int16_t dac_max;
} asgp_axis_cal_t;

typedef struct {
    uint8_t mode;
    uint8_t have_override;
    int16_t override_pm[2]; /* forward, turn in per mille */
    uint32_t override_ms;
    uint8_t host_seen;
    uint32_t host_ms;
} asgp_safety_t;

typedef struct {
    int16_t user_pm[2];   /* the user's calibrated deflection, per mille */
    int16_t out_pm[2];    /* the commanded deflection after the rules, per mille */
    uint16_t out_code[2]; /* DAC codes written to the chair */
    uint8_t status;       /* ASGP_ST_* bits */
} asgp_output_t;

/* The default calibration from config.h: axis 0 forward, axis 1 turn. */
void asgp_default_calibration(asgp_axis_cal_t cal[2]);
void asgp_safety_init(asgp_safety_t *s);

/* Any valid frame from the host (refreshes the host timeout). */
void asgp_safety_host_alive(asgp_safety_t *s, uint32_t now_ms);
/* Returns 0 or an ASGP_ERR_* code (the mode is then unchanged). */
uint8_t asgp_safety_set_mode(asgp_safety_t *s, uint8_t mode, uint32_t now_ms);
/* Returns 0 or an ASGP_ERR_* code (the override is then ignored). */
uint8_t asgp_safety_set_override(asgp_safety_t *s, int16_t fwd_pm, int16_t turn_pm,
                                 uint32_t now_ms);

/* ADC counts -> per mille deflection with the dead band removed, limited to +-1000. */
int16_t asgp_adc_to_permille(const asgp_axis_cal_t *cal, int16_t raw);
/* per mille -> DAC code, clamped to the axis window; *clamped set to 1 if it clamped. */
uint16_t asgp_permille_to_dac(const asgp_axis_cal_t *cal, int16_t pm, uint8_t *clamped);

/* One control step: raw ADC readings -> what the board writes to the chair. */
void asgp_safety_step(asgp_safety_t *s, const asgp_axis_cal_t cal[2], const int16_t raw[2],
                      uint32_t now_ms, asgp_output_t *out);

#ifdef __cplusplus
}
#endif

#endif /* ASGP_SAFETY_H */
