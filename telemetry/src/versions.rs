//! The rule that lets two versions of the stack meet on one machine safely: a frame whose layout
//! changes gets a new version in its `#[type_name]`, so a process of the other version is
//! refused by the plane, naming both, instead of reading the bytes as its own.
//!
//! `frame-layouts.txt` records each version's layout: its size, its alignment and a fingerprint
//! of its fields (names, order, integer or float or bool, array lengths, from the derived `Debug`
//! of its default). A layout that changes under a kept version fails here; an old version's line
//! stays, as the record of what older processes speak.

use crate::frames::{
    BusHealth, Directives, GoalFrame, GripFrame, Heartbeat, JointLayout, JointState,
    SupervisorCommand, SupervisorEvent,
};
use crate::motion::{BaseCommand, BaseState, BodyFrames, LiftAllowance, LiftCommand, LiftState};
use crate::plane::{topic, type_name, Plane, PlaneError};
use crate::sensors::{CameraFrameHeader, LidarScan};
use crate::wire::{BlackboxSave, WireFrame};
use iceoryx2::prelude::ZeroCopySend;
use iceoryx2::service::static_config::message_type_details::{TypeDetail, TypeVariant};

const RECORDED: &str = include_str!("../frame-layouts.txt");

/// `name size align fingerprint` of a frame type as this build has it.
fn layout<T: ZeroCopySend + Default + std::fmt::Debug>() -> String {
    let detail = TypeDetail::new::<T>(TypeVariant::FixedSize);
    let name = type_name(&detail);
    let fields = shape(&format!("{:?}", T::default()));
    format!(
        "{name} {} {} {:016x}",
        detail.size(),
        detail.alignment(),
        fnv1a(&fields)
    )
}

/// The Debug text with every value replaced by its kind: the fields and their order stay, the
/// default values (which may change freely) go.
fn shape(debug: &str) -> String {
    let mut out = String::new();
    let mut token = String::new();
    let flush = |token: &mut String, out: &mut String| {
        if !token.is_empty() {
            let kind = match token.as_str() {
                "true" | "false" => "b",
                "NaN" | "inf" | "-inf" => "f",
                t if t.starts_with(|c: char| c.is_ascii_digit() || c == '-') => {
                    if t.contains(['.', 'e']) {
                        "f"
                    } else {
                        "i"
                    }
                }
                t => t,
            };
            out.push_str(kind);
            token.clear();
        }
    };
    for c in debug.chars() {
        if c.is_alphanumeric() || "_.-+".contains(c) {
            token.push(c);
        } else {
            flush(&mut token, &mut out);
            out.push(c);
        }
    }
    flush(&mut token, &mut out);
    out
}

fn fnv1a(text: &str) -> u64 {
    text.bytes().fold(0xcbf2_9ce4_8422_2325, |h, b| {
        (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3)
    })
}

fn current() -> Vec<String> {
    vec![
        layout::<JointState>(),
        layout::<GoalFrame>(),
        layout::<JointLayout>(),
        layout::<Directives>(),
        layout::<Heartbeat>(),
        layout::<SupervisorEvent>(),
        layout::<GripFrame>(),
        layout::<SupervisorCommand>(),
        layout::<BusHealth>(),
        layout::<BaseCommand>(),
        layout::<BaseState>(),
        layout::<LiftCommand>(),
        layout::<LiftAllowance>(),
        layout::<LiftState>(),
        layout::<BodyFrames>(),
        layout::<CameraFrameHeader>(),
        layout::<LidarScan>(),
        layout::<WireFrame>(),
        layout::<BlackboxSave>(),
    ]
}

#[test]
fn a_frame_whose_layout_changed_has_a_new_version() {
    let recorded: Vec<&str> = RECORDED
        .lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .collect();
    let mut wrong = Vec::new();
    for line in current() {
        let name = line.split(' ').next().unwrap_or_default();
        assert!(
            name.starts_with("nori::")
                && name
                    .rsplit_once('/')
                    .is_some_and(|(_, v)| v.parse::<u32>().is_ok()),
            "{name}: a frame's type name is nori::<Name>/<version>"
        );
        match recorded.iter().find(|r| r.split(' ').next() == Some(name)) {
            Some(r) if *r == line => {}
            Some(r) => wrong.push(format!(
                "{name} changed its layout ({r} → {line}): give it a new version in its \
                 #[type_name] and add its line, keeping the old one"
            )),
            None => wrong.push(format!("{name} is not recorded: add `{line}`")),
        }
    }
    assert!(wrong.is_empty(), "{}", wrong.join("\n"));
}

#[test]
fn the_fingerprint_sees_a_field_moved_or_retyped_but_not_a_default() {
    assert_ne!(shape("A { a: 0, b: 0.0 }"), shape("A { b: 0.0, a: 0 }"));
    assert_ne!(shape("A { a: 0 }"), shape("A { a: 0.0 }"));
    assert_ne!(shape("A { a: [0, 0] }"), shape("A { a: [0, 0, 0] }"));
    assert_eq!(
        shape("A { a: 5, b: -1.5, c: NaN }"),
        shape("A { a: 0, b: 2e3, c: 0.0 }")
    );
    assert_eq!(shape("A { on: true }"), shape("A { on: false }"));
}

/// Two frame types of one name and two versions, as two builds of the stack would have them.
mod probe {
    use iceoryx2::prelude::ZeroCopySend;

    #[repr(C)]
    #[derive(Debug, Default, Clone, Copy, ZeroCopySend)]
    #[type_name("nori::Probe/1")]
    pub struct V1 {
        pub a: u32,
    }

    #[repr(C)]
    #[derive(Debug, Default, Clone, Copy, ZeroCopySend)]
    #[type_name("nori::Probe/2")]
    pub struct V2 {
        pub a: u32,
        pub b: f32,
    }
}

#[test]
fn a_process_of_another_version_is_refused_naming_both() {
    let domain = format!("nori_versions_{}", std::process::id());
    let old = Plane::open(&domain, "old").unwrap();
    let new = Plane::open(&domain, "new").unwrap();
    let v1 = topic::<probe::V1>("nori/test/probe", 1, 4, 2, 2);
    let v2 = topic::<probe::V2>("nori/test/probe", 1, 4, 2, 2);
    let _running = old.publisher(&v1).unwrap();
    let Err(e) = new.subscriber(&v2) else {
        panic!("a subscriber of the other version was let in");
    };
    assert!(
        matches!(&e, PlaneError::OtherVersion { ours, theirs, .. }
            if ours == "nori::Probe/2" && theirs == "nori::Probe/1"),
        "{e:?}"
    );
    let said = e.to_string();
    assert!(
        said.contains("nori::Probe/1") && said.contains("nori::Probe/2"),
        "{said}"
    );
    // The same version still meets.
    assert!(new.subscriber(&v1).is_ok());
}
