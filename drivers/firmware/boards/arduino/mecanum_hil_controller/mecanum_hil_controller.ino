// The reference controller on an Arduino: the core of drivers/firmware/core behind the
// board seam, four DC motors with an H-bridge each (PWM + direction pin), one quadrature
// encoder channel per wheel counted by an interrupt, and an e-stop button.
//
// Before building, copy the core into this sketch's src/ folder:
//     make -C drivers/firmware arduino-sketch
// The pin map, the encoder resolution and the speed loop's gains below are placeholders:
// edit them for your robot (and ROBOT_K / WHEEL_LIMIT_RPM from its robot profile).
// Four interrupt pins are needed: an Arduino Mega 2560 has six (2, 3, 18, 19, 20, 21).

#include "src/mh_core.h"

// ---- the robot (drivers/tdam-stm.toml: lx_plus_ly_m / wheel_radius_m, wheel_speed_max_rpm)
static const float ROBOT_K = 0.465f / 0.102f;
static const float WHEEL_LIMIT_RPM = 130.0f;
static const uint16_t TELEMETRY_RATE_HZ = 100;
static const long BAUD = 115200;  // 100 Hz telemetry is 3300 bytes/s: within 115200 baud

// ---- the hardware (wheel order 1 FL, 2 FR, 3 RL, 4 RR)
static const uint8_t PWM_PIN[4] = {4, 5, 6, 7};
static const uint8_t DIR_PIN[4] = {22, 23, 24, 25};
static const uint8_t ENC_A_PIN[4] = {2, 3, 18, 19};  // interrupt pins
static const uint8_t ENC_B_PIN[4] = {26, 27, 28, 29};
static const uint8_t ESTOP_PIN = 30;          // to ground when pressed (INPUT_PULLUP)
static const float COUNTS_PER_REV = 1200.0f;  // encoder edges counted per wheel turn
static const float KP = 0.8f;                 // PWM counts per rpm of error
static const float KI = 4.0f;                 // PWM counts per rpm*s of error integral
static const float FEED_FORWARD = 255.0f / 150.0f;  // PWM counts per rpm of target
static const uint32_t SPEED_PERIOD_US = 5000;       // speed measurement and loop period

static volatile long enc_count[4];
static float wheel_rpm[4];
static float wheel_target[4];
static float wheel_integral[4];
static long last_count[4];
static uint32_t last_speed_us;

static void count(uint8_t i)
{
    enc_count[i] += digitalRead(ENC_B_PIN[i]) ? -1 : 1;
}
static void enc0() { count(0); }
static void enc1() { count(1); }
static void enc2() { count(2); }
static void enc3() { count(3); }

// ---- the board seam
static uint32_t board_now_us(void *) { return micros(); }

static size_t board_write(void *, const uint8_t *data, size_t len)
{
    int room = Serial.availableForWrite();  // never block the loop
    if (room <= 0) return 0;
    if ((size_t)room < len) len = (size_t)room;
    return Serial.write(data, len);
}

static void board_read_wheels(void *, float rpm[4])
{
    for (uint8_t i = 0; i < 4; i++) rpm[i] = wheel_rpm[i];
}

static void board_set_targets(void *, const float rpm[4])
{
    for (uint8_t i = 0; i < 4; i++) {
        wheel_target[i] = rpm[i];
        if (rpm[i] == 0.0f) wheel_integral[i] = 0.0f;
    }
}

static bool board_estop_pressed(void *) { return digitalRead(ESTOP_PIN) == LOW; }

static mh_core core;

// Measures the wheel speeds and runs a PI speed loop per wheel.
static void speed_loop(uint32_t now)
{
    float dt = (now - last_speed_us) * 1e-6f;
    last_speed_us = now;
    for (uint8_t i = 0; i < 4; i++) {
        noInterrupts();
        long c = enc_count[i];
        interrupts();
        wheel_rpm[i] = (c - last_count[i]) / COUNTS_PER_REV * 60.0f / dt;
        last_count[i] = c;
        float error = wheel_target[i] - wheel_rpm[i];
        float u = 0.0f;
        if (wheel_target[i] != 0.0f) {
            wheel_integral[i] += error * dt;
            u = FEED_FORWARD * wheel_target[i] + KP * error + KI * wheel_integral[i];
        }
        int pwm = (int)constrain(u < 0 ? -u : u, 0.0f, 255.0f);
        digitalWrite(DIR_PIN[i], u < 0 ? LOW : HIGH);
        analogWrite(PWM_PIN[i], pwm);
    }
}

void setup()
{
    for (uint8_t i = 0; i < 4; i++) {
        pinMode(PWM_PIN[i], OUTPUT);
        pinMode(DIR_PIN[i], OUTPUT);
        pinMode(ENC_A_PIN[i], INPUT_PULLUP);
        pinMode(ENC_B_PIN[i], INPUT_PULLUP);
    }
    pinMode(ESTOP_PIN, INPUT_PULLUP);
    attachInterrupt(digitalPinToInterrupt(ENC_A_PIN[0]), enc0, RISING);
    attachInterrupt(digitalPinToInterrupt(ENC_A_PIN[1]), enc1, RISING);
    attachInterrupt(digitalPinToInterrupt(ENC_A_PIN[2]), enc2, RISING);
    attachInterrupt(digitalPinToInterrupt(ENC_A_PIN[3]), enc3, RISING);
    Serial.begin(BAUD);

    mh_board board = {0, board_now_us, board_write, board_read_wheels, board_set_targets,
                      board_estop_pressed, 0};
    mh_config cfg = {TELEMETRY_RATE_HZ, WHEEL_LIMIT_RPM, ROBOT_K, "arduino"};
    mh_init(&core, &board, &cfg);
    last_speed_us = micros();
}

void loop()
{
    uint8_t buf[32];
    size_t n = 0;
    while (n < sizeof buf && Serial.available() > 0) buf[n++] = (uint8_t)Serial.read();
    if (n > 0) mh_feed(&core, buf, n);
    uint32_t now = micros();
    if (now - last_speed_us >= SPEED_PERIOD_US) speed_loop(now);
    mh_poll(&core);
}
