/* Safety logic of the board (see safety.h for the rules). */
#include "safety.h"

#include "config.h"
#include "protocol.h"

#include <string.h>

void asgp_default_calibration(asgp_axis_cal_t cal[2])
{
    for (int i = 0; i < 2; ++i) {
        cal[i].adc_neutral = ASGP_ADC_NEUTRAL;
        cal[i].adc_span = ASGP_ADC_SPAN;
        cal[i].adc_deadband = ASGP_ADC_DEADBAND;
        cal[i].adc_fault_low = ASGP_ADC_FAULT_LOW;
        cal[i].adc_fault_high = ASGP_ADC_FAULT_HIGH;
        cal[i].dac_neutral = ASGP_DAC_NEUTRAL;
        cal[i].dac_span = ASGP_DAC_SPAN;
        cal[i].dac_min = ASGP_DAC_MIN;
        cal[i].dac_max = ASGP_DAC_MAX;
    }
    cal[0].limit_pos = ASGP_FWD_LIMIT_POS;
    cal[0].limit_neg = ASGP_FWD_LIMIT_NEG;
    cal[1].limit_pos = ASGP_TURN_LIMIT_POS;
    cal[1].limit_neg = ASGP_TURN_LIMIT_NEG;
}

void asgp_safety_init(asgp_safety_t *s)
{
    memset(s, 0, sizeof(*s));
    s->mode = ASGP_MODE_PASSTHROUGH;
}

void asgp_safety_host_alive(asgp_safety_t *s, uint32_t now_ms)
{
    s->host_seen = 1;
    s->host_ms = now_ms;
}

uint8_t asgp_safety_set_mode(asgp_safety_t *s, uint8_t mode, uint32_t now_ms)
{
    (void)now_ms;
    if (mode != ASGP_MODE_PASSTHROUGH && mode != ASGP_MODE_OVERRIDE) {
        return ASGP_ERR_BAD_MODE;
    }
    if (mode != s->mode) {
        s->have_override = 0; /* an override never outlives a mode change */
    }
    s->mode = mode;
    return 0;
}

uint8_t asgp_safety_set_override(asgp_safety_t *s, int16_t fwd_pm, int16_t turn_pm,
                                 uint32_t now_ms)
{
    if (fwd_pm > ASGP_PERMILLE || fwd_pm < -ASGP_PERMILLE || turn_pm > ASGP_PERMILLE ||
        turn_pm < -ASGP_PERMILLE) {
        return ASGP_ERR_OVERRIDE_RANGE;
    }
    if (s->mode != ASGP_MODE_OVERRIDE) {
        return ASGP_ERR_NOT_IN_OVERRIDE;
    }
    s->override_pm[0] = fwd_pm;
    s->override_pm[1] = turn_pm;
    s->override_ms = now_ms;
    s->have_override = 1;
    return 0;
}

int16_t asgp_adc_to_permille(const asgp_axis_cal_t *cal, int16_t raw)
{
    int32_t d = (int32_t)raw - cal->adc_neutral;
    int32_t mag = d < 0 ? -d : d;
    if (mag <= cal->adc_deadband) {
        return 0;
    }
    /* rescale so the deflection is continuous at the edge of the dead band */
    int32_t usable = (int32_t)cal->adc_span - cal->adc_deadband;
    int32_t pm = ((mag - cal->adc_deadband) * ASGP_PERMILLE + usable / 2) / usable;
    if (pm > ASGP_PERMILLE) {
        pm = ASGP_PERMILLE;
    }
    return (int16_t)(d < 0 ? -pm : pm);
}

uint16_t asgp_permille_to_dac(const asgp_axis_cal_t *cal, int16_t pm, uint8_t *clamped)
{
    int32_t v = pm;
    if (v > cal->limit_pos) {
        v = cal->limit_pos;
        *clamped = 1;
    } else if (v < -(int32_t)cal->limit_neg) {
        v = -(int32_t)cal->limit_neg;
        *clamped = 1;
    }
    /* round half away from zero, the same in the Python mirror */
    int32_t num = v * cal->dac_span;
    int32_t off = (num >= 0 ? num + ASGP_PERMILLE / 2 : num - ASGP_PERMILLE / 2) / ASGP_PERMILLE;
    int32_t code = cal->dac_neutral + off;
    if (code > cal->dac_max) {
        code = cal->dac_max;
        *clamped = 1;
    } else if (code < cal->dac_min) {
        code = cal->dac_min;
        *clamped = 1;
    }
    return (uint16_t)code;
}

void asgp_safety_step(asgp_safety_t *s, const asgp_axis_cal_t cal[2], const int16_t raw[2],
                      uint32_t now_ms, asgp_output_t *out)
{
    uint8_t status = 0;
    uint8_t clamped = 0;

    if (s->mode == ASGP_MODE_OVERRIDE && s->host_seen &&
        (uint32_t)(now_ms - s->host_ms) >= ASGP_HOST_TIMEOUT_MS) {
        s->mode = ASGP_MODE_PASSTHROUGH; /* rule 5 */
        s->have_override = 0;
        status |= ASGP_ST_HOST_LOST;
    }
    if (s->mode == ASGP_MODE_OVERRIDE) {
        status |= ASGP_ST_MODE_OVERRIDE;
    }

    uint8_t fault = 0;
    for (int i = 0; i < 2; ++i) {
        if (raw[i] < cal[i].adc_fault_low || raw[i] > cal[i].adc_fault_high) {
            fault = 1;
        }
        out->user_pm[i] = asgp_adc_to_permille(&cal[i], raw[i]);
    }
    if (s->have_override && (uint32_t)(now_ms - s->override_ms) >= ASGP_WATCHDOG_MS) {
        s->have_override = 0; /* stale once is stale for good (2^32 ms later too) */
    }
    uint8_t fresh = s->mode == ASGP_MODE_OVERRIDE && s->have_override;
    if (s->mode == ASGP_MODE_OVERRIDE && !fresh) {
        status |= ASGP_ST_WATCHDOG;
    }
    uint8_t user_neutral = out->user_pm[0] == 0 && out->user_pm[1] == 0;

    if (fault) { /* rule 1 */
        status |= ASGP_ST_ADC_FAULT;
        out->out_pm[0] = 0;
        out->out_pm[1] = 0;
    } else if (user_neutral) { /* rule 2 */
        if (fresh) {
            status |= ASGP_ST_NEUTRAL_STOP;
        }
        out->out_pm[0] = 0;
        out->out_pm[1] = 0;
    } else if (fresh) { /* rule 3 */
        status |= ASGP_ST_OVERRIDE_ACTIVE;
        out->out_pm[0] = s->override_pm[0];
        out->out_pm[1] = s->override_pm[1];
    } else {
        out->out_pm[0] = out->user_pm[0];
        out->out_pm[1] = out->user_pm[1];
    }
    for (int i = 0; i < 2; ++i) { /* rule 4 */
        out->out_code[i] = asgp_permille_to_dac(&cal[i], out->out_pm[i], &clamped);
    }
    if (clamped) {
        status |= ASGP_ST_CLAMPED;
    }
    out->status = status;
}
