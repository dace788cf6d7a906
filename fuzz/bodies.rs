//! Fuzz bodies: every decoder that faces bytes from outside the process, with the invariants
//! that must hold for any input. Shared, unchanged, by the cargo-fuzz targets
//! (`fuzz/fuzz_targets/*.rs`, nightly) and by the bounded property tests that run in CI on
//! stable (`tests/tests/fuzz_bodies.rs`). A body panics only when an invariant breaks.

#![allow(dead_code, clippy::unwrap_used, clippy::expect_used)]

use std::time::Duration;

/// The servo side of the line: the driver's feedback collection (decoder, status packets,
/// feedback blocks, id matching) over a transport that delivers `data` in pieces whose sizes
/// come from the data itself; then the raw decoder, status and instruction parsers directly.
pub fn status_decoder(data: &[u8]) {
    use bus_driver::bus::Bus;
    use feetech::registers::FeedbackBlock;
    use feetech::{Decoder, Instruction, StatusPacket, MAX_PACKET};

    struct Replay<'a> {
        data: &'a [u8],
        piece: usize,
        sent: usize,
    }
    impl bus_driver::Transport for Replay<'_> {
        fn baud(&self) -> u32 {
            1_000_000
        }
        fn send(&mut self, bytes: &[u8]) -> Result<(), bus_driver::transport::TransportError> {
            self.sent += bytes.len();
            Ok(())
        }
        fn receive(
            &mut self,
            buf: &mut [u8],
            _timeout: Duration,
        ) -> Result<usize, bus_driver::transport::TransportError> {
            let n = self.piece.min(self.data.len()).min(buf.len());
            buf[..n].copy_from_slice(&self.data[..n]);
            self.data = &self.data[n..];
            Ok(n)
        }
        fn discard_input(&mut self) -> Result<(), bus_driver::transport::TransportError> {
            Ok(())
        }
    }

    let piece = 1 + usize::from(data.first().copied().unwrap_or(0) % 97);
    let ids = [1u8, 2, 3, 4, 5, 6, 7, 8];
    let mut bus = Bus::new(
        Replay {
            data,
            piece,
            sent: 0,
        },
        Duration::ZERO,
    );
    let mut out = [None; 8];
    bus.request_feedback(&ids).unwrap();
    let answered = bus.collect_feedback(&ids, &mut out).unwrap();
    assert!(answered <= ids.len());
    assert_eq!(answered, out.iter().filter(|o| o.is_some()).count());
    let c = bus.counters;
    assert_eq!(c.replies as usize, answered);
    assert_eq!(c.missing as usize, ids.len() - answered);
    // Every accepted reply is a well-formed packet of an id we asked, found in the input.
    for (slot, o) in out.iter().enumerate() {
        if let Some((block, _)) = o {
            let id = ids[slot];
            let found = data.windows(4 + 17).any(|w| {
                w[0] == 0xFF
                    && w[1] == 0xFF
                    && w[2] == id
                    && w[3] == 17
                    && FeedbackBlock::parse(&w[5..20]).as_ref() == Some(block)
            });
            assert!(found, "servo {id}'s block is not in the input");
        }
    }

    // The raw decoder: bounded progress, every frame re-encodes to itself.
    let mut d = Decoder::new();
    let mut rest = data;
    let mut steps = 0usize;
    let bound = 2 * data.len() + 4;
    loop {
        let taken = d.push(rest);
        rest = &rest[taken..];
        let mut any = false;
        while let Some(r) = d.next_frame() {
            any = true;
            steps += 1;
            assert!(steps <= bound, "decoder does not progress");
            let Ok(frame) = r else { continue };
            let mut buf = [0u8; MAX_PACKET];
            let n = frame.encode(&mut buf).expect("a decoded frame encodes");
            let mut again = Decoder::new();
            again.push(&buf[..n]);
            assert_eq!(again.next_frame(), Some(Ok(frame.clone())));
            if let Ok(status) = StatusPacket::parse(&frame) {
                let _ = FeedbackBlock::parse(status.params);
            }
            let _ = Instruction::parse(&frame);
        }
        if rest.is_empty() {
            break;
        }
        if taken == 0 && !any {
            d.clear();
        }
    }
    while d.finish().is_some() {
        steps += 1;
        assert!(steps <= bound, "finish does not progress");
    }
}

/// The simulator's device side (a servo bus fed by the host): any bytes are decoded, counted
/// and answered or ignored; nothing panics and the replies stay bounded.
pub fn device_side(data: &[u8]) {
    thread_local! {
        static BUS: std::cell::RefCell<Option<sim::SimBus>> = const { std::cell::RefCell::new(None) };
    }
    BUS.with(|b| {
        let mut b = b.borrow_mut();
        let bus = b.get_or_insert_with(|| {
            let d = sim::RobotDescription::nori_a3();
            sim::SimBus::new(&d, d.bus("left_arm").unwrap())
        });
        let t = bus.time();
        bus.receive(t, data);
        let mut replies = 0;
        while let Some(r) = bus.pop_due(f64::MAX) {
            replies += r.bytes.len();
        }
        // At most one status packet per id byte received, each at most MAX_PACKET bytes.
        assert!(replies <= data.len().max(1) * feetech::MAX_PACKET);
    });
}

/// A versioned fleet message from the network: decoded as each message type; a message that
/// decodes re-encodes to a stable form; an action chunk that passes the gate is the right
/// shape, finite and inside every joint's range.
pub fn wire_messages(data: &[u8]) {
    use fleet_agent::gate::{ActionGate, GateConfig, Range};
    use fleet_agent::schema::{
        decode, encode, ActionChunk, EventMsg, LayoutMsg, ObservationMsg, StateMsg,
    };

    fn stable<T: serde::Serialize + for<'de> serde::Deserialize<'de>>(data: &[u8]) {
        if let Ok(m) = decode::<T>(data) {
            let bytes = encode(&m);
            let again: T = decode(&bytes).expect("a decoded message decodes after re-encoding");
            assert_eq!(encode(&again), bytes);
        }
    }
    stable::<StateMsg>(data);
    stable::<LayoutMsg>(data);
    stable::<EventMsg>(data);
    stable::<ObservationMsg>(data);
    stable::<ActionChunk>(data);

    let ranges = [
        Range {
            min: -1.0,
            max: 1.0,
        },
        Range {
            min: -2.0,
            max: 0.5,
        },
        Range { min: 0.0, max: 3.0 },
    ];
    let config = GateConfig {
        max_age_ns: 250_000_000,
        max_steps: 128,
        max_span_ns: 3_000_000_000,
        body: fleet_agent::gate::BodyLimits {
            lift_m: fleet_agent::gate::Range {
                min: 0.01,
                max: 0.75,
            },
            max_linear_m_s: 0.2,
            max_angular_rad_s: 1.0,
        },
    };
    let mut gate = ActionGate::new(config);
    let now = 10_000_000_000u64;
    if let Ok(chunk) = gate.check(data, now, &ranges) {
        let joints = usize::from(chunk.joint_count);
        assert_eq!(joints, ranges.len());
        assert!(!chunk.step_offsets_ns.is_empty() && chunk.step_offsets_ns.len() <= 128);
        assert_eq!(chunk.targets.len(), chunk.step_offsets_ns.len() * joints);
        assert!(chunk.step_offsets_ns.windows(2).all(|w| w[0] < w[1]));
        assert!(now.saturating_sub(chunk.observation_ns) <= config.max_age_ns);
        for (i, v) in chunk.targets.iter().enumerate() {
            let r = ranges[i % joints];
            if chunk.joint_mask & (1 << (i % joints)) != 0 {
                assert!(
                    v.is_finite() && *v >= r.min && *v <= r.max,
                    "{v} passed the gate"
                );
            }
        }
    }
    assert_eq!(
        gate.accepted() + gate.rejected().iter().sum::<u64>(),
        1,
        "every chunk is counted once"
    );
}

/// The text of `data`, lossily (configuration files are read as UTF-8 text).
fn text(data: &[u8]) -> std::borrow::Cow<'_, str> {
    String::from_utf8_lossy(data)
}

/// A bus-driver configuration and calibration (split at the first NUL byte; the embedded
/// calibration when there is none): refused with a reason, or accepted only when every safety
/// bound holds.
pub fn driver_config(data: &[u8]) {
    use bus_driver::config::DEFAULT_CALIBRATION_TOML;
    use bus_driver::LoadedConfig;
    let (config, calibration) = match data.iter().position(|&b| b == 0) {
        Some(i) => (text(&data[..i]), text(&data[i + 1..])),
        None => (text(data), DEFAULT_CALIBRATION_TOML.into()),
    };
    match LoadedConfig::parse_texts(&config, "fuzz.toml", &calibration, "fuzz-calibration.toml") {
        Ok(c) => {
            let d = &c.config;
            assert!(d.rate_hz.is_finite() && (1.0..=1000.0).contains(&d.rate_hz));
            assert!(d.safe_hold_torque_percent > 0.0 && d.safe_hold_torque_percent <= 100.0);
            assert!((1..=10_000).contains(&d.goal_max_age_ms));
            for b in d.backstops.values() {
                assert!(b.max_temperature_c <= 60);
                assert!(b.max_torque_limit_percent > 0.0 && b.max_torque_limit_percent <= 100.0);
            }
            for (name, cal) in &c.calibration.joint {
                assert!(cal.validate(name).is_ok());
            }
            let _ = d.period();
        }
        Err(e) => {
            let msg = e.to_string();
            assert!(msg.contains("fuzz"), "the error names no file: {msg}");
        }
    }
}

/// A supervisor configuration: refused with a reason, or its thermal tier below the firmware.
pub fn supervisor_config(data: &[u8]) {
    use supervisor::config::SupervisorConfig;
    match SupervisorConfig::parse(&text(data), "fuzz.toml") {
        Ok(c) => {
            assert!(c.thermal.trip_c < 60.0 && c.thermal.reenable_below_c < c.thermal.trip_c);
            assert!(c.stall.window >= 2);
        }
        Err(e) => assert!(e.to_string().contains("fuzz.toml")),
    }
}

/// A fleet-agent configuration: refused with a reason, or its limits sane.
pub fn agent_config(data: &[u8]) {
    use fleet_agent::AgentConfig;
    match AgentConfig::parse(&text(data), "fuzz.toml") {
        Ok(c) => {
            assert!(c.actions.blend_new > 0.0 && c.actions.blend_new <= 1.0);
            assert!(c.actions.forward_hz > 0.0 && c.actions.forward_hz <= 1000.0);
            let _ = c.gate();
        }
        Err(e) => assert!(e.to_string().contains("fuzz.toml")),
    }
}

/// The model lab's telemetry CSV: rows parsed or refused with a reason; accepted rows aligned
/// on a grid without panicking or a grid that grows with the square of the input.
pub fn telemetry_csv(data: &[u8]) {
    use model_lab::data::{parse_csv, Dataset, Meta};
    let Ok(rows) = parse_csv(&text(data), "fuzz.csv") else {
        return;
    };
    if let Ok(d) = Dataset::from_runs(vec![("fuzz.csv".into(), rows)], Meta::default(), "fuzz.csv")
    {
        assert!(d.motors.len() <= model_lab::data::MAX_MOTORS);
        for col in [&d.temperature, &d.current, &d.position] {
            assert_eq!(col.len(), d.motors.len());
            assert!(col.iter().all(|c| c.len() == d.t.len()));
        }
    }
}

/// The lidar's line: the protocol decoder and the revolution assembler over any bytes, from
/// inside a scan stream (first byte odd) or waiting for an answer. Whatever comes in, a node
/// has an angle below 360°, and a published revolution holds at most a frame's points, each
/// bearing in [0, 2π) and each range 0 or within the limits.
pub fn lidar_stream(data: &[u8]) {
    use lidar::protocol::{Decoder, Event, FULL_TURN_Q6};
    use lidar::scan::{Assembler, ScanLimits};
    use telemetry::sensors::MAX_SCAN_POINTS;

    let limits = ScanLimits::C1;
    let mut decoder = Decoder::new();
    let mut assembler = Assembler::new(limits);
    if data.first().is_some_and(|b| b & 1 == 1) {
        for b in [0xA5, 0x5A, 0x05, 0x00, 0x00, 0x40, 0x81] {
            decoder.push(b);
        }
    }
    for (i, &b) in data.iter().enumerate() {
        let Some(Event::Node(node)) = decoder.push(b) else {
            continue;
        };
        assert!(node.angle_q6 < FULL_TURN_Q6);
        if assembler.push(node, i as u64) {
            let scan = assembler.scan_mut();
            assert!(scan.point_count as usize <= MAX_SCAN_POINTS);
            for p in scan.points() {
                assert!((0.0..std::f32::consts::TAU).contains(&p.angle_rad), "{p:?}");
                let r = f64::from(p.range_m);
                assert!(r == 0.0 || (limits.min_range_m..=limits.max_range_m).contains(&r));
            }
        }
    }
}

/// A camera's byte stream (the simulator's framing): any bytes, in pieces whose sizes come
/// from the data; every frame read is one its header describes, never longer than the bound.
pub fn camera_stream(data: &[u8]) {
    use camera::stream::StreamReader;
    const MAX: usize = 4096;
    let mut reader = StreamReader::new(MAX);
    let piece = 1 + usize::from(data.first().copied().unwrap_or(0) % 61);
    for chunk in data.chunks(piece) {
        reader.push(chunk);
        while let Some((header, payload)) = reader.next_frame() {
            assert_eq!(payload.len(), header.len as usize);
            assert!(payload.len() <= MAX);
        }
    }
}
