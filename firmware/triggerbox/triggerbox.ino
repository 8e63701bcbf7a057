// slscan trigger box, reference firmware (protocol version 2).
//
// Boards: Arduino Uno / Nano (ATmega328P) and Raspberry Pi Pico (RP2040, arduino-pico core).
// Output: TRIGGER_PIN goes high for WIDTH us at the start of every pulse; wire it (through a
// level shifter or opto-coupler where the inputs need it) to the projector's TRIG_IN and
// the camera's trigger line. The on-board LED lights while a train runs.
// Input: INPUT_PIN (internal pull-up) is the operator's foot switch, a normally-open contact
// to GND; each press (the contact closing and staying closed for DEBOUNCE_MS) is counted.
//
// Line protocol (115200 baud, "\n" or "\r\n" line ends, one reply line per command; the
// host driver is scanner/drivers/triggerbox.py, whose docstring is the reference):
//   ID?            -> ID SLSCAN-TRIGGERBOX 2 <board>
//   PERIOD <us>    -> OK        100..10000000
//   WIDTH <us>     -> OK        1..period-1 (checked at ARM)
//   ARM <n>        -> OK        1..1000000
//   START          -> OK        first pulse now, then one per period
//   STOP           -> OK
//   COUNT?         -> COUNT <sent> <armed>
//   PRESSES?       -> PRESSES <n>   foot-switch presses since start-up (protocol 2)
//   errors         -> ERR <code> <text>: 1 unknown command, 2 bad value,
//                     3 width not below period, 4 not armed, 5 busy
// On start-up the firmware prints "READY SLSCAN-TRIGGERBOX 2".
//
// Timing: pulses are scheduled from one start time (t0 + i * period, no drift) and driven
// from loop(), so jitter is a few microseconds; serial commands are parsed between pulses
// without blocking. The input is sampled from loop() too; the host polls the press count
// (an event counter: no unsolicited lines, no press lost between polls).

#include <Arduino.h>

#if defined(ARDUINO_ARCH_RP2040)
static const char *BOARD = "rp2040";
static const uint8_t TRIGGER_PIN = 15;
static const uint8_t INPUT_PIN = 14;
#else
static const char *BOARD = "avr";
static const uint8_t TRIGGER_PIN = 2;
static const uint8_t INPUT_PIN = 3;
#endif

static const uint32_t MIN_PERIOD_US = 100;
static const uint32_t MAX_PERIOD_US = 10000000UL;
static const uint32_t MAX_COUNT = 1000000UL;
static const uint32_t DEBOUNCE_MS = 20;

static uint32_t period_us = 50000;
static uint32_t width_us = 100;
static uint32_t armed = 0;      // pulses in the armed train; 0 = not armed
static uint32_t sent = 0;       // pulses sent since ARM
static bool running = false;
static bool pin_high = false;
static uint32_t t0 = 0;         // micros() of the first pulse
static uint32_t presses = 0;    // debounced foot-switch presses since start-up
static bool input_closed = false;   // debounced state of the input
static bool input_raw = false;      // last sampled state
static uint32_t input_changed = 0;  // millis() when the sampled state last changed

static char line[48];
static uint8_t line_len = 0;
static bool line_overflow = false;

static void reply_error(uint8_t code, const char *text) {
  Serial.print("ERR ");
  Serial.print(code);
  Serial.print(' ');
  Serial.println(text);
}

// Parses a decimal number filling the rest of the line; false on anything else.
static bool parse_u32(const char *s, uint32_t *out) {
  if (*s == '\0') return false;
  uint32_t v = 0;
  for (; *s; ++s) {
    if (*s < '0' || *s > '9') return false;
    uint32_t d = (uint32_t)(*s - '0');
    if (v > (0xFFFFFFFFUL - d) / 10) return false;
    v = v * 10 + d;
  }
  *out = v;
  return true;
}

static void stop_train() {
  running = false;
  pin_high = false;
  digitalWrite(TRIGGER_PIN, LOW);
  digitalWrite(LED_BUILTIN, LOW);
}

static void handle(const char *cmd) {
  uint32_t v;
  if (strcmp(cmd, "ID?") == 0) {
    Serial.print("ID SLSCAN-TRIGGERBOX 2 ");
    Serial.println(BOARD);
  } else if (strcmp(cmd, "COUNT?") == 0) {
    Serial.print("COUNT ");
    Serial.print(sent);
    Serial.print(' ');
    Serial.println(armed);
  } else if (strcmp(cmd, "PRESSES?") == 0) {
    Serial.print("PRESSES ");
    Serial.println(presses);
  } else if (strncmp(cmd, "PERIOD ", 7) == 0) {
    if (running) { reply_error(5, "busy"); return; }
    if (!parse_u32(cmd + 7, &v) || v < MIN_PERIOD_US || v > MAX_PERIOD_US) { reply_error(2, "bad value"); return; }
    period_us = v;
    Serial.println("OK");
  } else if (strncmp(cmd, "WIDTH ", 6) == 0) {
    if (running) { reply_error(5, "busy"); return; }
    if (!parse_u32(cmd + 6, &v) || v < 1) { reply_error(2, "bad value"); return; }
    width_us = v;
    Serial.println("OK");
  } else if (strncmp(cmd, "ARM ", 4) == 0) {
    if (running) { reply_error(5, "busy"); return; }
    if (!parse_u32(cmd + 4, &v) || v < 1 || v > MAX_COUNT) { reply_error(2, "bad value"); return; }
    if (width_us >= period_us) { reply_error(3, "width not below period"); return; }
    armed = v;
    sent = 0;
    Serial.println("OK");
  } else if (strcmp(cmd, "START") == 0) {
    if (running) { reply_error(5, "busy"); return; }
    if (armed == 0 || sent != 0) { reply_error(4, "not armed"); return; }
    t0 = micros();
    running = true;
    digitalWrite(LED_BUILTIN, HIGH);
    Serial.println("OK");
  } else if (strcmp(cmd, "STOP") == 0) {
    stop_train();
    Serial.println("OK");
  } else {
    reply_error(1, "unknown command");
  }
}

static void poll_serial() {
  while (Serial.available() > 0) {
    char c = (char)Serial.read();
    if (c == '\r') continue;
    if (c == '\n') {
      line[line_len] = '\0';
      if (line_overflow) reply_error(2, "bad value");
      else if (line_len > 0) handle(line);
      line_len = 0;
      line_overflow = false;
    } else if (line_len < sizeof(line) - 1) {
      line[line_len++] = c;
    } else {
      line_overflow = true;
    }
  }
}

static void run_train() {
  if (!running) return;
  uint32_t now = micros();
  uint32_t next_start = t0 + sent * period_us;  // unsigned arithmetic wraps with micros()
  if (!pin_high && (int32_t)(now - next_start) >= 0) {
    digitalWrite(TRIGGER_PIN, HIGH);
    pin_high = true;
  } else if (pin_high && (int32_t)(now - (next_start + width_us)) >= 0) {
    digitalWrite(TRIGGER_PIN, LOW);
    pin_high = false;
    sent++;
    if (sent >= armed) {
      stop_train();
      armed = 0;  // one START per ARM
    }
  }
}

// Counts a press when the input has been closed (low) for DEBOUNCE_MS after being open.
static void poll_input() {
  bool raw = digitalRead(INPUT_PIN) == LOW;
  uint32_t now = millis();
  if (raw != input_raw) {
    input_raw = raw;
    input_changed = now;
  } else if (raw != input_closed && now - input_changed >= DEBOUNCE_MS) {
    input_closed = raw;
    if (raw) presses++;
  }
}

void setup() {
  pinMode(TRIGGER_PIN, OUTPUT);
  digitalWrite(TRIGGER_PIN, LOW);
  pinMode(LED_BUILTIN, OUTPUT);
  digitalWrite(LED_BUILTIN, LOW);
  pinMode(INPUT_PIN, INPUT_PULLUP);
  Serial.begin(115200);
#if defined(ARDUINO_ARCH_RP2040)
  uint32_t wait_start = millis();
  while (!Serial && millis() - wait_start < 2000) {}  // native USB: give the host time to open the port
#endif
  Serial.println("READY SLSCAN-TRIGGERBOX 2");
}

void loop() {
  run_train();
  poll_input();
  poll_serial();
}
