//! One simulated STS servo: the register file, the firmware (position and speed loops, torque
//! limit, protections) and the physical plant (DC motor through a gearbox, friction, one-node
//! thermal model).
//!
//! The plant is quasi-static electrically (the winding's L/R is far below the control period):
//! `I = (duty·V − ke·ω)/R`, output torque `kt·I`, both referred to the output shaft.

use crate::description::ServoRating;
use feetech::encoding::{decode_sign_magnitude, encode_sign_magnitude, u16_le};
use feetech::registers::{self as reg, Register, TABLE_SIZE};
use feetech::{ServoModel, ServoStatus, AMPS_PER_CURRENT_UNIT, STEPS_PER_TURN};
use std::f64::consts::TAU;

/// Radians per encoder step.
pub const RAD_PER_STEP: f64 = TAU / STEPS_PER_TURN as f64;
/// Raw position of the output shaft at joint angle 0.
pub const CENTER_STEP: f64 = 2048.0;
/// Duty ceiling of the firmware (it never drives 100 %).
pub const MAX_DUTY: f64 = 0.97;
/// Gain of the firmware position loop: duty ≈ kp · 0.166 · error(rad) (BAM's identification).
pub const DUTY_PER_KP_RAD: f64 = 0.166;
/// Below this speed (rad/s) a joint whose drive torque cannot beat static friction sticks.
const STICK_SPEED: f64 = 1e-3;
/// The firmware's control period, s: it reads the encoder and sets the duty once per period
/// and the PWM holds that duty until the next (1 kHz, the simulator's default step; Feetech
/// does not publish its loop rate). Whatever step the caller integrates with, the duty changes
/// on the same ticks: a replay at 1 ms and a reference at 0.1 ms run the same firmware.
pub const FIRMWARE_PERIOD_S: f64 = 0.001;
/// Time closer to a firmware tick than this, s, is on it (sums of small steps round).
pub const TICK_TOLERANCE_S: f64 = 1e-9;
/// Integral gain of the speed mode's loop, per second, times the back-EMF constant: the
/// firmware's "constant speed" mode holds the goal speed under a steady load (the speed
/// error's integral settles in about 1/20 s), within what the torque allows.
const SPEED_KI_PER_S: f64 = 20.0;

/// Electrical and thermal constants of one servo, output-referred, derived from its ratings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Plant {
    /// Winding resistance, Ω (rated voltage / stall current).
    pub resistance: f64,
    /// Torque constant at the output, N·m/A (motor kt × gear ratio).
    pub kt: f64,
    /// Back-EMF constant at the output, V·s/rad (motor ke × gear ratio).
    pub ke: f64,
    /// Gear ratio, for reporting motor-side constants.
    pub gear_ratio: f64,
    /// Rotor inertia reflected to the output, kg·m².
    pub armature: f64,
    /// Coulomb friction, N·m.
    pub coulomb: f64,
    /// Viscous friction, N·m·s/rad.
    pub viscous: f64,
    /// Heat capacity, J/K.
    pub heat_capacity: f64,
    /// Thermal resistance to ambient, K/W.
    pub thermal_resistance: f64,
    /// Constant electronics loss, W.
    pub idle_power: f64,
}

impl Plant {
    /// Constants from a servo's ratings: R from stall current at rated voltage, kt from stall
    /// torque over stall current, ke from the no-load speed.
    pub fn from_rating(r: &ServoRating) -> Self {
        let stall_torque = r.stall_torque_kgcm * 0.0980665;
        Plant {
            resistance: r.rated_voltage / r.stall_current_a,
            kt: stall_torque / r.stall_current_a,
            ke: r.rated_voltage / r.no_load_speed_rad_s,
            gear_ratio: r.gear_ratio,
            armature: r.armature_kgm2,
            coulomb: r.coulomb_nm,
            viscous: r.viscous_nms,
            heat_capacity: r.heat_capacity_j_per_k,
            thermal_resistance: r.thermal_resistance_k_per_w,
            idle_power: r.idle_power_w,
        }
    }
}

/// What the firmware's protections have done, latched until the host re-enables torque.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Protections {
    /// Seconds the current has been above `Protection_Current`.
    over_current_for: f64,
    /// Seconds the duty has been above `Overload_Torque`.
    overload_for: f64,
    /// Over-current tripped: output off.
    pub over_current: bool,
    /// Overload tripped: output limited to `Protective_Torque`.
    pub overload: bool,
    /// Over-temperature cutoff: output off, announced by the status byte's overheat bit.
    pub over_temperature: bool,
}

/// Counters the tests read back ("what the servo received").
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct ServoLog {
    /// Goal_Position writes received.
    pub goal_writes: u64,
    /// Smallest Goal_Position received (steps), if any.
    pub goal_min: Option<i32>,
    /// Largest Goal_Position received (steps), if any.
    pub goal_max: Option<i32>,
    /// Writes that reached the EEPROM flash (Lock = 0 and a changed value).
    pub eeprom_writes: u64,
    /// Times the over-temperature cutoff fired.
    pub hardware_cutoffs: u64,
    /// Times over-current protection fired.
    pub over_current_trips: u64,
    /// Times overload protection fired.
    pub overload_trips: u64,
    /// Torque_Enable = 0 writes.
    pub torque_off_writes: u64,
    /// Torque_Enable = 1 writes.
    pub torque_on_writes: u64,
    /// When the last Goal_Position write arrived (simulated s).
    pub last_goal_write_s: Option<f64>,
    /// When the last Torque_Enable write arrived (simulated s), and the value written.
    pub last_torque_write: Option<(f64, u8)>,
    /// When the last Torque_Enable = 1 write arrived (simulated s).
    pub last_torque_on_s: Option<f64>,
    /// Time its joint spent past a hard stop with its motor pushing it further in, s (by hand
    /// with the torque off, or sagging in under gravity while the motor holds against it, does
    /// not count).
    pub stop_press_s: f64,
    /// The most the motor pushed while pressing a stop, 0.1 % of full duty (comparable with
    /// Torque_Limit).
    pub stop_press_max_permille: u16,
    /// Times its joint went past a hard stop (struck it, or sagged or was pushed onto it).
    pub stop_hits: u64,
    /// The fastest its joint went past a hard stop with its torque on, rad/s: a strike's speed.
    pub stop_hit_max_speed_rad_s: f64,
    /// The same with its torque off (a hand sweeping it limp, an arm dropped by a trip), rad/s.
    pub limp_hit_max_speed_rad_s: f64,
}

/// The registers the firmware consults every step, decoded once per write (not per step).
#[derive(Debug, Clone, Copy, Default)]
struct Firmware {
    torque_enable: i32,
    mode: i32,
    kp: f64,
    homing: f64,
    goal: f64,
    limits: Option<(f64, f64)>,
    profile_speed: f64,
    profile_accel: f64,
    pwm_goal: f64,
    speed_goal: f64,
    torque_cap: f64,
    protective_duty: f64,
    unloading: u8,
    temperature_limit: f64,
    current_limit: f64,
    over_current_time: f64,
    overload_duty: f64,
    overload_time: f64,
}

/// Standard gravity, m/s².
pub const GRAVITY_M_S2: f64 = 9.81;

/// What a servo's output meets over a step, and the room it is in.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Surroundings {
    /// Load torque on the output, N·m (gravity, contacts), opposing positive motion when
    /// positive.
    pub load_torque_n_m: f64,
    /// Load inertia on the output, kg·m², added to the armature's.
    pub load_inertia_kg_m2: f64,
    /// Ambient temperature, °C.
    pub ambient_c: f64,
    /// How many times faster the thermal node is integrated (accelerated heating scenarios).
    pub thermal_speedup: f64,
}

impl Surroundings {
    /// A free output on a bench at 25 °C, heating in real time.
    pub const BENCH: Surroundings = Surroundings {
        load_torque_n_m: 0.0,
        load_inertia_kg_m2: 0.0,
        ambient_c: 25.0,
        thermal_speedup: 1.0,
    };

    /// These surroundings with a load torque of `n_m`.
    pub fn torque(self, n_m: f64) -> Surroundings {
        Surroundings {
            load_torque_n_m: n_m,
            ..self
        }
    }

    /// These surroundings with a load inertia of `kg_m2`.
    pub fn inertia(self, kg_m2: f64) -> Surroundings {
        Surroundings {
            load_inertia_kg_m2: kg_m2,
            ..self
        }
    }

    /// A point mass `mass_kg` at `arm_m` on the servo's output, hanging at angle 0, over a step
    /// of `h` s from the servo's state: gravity taken at the step's middle, as the servo holds
    /// it over the step (at the step's start it would pump energy into a free swing, a step's
    /// error per swing), and the mass's inertia.
    pub fn pendulum(self, mass_kg: f64, arm_m: f64, servo: &Servo, h: f64) -> Surroundings {
        let middle = servo.angle + 0.5 * h * servo.speed;
        self.torque(mass_kg * GRAVITY_M_S2 * arm_m * middle.sin())
            .inertia(mass_kg * arm_m * arm_m)
    }
}

/// One simulated servo.
#[derive(Debug, Clone)]
pub struct Servo {
    /// Bus id.
    pub id: u8,
    /// Its model, which its `Model_Number` register reports.
    pub model: ServoModel,
    /// When the instruction being executed arrived (simulated s), for the log.
    pub now: f64,
    /// Plant constants.
    pub plant: Plant,
    /// Register file as the host sees it.
    regs: [u8; TABLE_SIZE],
    /// What the EEPROM holds across a reboot.
    flash: [u8; TABLE_SIZE],
    /// Output angle, rad (0 at raw step 2048).
    pub angle: f64,
    /// Output speed, rad/s.
    pub speed: f64,
    /// Winding temperature, °C.
    pub temperature: f64,
    /// Highest winding temperature reached, °C.
    pub max_temperature: f64,
    /// Motor current, A (signed).
    pub current: f64,
    /// Applied duty, −1..1.
    pub duty: f64,
    /// Supply voltage at the servo, V.
    pub supply: f64,
    /// Profiled position setpoint, steps (position mode).
    setpoint: f64,
    /// Profiled setpoint speed, steps/s.
    setpoint_speed: f64,
    /// Position control is off (torque off, or another mode): the profile starts again from
    /// where the servo is when it comes back.
    profile_restarts: bool,
    /// Speed mode: the integral of the speed error, rad.
    speed_integral: f64,
    /// With backlash: the motor side's angle less the output's, within ±half the play, rad ...
    motor_lead: f64,
    /// ... and the motor side's speed, rad/s (the output's, `speed`, without backlash).
    motor_speed: f64,
    /// Time since the firmware's last tick, s (0: a tick is due).
    since_tick: f64,
    /// The last exponential decay the plant computed (most steps repeat it).
    decay: Decay,
    /// Protection state.
    pub protections: Protections,
    /// Counters for tests and reports.
    pub log: ServoLog,
    /// When false the servo does not answer (unplugged, or rebooting).
    pub answering: bool,
    /// Effects a fitted model extension adds (none by default).
    pub extension: crate::extension::ServoExtension,
    /// Temperature of the sensor node, °C (the winding's unless `extension` gives it a lag).
    pub sensor_temperature: f64,
    /// Heat flowing in from neighbouring servos, W (set by the bus before each step).
    pub external_heat_w: f64,
    /// Where its encoder reads, less 2048 steps, when its joint is at zero: the spline tooth
    /// its horn was fitted on (0 on the simulated A3 as delivered).
    pub horn_steps: f64,
    fw: Firmware,
}

impl Servo {
    /// A servo with factory defaults, at `angle` rad and ambient temperature.
    pub fn new(id: u8, model: ServoModel, rating: &ServoRating, angle: f64, ambient: f64) -> Self {
        let mut s = Servo {
            id,
            model,
            now: 0.0,
            plant: Plant::from_rating(rating),
            regs: [0; TABLE_SIZE],
            flash: [0; TABLE_SIZE],
            angle,
            speed: 0.0,
            temperature: ambient,
            max_temperature: ambient,
            current: 0.0,
            duty: 0.0,
            supply: rating.rated_voltage,
            setpoint: CENTER_STEP + angle / RAD_PER_STEP,
            setpoint_speed: 0.0,
            profile_restarts: true,
            speed_integral: 0.0,
            motor_lead: 0.0,
            motor_speed: 0.0,
            since_tick: 0.0,
            decay: Decay::default(),
            protections: Protections::default(),
            log: ServoLog::default(),
            answering: true,
            extension: Default::default(),
            sensor_temperature: ambient,
            external_heat_w: 0.0,
            horn_steps: 0.0,
            fw: Firmware::default(),
        };
        let factory: &[(Register, i32)] = &[
            (reg::FIRMWARE_MAJOR, 3),
            (reg::FIRMWARE_MINOR, 10),
            (reg::MODEL_NUMBER, i32::from(model.model_number())),
            (reg::ID, i32::from(id)),
            (reg::BAUD_RATE, 0),
            // Factory return delay is 500 µs; the driver sets it to 0 once (EEPROM).
            (reg::RETURN_DELAY_TIME, 250),
            (reg::MIN_POSITION_LIMIT, 0),
            (reg::MAX_POSITION_LIMIT, 4095),
            (reg::MAX_TEMPERATURE_LIMIT, 70),
            (reg::MAX_VOLTAGE_LIMIT, 140),
            (reg::MIN_VOLTAGE_LIMIT, 40),
            (reg::MAX_TORQUE_LIMIT, 1000),
            (reg::UNLOADING_CONDITION, 0x2C),
            (reg::LED_ALARM_CONDITION, 0x2F),
            (reg::P_COEFFICIENT, 32),
            (reg::D_COEFFICIENT, 32),
            (reg::PROTECTION_CURRENT, 500),
            (reg::PROTECTIVE_TORQUE, 20),
            (reg::PROTECTION_TIME, 200),
            (reg::OVERLOAD_TORQUE, 80),
            (reg::OVER_CURRENT_PROTECTION_TIME, 200),
            (reg::TORQUE_LIMIT, 1000),
            (reg::LOCK, 1),
        ];
        for (r, v) in factory {
            s.set(*r, *v);
        }
        s.flash = s.regs;
        s.set_goal_to_present();
        s.refresh_firmware();
        s
    }

    fn refresh_firmware(&mut self) {
        let (lo, hi) = (
            self.get(reg::MIN_POSITION_LIMIT),
            self.get(reg::MAX_POSITION_LIMIT),
        );
        self.fw = Firmware {
            torque_enable: self.get(reg::TORQUE_ENABLE),
            mode: self.get(reg::OPERATING_MODE),
            kp: f64::from(self.get(reg::P_COEFFICIENT)),
            homing: f64::from(self.get(reg::HOMING_OFFSET)),
            goal: f64::from(self.get(reg::GOAL_POSITION)),
            limits: (lo != 0 || hi != 0).then_some((f64::from(lo), f64::from(hi))),
            profile_speed: f64::from(self.get(reg::GOAL_VELOCITY).abs()),
            profile_accel: f64::from(self.get(reg::ACCELERATION)) * 100.0,
            pwm_goal: f64::from(decode_sign_magnitude(
                u16_le(self.regs[44], self.regs[45]),
                10,
            )) / 1000.0,
            speed_goal: f64::from(self.get(reg::GOAL_VELOCITY)) * RAD_PER_STEP,
            torque_cap: MAX_DUTY.min(f64::from(self.get(reg::TORQUE_LIMIT)) / 1000.0),
            protective_duty: f64::from(self.get(reg::PROTECTIVE_TORQUE)) / 100.0,
            unloading: self.get(reg::UNLOADING_CONDITION) as u8,
            temperature_limit: f64::from(self.get(reg::MAX_TEMPERATURE_LIMIT)),
            current_limit: f64::from(self.get(reg::PROTECTION_CURRENT)) * AMPS_PER_CURRENT_UNIT,
            over_current_time: f64::from(self.get(reg::OVER_CURRENT_PROTECTION_TIME)) * 0.01,
            overload_duty: f64::from(self.get(reg::OVERLOAD_TORQUE)) / 100.0,
            overload_time: f64::from(self.get(reg::PROTECTION_TIME)) * 0.01,
        };
    }

    fn set(&mut self, r: Register, v: i32) {
        let raw = match r.encoding {
            reg::Encoding::Unsigned => v as u16,
            reg::Encoding::SignMagnitude(bit) => encode_sign_magnitude(v, bit)
                .unwrap_or(if v < 0 { u16::MAX } else { (1 << bit) - 1 }),
        };
        let a = r.addr as usize;
        self.regs[a] = raw as u8;
        if r.size == 2 {
            self.regs[a + 1] = (raw >> 8) as u8;
        }
    }

    /// A register's value, decoded.
    pub fn get(&self, r: Register) -> i32 {
        let a = r.addr as usize;
        r.decode(&self.regs[a..a + r.size as usize]).unwrap_or(0)
    }

    /// Raw position (steps) of the output shaft, before the homing offset.
    fn raw_position(&self) -> f64 {
        CENTER_STEP + self.horn_steps + self.angle / RAD_PER_STEP
    }

    /// Calibrated for a joint with stops at `lower_rad`..`upper_rad`, as the commissioning
    /// leaves a servo: a homing offset that makes Present_Position read 2048 at the joint's
    /// zero (the horn's tooth taken out), and position limits `margin_rad` inside the stops,
    /// in EEPROM. Its goal follows, so it holds where it is.
    pub fn calibrate(&mut self, lower_rad: f64, upper_rad: f64, margin_rad: f64) {
        let step = |rad: f64| (CENTER_STEP + rad / RAD_PER_STEP).round() as i32;
        self.set(reg::HOMING_OFFSET, self.horn_steps.round() as i32);
        self.set(reg::MIN_POSITION_LIMIT, step(lower_rad + margin_rad));
        self.set(reg::MAX_POSITION_LIMIT, step(upper_rad - margin_rad));
        self.flash[..40].copy_from_slice(&self.regs[..40]);
        self.set_goal_to_present();
    }

    /// As a servo is set up but not calibrated: its homing offset and position limits the
    /// factory's (0, 0..4095), in EEPROM. Its goal follows, so it holds where it is.
    pub fn clear_calibration(&mut self) {
        self.set(reg::HOMING_OFFSET, 0);
        self.set(reg::MIN_POSITION_LIMIT, 0);
        self.set(reg::MAX_POSITION_LIMIT, 4095);
        self.flash[..40].copy_from_slice(&self.regs[..40]);
        self.set_goal_to_present();
    }

    /// Fits its horn `steps` off the joint's zero (a new servo's); its goal follows, so it
    /// holds where it is.
    pub fn fit_horn(&mut self, steps: f64) {
        self.horn_steps = steps;
        self.set_goal_to_present();
    }

    fn present_position(&self) -> i32 {
        let homing = self.get(reg::HOMING_OFFSET);
        (self.raw_position().round() as i32 - homing).rem_euclid(STEPS_PER_TURN as i32)
    }

    fn set_goal_to_present(&mut self) {
        let p = self.present_position();
        self.set(reg::GOAL_POSITION, p);
        self.setpoint = f64::from(p);
        self.setpoint_speed = 0.0;
        self.fw.goal = f64::from(p);
    }

    /// The line rate it listens and answers at (its `Baud_Rate` register; an undefined code is
    /// no rate any host can set, so the servo hears nobody).
    pub fn line_baud(&self) -> Option<u32> {
        feetech::timing::BAUD_CODES
            .get(usize::try_from(self.get(reg::BAUD_RATE)).ok()?)
            .copied()
    }

    /// Its reply delay, s (`Return_Delay_Time`, 2 µs a count).
    pub fn return_delay_s(&self) -> f64 {
        f64::from(self.get(reg::RETURN_DELAY_TIME)) * 2e-6
    }

    /// The Torque_Limit register, 0.1 %.
    pub fn torque_limit(&self) -> u16 {
        self.get(reg::TORQUE_LIMIT) as u16
    }

    /// Whether the output stage is driving: torque enabled and no protection holds it off.
    pub fn torque_enabled(&self) -> bool {
        self.fw.torque_enable == 1
            && !self.protections.over_current
            && !self.protections.over_temperature
    }

    /// Power cycle: SRAM back to defaults, EEPROM from flash, protections cleared.
    pub fn reboot(&mut self) {
        self.regs[..40].copy_from_slice(&self.flash[..40]);
        self.id = self.get(reg::ID) as u8;
        self.set(reg::TORQUE_ENABLE, 0);
        let max_torque = self.get(reg::MAX_TORQUE_LIMIT);
        self.set(reg::TORQUE_LIMIT, max_torque);
        self.set(reg::LOCK, 1);
        self.protections = Protections::default();
        self.refresh_firmware();
        self.set_goal_to_present();
    }

    /// Reads `len` registers at `addr` into `out` (the feedback block reflects the plant now).
    /// Returns false when the range leaves the table.
    pub fn read(&mut self, addr: u8, len: u8, out: &mut [u8]) -> bool {
        let (a, n) = (addr as usize, len as usize);
        if a + n > TABLE_SIZE || out.len() < n {
            return false;
        }
        self.refresh_feedback();
        out[..n].copy_from_slice(&self.regs[a..a + n]);
        true
    }

    /// Applies a WRITE of `data` at `addr`. Read-only registers are ignored, as on the servo.
    pub fn write(&mut self, addr: u8, data: &[u8]) -> bool {
        let a = addr as usize;
        if a + data.len() > TABLE_SIZE {
            return false;
        }
        let locked = self.get(reg::LOCK) != 0;
        for (i, &b) in data.iter().enumerate() {
            let at = a + i;
            if at >= reg::FEEDBACK_ADDR as usize {
                continue;
            }
            if at < 40 && !locked && self.flash[at] != b {
                self.flash[at] = b;
                self.log.eeprom_writes += 1;
            }
            self.regs[at] = b;
        }
        // A new id (and a new line rate) takes effect at once; the flash keeps it only when
        // the EEPROM was unlocked.
        self.id = self.get(reg::ID) as u8;
        self.refresh_firmware();
        let touches = |r: Register| a <= r.addr as usize && (r.addr as usize) < a + data.len();
        if touches(reg::GOAL_POSITION) {
            let goal = self.get(reg::GOAL_POSITION);
            let log = &mut self.log;
            log.goal_writes += 1;
            log.goal_min = Some(log.goal_min.map_or(goal, |m| m.min(goal)));
            log.goal_max = Some(log.goal_max.map_or(goal, |m| m.max(goal)));
            log.last_goal_write_s = Some(self.now);
        }
        if touches(reg::TORQUE_ENABLE) {
            let value = self.get(reg::TORQUE_ENABLE);
            self.log.last_torque_write = Some((self.now, value as u8));
            match value {
                0 => self.log.torque_off_writes += 1,
                1 => {
                    self.log.torque_on_writes += 1;
                    self.log.last_torque_on_s = Some(self.now);
                    // Re-enabling clears latched protections whose cause is gone.
                    let limit = f64::from(self.get(reg::MAX_TEMPERATURE_LIMIT));
                    self.protections.over_current = false;
                    self.protections.overload = false;
                    self.protections.over_current_for = 0.0;
                    self.protections.overload_for = 0.0;
                    if self.temperature < limit {
                        self.protections.over_temperature = false;
                    }
                }
                _ => {}
            }
        }
        true
    }

    /// The status byte of a reply (also register 65): the bit of each protection that has
    /// unloaded the motor (overheat 2, over-current 3, overload 5) and the voltage window (bit 0),
    /// as the STS firmware reports them in every reply (protocol notes, "ERR / Status bits").
    pub fn status(&self) -> ServoStatus {
        let mut bits = 0;
        if self.protections.over_temperature {
            bits |= ServoStatus::OVERHEAT;
        }
        if self.protections.over_current {
            bits |= ServoStatus::OVER_CURRENT;
        }
        if self.protections.overload {
            bits |= ServoStatus::OVERLOAD;
        }
        let v = self.supply * 10.0;
        if v > f64::from(self.get(reg::MAX_VOLTAGE_LIMIT))
            || v < f64::from(self.get(reg::MIN_VOLTAGE_LIMIT))
        {
            bits |= ServoStatus::VOLTAGE;
        }
        ServoStatus(bits)
    }

    fn refresh_feedback(&mut self) {
        let pos = self.present_position();
        self.set(reg::PRESENT_POSITION, pos);
        let speed = (self.speed / RAD_PER_STEP).round() as i32;
        self.set(reg::PRESENT_VELOCITY, speed.clamp(-32767, 32767));
        self.set(reg::PRESENT_LOAD, (self.duty * 1000.0).round() as i32);
        self.set(
            reg::PRESENT_VOLTAGE,
            (self.supply * 10.0).round().clamp(0.0, 255.0) as i32,
        );
        // The sensor register is an integer °C, of the sensor node (the winding unless an
        // extension says the sensor lags).
        let sensed = if self.extension.sensor_time_constant_s > 0.0 {
            self.sensor_temperature
        } else {
            self.temperature
        };
        self.set(
            reg::PRESENT_TEMPERATURE,
            sensed.round().clamp(0.0, 255.0) as i32,
        );
        let status = self.status().0;
        self.set(reg::STATUS, i32::from(status));
        self.set(
            reg::MOVING,
            i32::from(self.speed.abs() > 4.0 * RAD_PER_STEP),
        );
        let current = ((self.current + self.extension.current_offset_a) / AMPS_PER_CURRENT_UNIT)
            .round() as i32;
        self.set(reg::PRESENT_CURRENT, current.clamp(-32767, 32767));
    }

    /// The firmware: duty from the active mode, torque limit and protections.
    fn firmware_duty(&mut self, dt: f64) -> f64 {
        if !self.torque_enabled() || self.fw.mode != 0 {
            self.profile_restarts = true;
        } else if std::mem::take(&mut self.profile_restarts) {
            // The profile starts from where the servo is when position control takes over
            // (its torque on, or back from another mode), not from a setpoint left behind.
            self.setpoint = self.raw_position() - self.fw.homing;
            self.setpoint_speed = 0.0;
        }
        if !self.torque_enabled() {
            self.speed_integral = 0.0;
            return 0.0;
        }
        let duty = match self.fw.mode {
            1 => {
                // Speed mode: feed-forward of the back-EMF, proportional and integral action
                // on the speed error. The integral does not wind up: it stops growing while
                // the output is at its torque limit (a wheel held by a wall), and a goal of 0
                // stops the motor (no residue of the last push).
                let (goal, ke, supply) = (self.fw.speed_goal, self.plant.ke, self.supply.max(1.0));
                let error = goal - self.speed;
                let ki = SPEED_KI_PER_S * ke;
                if goal == 0.0 {
                    self.speed_integral = 0.0;
                }
                let duty = |integral: f64| (goal * ke + 2.0 * ke * error + ki * integral) / supply;
                let grown = self.speed_integral + error * dt;
                let cap = self.fw.torque_cap;
                if duty(grown).abs() <= cap || grown.abs() < self.speed_integral.abs() {
                    self.speed_integral = grown;
                }
                duty(self.speed_integral)
            }
            2 => self.fw.pwm_goal,
            _ => {
                self.advance_setpoint(dt);
                let error = (self.setpoint - self.raw_position() + self.fw.homing) * RAD_PER_STEP;
                let gain = DUTY_PER_KP_RAD * (1.0 + self.extension.duty_gain_error);
                self.fw.kp * gain * error
            }
        };
        let mut cap = self.fw.torque_cap;
        if self.protections.overload {
            cap = cap.min(self.fw.protective_duty);
        }
        duty.clamp(-cap, cap)
    }

    /// Moves the position setpoint toward the goal with the profile velocity/acceleration
    /// (0 = unlimited), within the EEPROM position limits.
    fn advance_setpoint(&mut self, dt: f64) {
        let mut goal = self.fw.goal;
        if let Some((lo, hi)) = self.fw.limits {
            goal = goal.clamp(lo, hi);
        }
        let vmax = self.fw.profile_speed;
        if vmax == 0.0 {
            self.setpoint = goal;
            self.setpoint_speed = 0.0;
            return;
        }
        let amax = self.fw.profile_accel;
        let remaining = goal - self.setpoint;
        let mut v = remaining.signum() * vmax;
        if amax > 0.0 {
            // Brake in time to stop at the goal.
            let stop_speed = (2.0 * amax * remaining.abs()).sqrt();
            v = remaining.signum() * vmax.min(stop_speed);
            let dv = (v - self.setpoint_speed).clamp(-amax * dt, amax * dt);
            v = self.setpoint_speed + dv;
        }
        let step = v * dt;
        if step.abs() >= remaining.abs() {
            self.setpoint = goal;
            self.setpoint_speed = 0.0;
        } else {
            self.setpoint += step;
            self.setpoint_speed = v;
        }
    }

    /// Advances the servo by `dt` seconds in `around` (the load on its output, the ambient
    /// temperature, the thermal speed-up). The firmware runs on its own ticks
    /// ([`FIRMWARE_PERIOD_S`]) within `dt`; the load is held over `dt`.
    pub fn step(&mut self, dt: f64, around: Surroundings) {
        let Surroundings {
            load_torque_n_m: load_torque,
            load_inertia_kg_m2: load_inertia,
            ambient_c: ambient,
            thermal_speedup,
        } = around;
        let mut left = dt;
        while left > TICK_TOLERANCE_S {
            if self.since_tick == 0.0 {
                self.duty = self.firmware_duty(FIRMWARE_PERIOD_S);
            }
            let h = left.min(self.until_tick());
            self.step_plant(h, load_torque, load_inertia);
            self.step_thermal(h * thermal_speedup, ambient);
            self.step_protections(h);
            left -= h;
            self.since_tick += h;
            if self.until_tick() <= TICK_TOLERANCE_S {
                self.since_tick = 0.0;
            }
        }
    }

    /// Time until the firmware's next tick, s: a caller whose load changes with the motion
    /// steps to it so that each of its steps holds one duty.
    pub fn until_tick(&self) -> f64 {
        FIRMWARE_PERIOD_S - self.since_tick
    }

    /// The motor, gearbox and load over `dt` at the held duty: the speed and angle integrated
    /// exactly for the linear part (the motor's back-EMF damping kt·ke/R is fast beside a light
    /// load, and an explicit step would bias it by half a step), friction as in [`coast`].
    fn step_plant(&mut self, dt: f64, load_torque: f64, load_inertia: f64) {
        let p = self.plant;
        let ext = self.extension;
        let play = ext.backlash_rad > 0.0;
        if !play {
            self.motor_speed = self.speed;
        }
        // The back-EMF is the motor's: with play in the gearbox its side may move alone.
        let driving = self.duty != 0.0 || self.torque_enabled();
        self.current = if driving {
            (self.duty * self.supply - p.ke * self.motor_speed) / p.resistance
        } else {
            0.0
        };
        // The motor's torque is `forcing − electrical·speed`.
        let (forcing, electrical) = if driving {
            (
                p.kt * self.duty * self.supply / p.resistance,
                p.kt * p.ke / p.resistance,
            )
        } else {
            (0.0, 0.0)
        };
        let motor_torque = p.kt * self.current;
        let armature = p.armature * (1.0 + ext.armature_error);
        // The friction budget: Coulomb, Stribeck's extra at rest, and a part proportional to
        // the torque the gearbox carries (different when the load drives the motor back).
        let back_driven = motor_torque * self.motor_speed < 0.0;
        let ratio = if back_driven {
            ext.friction_back_ratio
        } else {
            ext.friction_drive_ratio
        };
        let stribeck = if ext.stribeck_nm > 0.0 {
            let x = self.motor_speed / ext.stribeck_speed_rad_s;
            ext.stribeck_nm * (-x * x).exp()
        } else {
            0.0
        };
        let coulomb = p.coulomb + stribeck + ratio * motor_torque.abs();
        let motor = Drive {
            forcing,
            damping: electrical + p.viscous,
            coulomb,
        };
        let moved = if !play {
            let joint = Drive {
                forcing: forcing - load_torque,
                ..motor
            };
            let inertia = armature + load_inertia;
            let (speed, moved) = coast(self.speed, joint, inertia, dt, &mut self.decay);
            self.speed = speed;
            self.motor_speed = speed;
            moved
        } else {
            self.step_play(motor, load_torque, load_inertia, armature, dt)
        };
        self.angle += moved;
    }

    /// The gearbox with play: the motor side (armature, friction, the motor's torque) and the
    /// output (the load) move together while in contact at either end of the play, and apart
    /// inside it; reaching an end, they collide without bouncing (momentum kept). The output's
    /// move, rad.
    fn step_play(
        &mut self,
        motor: Drive,
        load_torque: f64,
        load_inertia: f64,
        armature: f64,
        dt: f64,
    ) -> f64 {
        let half = 0.5 * self.extension.backlash_rad;
        // An output with nothing on it still has its last gear's inertia.
        let output_inertia = load_inertia.max(0.05 * armature);
        let (wm, wo) = (self.motor_speed, self.speed);
        let motor_free = motor.forcing - motor.damping * wm;
        let coulomb = motor.coulomb;
        let motor_accel = if wm.abs() < STICK_SPEED && motor_free.abs() <= coulomb {
            0.0
        } else {
            (motor_free
                - coulomb
                    * if wm.abs() >= STICK_SPEED {
                        wm.signum()
                    } else {
                        motor_free.signum()
                    })
                / armature
        };
        let output_accel = -load_torque / output_inertia;
        let pushing = (self.motor_lead >= half - 1e-12 && wm >= wo && motor_accel >= output_accel)
            || (self.motor_lead <= -half + 1e-12 && wm <= wo && motor_accel <= output_accel);
        if pushing {
            let joint = Drive {
                forcing: motor.forcing - load_torque,
                ..motor
            };
            let inertia = armature + output_inertia;
            let (v, moved) = coast(wo, joint, inertia, dt, &mut self.decay);
            self.speed = v;
            self.motor_speed = v;
            self.motor_lead = self.motor_lead.clamp(-half, half);
            return moved;
        }
        let (motor_speed, motor_moved) = coast(wm, motor, armature, dt, &mut self.decay);
        let moved = dt * (wo + 0.5 * dt * output_accel);
        self.motor_speed = motor_speed;
        self.speed = wo + dt * output_accel;
        self.motor_lead += motor_moved - moved;
        if self.motor_lead.abs() > half {
            self.motor_lead = self.motor_lead.clamp(-half, half);
            let v = (armature * self.motor_speed + output_inertia * self.speed)
                / (armature + output_inertia);
            self.motor_speed = v;
            self.speed = v;
        }
        moved
    }

    fn step_thermal(&mut self, dt: f64, ambient: f64) {
        let p = self.plant;
        let ext = self.extension;
        let resistance =
            p.resistance * (1.0 + ext.resistance_tempco_per_k * (self.temperature - 25.0));
        let heat = p.idle_power + resistance * self.current * self.current + self.external_heat_w
            - (self.temperature - ambient) / p.thermal_resistance;
        let before = self.temperature;
        self.temperature += dt * heat / p.heat_capacity;
        self.max_temperature = self.max_temperature.max(self.temperature);
        self.sensor_temperature = if ext.sensor_time_constant_s > 0.0 {
            let e = (-dt / ext.sensor_time_constant_s).exp();
            self.sensor_temperature * e + (1.0 - e) * 0.5 * (before + self.temperature)
        } else {
            self.temperature
        };
    }

    fn step_protections(&mut self, dt: f64) {
        let fw = self.fw;
        let (pr, log) = (&mut self.protections, &mut self.log);
        if fw.unloading & ServoStatus::OVERHEAT != 0
            && self.temperature >= fw.temperature_limit
            && !pr.over_temperature
        {
            pr.over_temperature = true;
            log.hardware_cutoffs += 1;
        }
        pr.over_current_for = if self.current.abs() > fw.current_limit {
            pr.over_current_for + dt
        } else {
            0.0
        };
        if fw.unloading & ServoStatus::OVER_CURRENT != 0
            && !pr.over_current
            && pr.over_current_for > fw.over_current_time
        {
            pr.over_current = true;
            log.over_current_trips += 1;
        }
        pr.overload_for = if self.duty.abs() > fw.overload_duty {
            pr.overload_for + dt
        } else {
            0.0
        };
        if fw.unloading & ServoStatus::OVERLOAD != 0
            && !pr.overload
            && pr.overload_for > fw.overload_time
        {
            pr.overload = true;
            log.overload_trips += 1;
        }
    }

    /// Sets the servo up to replay logged commands (a bench's, or the model lab's): the
    /// position gain `kp`, and no protection that unloads the motor (a replay must follow the
    /// log, not the firmware's own cut-offs).
    pub fn configure_for_replay(&mut self, kp: u8) {
        self.write(reg::P_COEFFICIENT.addr, &[kp]);
        self.write(reg::UNLOADING_CONDITION.addr, &[0]);
    }

    /// Puts the servo at rest at `angle` rad, its goal where it is, with its winding (and its
    /// sensor) at `temperature_c`: the state a replay starts from, read off a record.
    pub fn place(&mut self, angle: f64, temperature_c: f64) {
        self.angle = angle;
        self.speed = 0.0;
        self.motor_lead = 0.0;
        self.motor_speed = 0.0;
        self.set_goal_to_present();
        self.temperature = temperature_c;
        self.sensor_temperature = temperature_c;
        self.max_temperature = temperature_c;
    }

    /// Writes the goal position for joint angle `angle_rad` (rounded to a step, within the
    /// register's range).
    pub fn command_goal(&mut self, angle_rad: f64) {
        let raw = (CENTER_STEP + self.horn_steps + angle_rad / RAD_PER_STEP)
            .round()
            .clamp(0.0, f64::from(STEPS_PER_TURN - 1)) as u16;
        self.write(reg::GOAL_POSITION.addr, &raw.to_le_bytes());
    }

    /// Writes Torque_Enable.
    pub fn command_torque(&mut self, on: bool) {
        self.write(reg::TORQUE_ENABLE.addr, &[u8::from(on)]);
    }

    /// Joint angle of a raw Present_Position value for this servo (homing offset applied).
    pub fn angle_of_present(&self, present: i32) -> f64 {
        (f64::from(present + self.get(reg::HOMING_OFFSET)) - CENTER_STEP - self.horn_steps)
            * RAD_PER_STEP
    }
}

/// The torque on a moving part: `forcing − damping·speed`, against Coulomb friction `coulomb`.
#[derive(Debug, Clone, Copy)]
struct Drive {
    forcing: f64,
    damping: f64,
    coulomb: f64,
}

/// `1 − e^(−x)`, remembered for the last `x`: a replay's steps are a firmware period long and
/// its damping and inertia rarely change, so most steps ask for the same decay again.
#[derive(Debug, Clone, Copy, Default)]
struct Decay {
    x: f64,
    decayed: f64,
}

impl Decay {
    fn of(&mut self, x: f64) -> f64 {
        if x != self.x {
            // Accurate when x is small (exp_m1).
            *self = Decay {
                x,
                decayed: -(-x).exp_m1(),
            };
        }
        self.decayed
    }
}

/// A part of `inertia` at `speed` under `drive` for `dt`: its speed after, and how far it
/// moved. Between stops the motion is linear (`J·ω' = forcing − damping·ω ∓ coulomb`) and is
/// integrated exactly; at rest, a drive static friction beats holds it (the stick band), and
/// friction stops a part, it never reverses it: one that comes to rest within `dt` stays
/// there unless the drive beats the friction, then starts the other way.
fn coast(speed: f64, drive: Drive, inertia: f64, dt: f64, decay: &mut Decay) -> (f64, f64) {
    let Drive {
        forcing,
        damping,
        coulomb,
    } = drive;
    let net = forcing - damping * speed;
    if speed.abs() < STICK_SPEED && net.abs() <= coulomb {
        return (0.0, 0.0);
    }
    let sign = if speed.abs() >= STICK_SPEED {
        speed.signum()
    } else {
        net.signum()
    };
    let push = forcing - sign * coulomb;
    let rate = damping / inertia;
    // Without damping worth the name over the step, the law is a constant acceleration.
    let undamped = rate * dt < 1e-9;
    // The speed the part tends to under this friction's sign (when damped).
    let terminal = push / damping;
    // Speed and distance after `t` under this friction's sign.
    let mut at = |t: f64| -> (f64, f64) {
        if undamped {
            let a = (push - damping * speed) / inertia;
            (speed + a * t, t * (speed + 0.5 * a * t))
        } else {
            let decayed = decay.of(rate * t);
            (
                speed + (terminal - speed) * decayed,
                terminal * t + (speed - terminal) * decayed / rate,
            )
        }
    };
    let (end, moved) = at(dt);
    if end * sign >= 0.0 {
        return (end, moved);
    }
    // It stops within the step: when (solved on the same law), how far, and what then.
    let stop = if undamped {
        -speed * inertia / (push - damping * speed)
    } else {
        ((speed - terminal) / -terminal).ln() / rate
    };
    // (Not finite only for a part inside the stick band not yet turned: it rests.)
    let stop = if stop.is_finite() {
        stop.clamp(0.0, dt)
    } else {
        dt
    };
    let (_, to_stop) = at(stop);
    if forcing.abs() <= coulomb || stop >= dt {
        return (0.0, to_stop);
    }
    let (after, moved_after) = coast(0.0, drive, inertia, dt - stop, decay);
    (after, to_stop + moved_after)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::description::RobotDescription;

    fn servo(model: &str) -> Servo {
        let d = RobotDescription::nori_a3();
        let r = d.rating(model).unwrap();
        Servo::new(1, r.model, r, 0.0, 25.0)
    }

    fn write_u16(s: &mut Servo, r: Register, v: i32) {
        let raw = match r.encoding {
            reg::Encoding::SignMagnitude(b) => encode_sign_magnitude(v, b).unwrap(),
            reg::Encoding::Unsigned => v as u16,
        };
        if r.size == 2 {
            s.write(r.addr, &raw.to_le_bytes());
        } else {
            s.write(r.addr, &[raw as u8]);
        }
    }

    #[test]
    fn plant_matches_ratings_at_stall() {
        let s = servo("sts3215");
        // At full duty and zero speed the current is the rated stall current and the torque the
        // rated stall torque (30 kg·cm).
        let i = s.supply / s.plant.resistance;
        assert!((i - 2.7).abs() < 1e-9);
        assert!((s.plant.kt * i - 30.0 * 0.0980665).abs() < 1e-9);
    }

    #[test]
    fn speed_mode_holds_the_goal_speed_under_a_steady_load() {
        let mut s = servo("sts3215");
        write_u16(&mut s, reg::OPERATING_MODE, 1);
        write_u16(&mut s, reg::TORQUE_ENABLE, 1);
        // Within what the STS3215 sustains against this load at 12 V (about 3.2 rad/s).
        let goal = 2.5;
        write_u16(
            &mut s,
            reg::GOAL_VELOCITY,
            (goal / RAD_PER_STEP).round() as i32,
        );
        // A wheel: the base's inertia and its rolling resistance (0.2 N·m·s/rad).
        for _ in 0..1000 {
            let load = 0.2 * s.speed;
            s.step(0.001, Surroundings::BENCH.torque(load).inertia(0.05));
        }
        assert!((s.speed - goal).abs() < 0.02 * goal, "{} rad/s", s.speed);
        // Held against nearly its stall torque for a while: the speed is what the torque
        // gives, the integral does not wind up, and a goal of 0 leaves no push behind.
        for _ in 0..500 {
            s.step(0.001, Surroundings::BENCH.torque(2.5).inertia(0.05));
        }
        assert!(s.speed < goal / 2.0, "{} rad/s", s.speed);
        write_u16(&mut s, reg::GOAL_VELOCITY, 0);
        for _ in 0..200 {
            let load = 0.2 * s.speed;
            s.step(0.001, Surroundings::BENCH.torque(load).inertia(0.05));
        }
        assert!(s.speed.abs() < 0.05, "{} rad/s after a goal of 0", s.speed);
        assert!(s.duty.abs() < 0.05, "still pushing at duty {}", s.duty);
    }

    /// The profile starts from where the servo is when position control takes over (its
    /// torque on, or back from speed mode), whatever setpoint it left behind: a goal written
    /// equal to the present position holds it there, even after its homing offset changed.
    #[test]
    fn a_goal_at_the_present_position_holds_when_position_control_takes_over() {
        let mut s = servo("sts3215");
        let run = |s: &mut Servo, seconds: f64| {
            for _ in 0..(seconds * 1000.0) as usize {
                s.step(0.001, Surroundings::BENCH.inertia(0.01));
            }
        };
        let goal_at_present = |s: &mut Servo| {
            let mut b = [0u8; 2];
            assert!(s.read(reg::PRESENT_POSITION.addr, 2, &mut b));
            write_u16(s, reg::GOAL_POSITION, i32::from(u16::from_le_bytes(b)));
        };
        write_u16(&mut s, reg::GOAL_VELOCITY, 300);
        write_u16(&mut s, reg::TORQUE_ENABLE, 1);
        write_u16(&mut s, reg::GOAL_POSITION, 2900);
        run(&mut s, 4.0);
        // Torque off, moved by hand, a new homing offset (RAM only): then held where it is.
        write_u16(&mut s, reg::TORQUE_ENABLE, 0);
        s.angle -= 1.0;
        write_u16(&mut s, reg::HOMING_OFFSET, -700);
        goal_at_present(&mut s);
        write_u16(&mut s, reg::TORQUE_ENABLE, 1);
        let held = s.angle;
        run(&mut s, 2.0);
        assert!((s.angle - held).abs() < 0.02, "{held} → {} rad", s.angle);
        // Turned in speed mode, its offset changed there, then back to position mode.
        write_u16(&mut s, reg::OPERATING_MODE, 1);
        write_u16(&mut s, reg::GOAL_VELOCITY, -300);
        run(&mut s, 2.0);
        write_u16(&mut s, reg::HOMING_OFFSET, 500);
        goal_at_present(&mut s);
        write_u16(&mut s, reg::GOAL_VELOCITY, 300);
        write_u16(&mut s, reg::OPERATING_MODE, 0);
        let held = s.angle;
        run(&mut s, 2.0);
        assert!((s.angle - held).abs() < 0.02, "{held} → {} rad", s.angle);
    }

    #[test]
    fn position_loop_follows_a_goal() {
        let mut s = servo("sts3215");
        write_u16(&mut s, reg::TORQUE_ENABLE, 1);
        write_u16(&mut s, reg::GOAL_POSITION, 2048 + 300);
        for _ in 0..2000 {
            s.step(0.001, Surroundings::BENCH);
        }
        let mut fb = [0u8; 15];
        s.read(reg::FEEDBACK_ADDR, 15, &mut fb);
        let f = feetech::FeedbackBlock::parse(&fb).unwrap();
        // Coulomb friction leaves a small steady-state error, as on the real servo.
        assert!((f.position - 2348).abs() <= 10, "position {}", f.position);
        assert_eq!(s.log.goal_writes, 1);
    }

    /// An STS3250 swinging 1 kg at 0.1 m: chasing a sine with goals written every 20.3 ms (off
    /// the firmware's ticks), then released at 2 s to swing free. Stepped at `max_step` (the
    /// pendulum's torque taken at each step's middle), the angle at each goal write.
    fn pendulum_run(max_step: f64) -> Vec<f64> {
        let d = RobotDescription::nori_a3();
        let r = d.rating("sts3250").unwrap();
        let mut s = Servo::new(1, r.model, r, 0.0, 25.0);
        s.configure_for_replay(32);
        s.command_torque(true);
        let (m, l, period) = (1.0, 0.1, 0.0203);
        let mut angles = Vec::new();
        for k in 0..200 {
            let t = k as f64 * period;
            angles.push(s.angle);
            s.command_goal(1.2 * (1.3 * t).sin());
            if t >= 2.0 {
                s.command_torque(false);
            }
            let mut left = period;
            while left > 1e-12 {
                let h = left.min(max_step);
                s.step(h, Surroundings::BENCH.pendulum(m, l, &s, h));
                left -= h;
            }
        }
        angles
    }

    /// The firmware sets the duty on its own ticks and the plant is integrated exactly between
    /// them: a model fitted through 1 ms steps is the servo a 0.1 ms reference runs (an
    /// explicit step biased the motor's damping by half a step, and a duty set at every step
    /// made the position loop depend on the caller's step: a step of the encoder apart).
    #[test]
    fn the_motion_does_not_depend_on_the_step_it_is_integrated_with() {
        let fine = pendulum_run(1e-4);
        // It does move, both under the loop and free.
        let swing = |a: &[f64]| a.iter().fold(0.0_f64, |m, x| m.max(x.abs()));
        assert!(swing(&fine[..90]) > 0.8 && swing(&fine[100..]) > 0.3);
        for max_step in [1e-3, 7e-4] {
            let coarse = pendulum_run(max_step);
            let worst = fine
                .iter()
                .zip(&coarse)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f64::max);
            assert!(
                worst < 0.1 * RAD_PER_STEP,
                "{max_step} s steps: {:.3} encoder steps from the 0.1 ms run",
                worst / RAD_PER_STEP
            );
        }
    }

    /// Friction stops a part where the exact law says (`ω = −c/b + (ω₀ + c/b)·e^(−b·t/J)`
    /// reaches 0 at `t = J/b·ln(1 + b·ω₀/c)`), and holds it there unless the drive beats it,
    /// then starts it the other way, whatever the step.
    #[test]
    fn friction_stops_a_part_where_the_exact_law_says() {
        let drive = |forcing| Drive {
            forcing,
            damping: 1.0,
            coulomb: 0.5,
        };
        let (j, w0) = (0.1, 2.0);
        let stop = j * (1.0_f64 + w0 / 0.5).ln();
        let travelled = -0.5 * stop + (w0 + 0.5) * (1.0 - (-stop / j).exp()) * j;
        let (w, moved) = coast(w0, drive(0.0), j, 1.0, &mut Decay::default());
        assert_eq!(w, 0.0);
        assert!((moved - travelled).abs() < 1e-12, "{moved} for {travelled}");
        // Before the stop, the law itself.
        let (w, _) = coast(w0, drive(0.0), j, 0.1, &mut Decay::default());
        assert!((w - (-0.5 + 2.5 * (-1.0_f64).exp())).abs() < 1e-12, "{w}");
        // A drive of 0.8 N·m against 0.5 of friction turns it: moving back at the step's end.
        let (w, moved) = coast(w0, drive(-0.8), j, 1.0, &mut Decay::default());
        assert!(w < -0.2 && moved < travelled, "{w} rad/s, {moved} rad");
        // At rest, a drive friction beats holds it.
        assert_eq!(
            coast(0.0, drive(0.4), j, 1.0, &mut Decay::default()),
            (0.0, 0.0)
        );
    }

    #[test]
    fn torque_off_means_no_current() {
        let mut s = servo("sts3215");
        write_u16(&mut s, reg::GOAL_POSITION, 3000);
        for _ in 0..100 {
            s.step(0.001, Surroundings::BENCH.torque(0.5));
        }
        assert_eq!(s.current, 0.0);
    }

    #[test]
    fn held_stall_heats_and_the_cutoff_drops_output_and_announces_it() {
        let mut s = servo("sts3215");
        write_u16(&mut s, reg::MAX_TEMPERATURE_LIMIT, 60);
        write_u16(
            &mut s,
            reg::UNLOADING_CONDITION,
            i32::from(ServoStatus::OVERHEAT),
        );
        write_u16(&mut s, reg::TORQUE_ENABLE, 1);
        write_u16(&mut s, reg::GOAL_POSITION, 2048 + 400);
        // A load the servo cannot move: it stalls at full duty.
        let mut t = 0.0;
        while !s.protections.over_temperature && t < 3600.0 {
            s.step(0.01, Surroundings::BENCH.torque(10.0));
            t += 0.01;
        }
        assert!(s.protections.over_temperature, "never cut off");
        assert!(s.temperature >= 60.0 && s.temperature < 60.5);
        s.step(0.01, Surroundings::BENCH.torque(10.0));
        assert_eq!(s.current, 0.0);
        assert_eq!(
            s.status().0,
            ServoStatus::OVERHEAT,
            "the STS firmware reports its overheat protection in the status byte"
        );
        assert_eq!(s.log.hardware_cutoffs, 1);
    }

    #[test]
    fn over_current_protection_trips_after_its_time() {
        let mut s = servo("sts3215");
        write_u16(&mut s, reg::PROTECTION_CURRENT, 200); // 1.3 A
        write_u16(&mut s, reg::OVER_CURRENT_PROTECTION_TIME, 10); // 100 ms
        write_u16(&mut s, reg::TORQUE_ENABLE, 1);
        write_u16(&mut s, reg::GOAL_POSITION, 2048 + 400);
        let mut steps = 0;
        while !s.protections.over_current && steps < 1000 {
            s.step(0.001, Surroundings::BENCH.torque(10.0));
            steps += 1;
        }
        assert!((100..=110).contains(&steps), "tripped after {steps} ms");
        assert!(s.status().over_current());
        s.step(0.001, Surroundings::BENCH.torque(10.0));
        assert_eq!(s.current, 0.0);
    }

    #[test]
    fn eeprom_writes_need_unlock_and_a_change() {
        let mut s = servo("sts3215");
        write_u16(&mut s, reg::MAX_TEMPERATURE_LIMIT, 60);
        assert_eq!(s.log.eeprom_writes, 0, "locked EEPROM must not be flashed");
        s.reboot();
        assert_eq!(s.get(reg::MAX_TEMPERATURE_LIMIT), 70);
        write_u16(&mut s, reg::LOCK, 0);
        write_u16(&mut s, reg::MAX_TEMPERATURE_LIMIT, 60);
        write_u16(&mut s, reg::MAX_TEMPERATURE_LIMIT, 60);
        assert_eq!(s.log.eeprom_writes, 1);
        s.reboot();
        assert_eq!(s.get(reg::MAX_TEMPERATURE_LIMIT), 60);
    }

    #[test]
    fn a_horn_on_another_tooth_moves_the_reading_not_the_joint() {
        let mut s = servo("sts3215");
        s.fit_horn(300.0);
        let mut feedback = [0u8; 2];
        assert!(s.read(reg::PRESENT_POSITION.addr, 2, &mut feedback));
        assert_eq!(u16::from_le_bytes(feedback), 2348);
        assert!((s.angle_of_present(2348)).abs() < 1e-12);
        // Torque on at the goal it was fitted with: it holds where it is.
        write_u16(&mut s, reg::TORQUE_ENABLE, 1);
        for _ in 0..500 {
            s.step(0.001, Surroundings::BENCH);
        }
        assert!(s.angle.abs() < 0.01, "{}", s.angle);
        s.command_goal(0.5);
        for _ in 0..2000 {
            s.step(0.001, Surroundings::BENCH);
        }
        assert!((s.angle - 0.5).abs() < 0.02, "{}", s.angle);
    }

    #[test]
    fn a_new_id_and_rate_act_at_once_and_last_only_when_unlocked() {
        let mut s = servo("sts3215");
        assert_eq!((s.id, s.line_baud()), (1, Some(1_000_000)));
        write_u16(&mut s, reg::ID, 9);
        write_u16(&mut s, reg::BAUD_RATE, 6);
        assert_eq!((s.id, s.line_baud()), (9, Some(57_600)));
        s.reboot();
        assert_eq!(
            (s.id, s.line_baud()),
            (1, Some(1_000_000)),
            "locked: not flashed"
        );
        write_u16(&mut s, reg::LOCK, 0);
        write_u16(&mut s, reg::ID, 9);
        s.reboot();
        assert_eq!(s.id, 9);
        write_u16(&mut s, reg::LOCK, 0);
        write_u16(&mut s, reg::BAUD_RATE, 8);
        assert_eq!(s.line_baud(), None, "code 8 is no rate");
    }
}
