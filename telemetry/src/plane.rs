//! The state plane: the iceoryx2 services of one robot, each defined once as a [`Topic`] with its
//! payload type and QoS (the first process to create a service fixes its QoS; every other must
//! ask for no more, so they are never spelled twice).
//!
//! A *domain* (the iceoryx2 prefix) separates robots or test runs on one machine.

use crate::frames::{
    Directives, GoalFrame, GripFrame, Heartbeat, JointLayout, JointState, SupervisorCommand,
    SupervisorEvent,
};
use crate::motion::{BaseCommand, BaseState, BodyFrames, LiftAllowance, LiftCommand, LiftState};
use crate::sensors::{CameraFrameHeader, LidarScan};
use crate::wire::{BlackboxSave, WireFrame};
use iceoryx2::node::{NodeCreationFailure, NodeListFailure};
use iceoryx2::port::publisher::{Publisher, PublisherCreateError};
use iceoryx2::port::subscriber::{Subscriber, SubscriberCreateError};
use iceoryx2::port::{LoanError, SendError};
use iceoryx2::prelude::*;
use iceoryx2::service::builder::publish_subscribe::{
    PublishSubscribeOpenError, PublishSubscribeOpenOrCreateError,
};
use iceoryx2::service::service_name::ServiceNameError;
use iceoryx2::service::static_config::message_type_details::{TypeDetail, TypeVariant};
use iceoryx2::service::static_config::messaging_pattern::MessagingPattern as ServicePattern;
use std::marker::PhantomData;
use thiserror::Error;

/// The default domain.
pub const DEFAULT_DOMAIN: &str = "nori";

/// A publisher of `T` on the plane.
pub type Pub<T> = Publisher<ipc::Service, T, ()>;
/// A subscriber of `T` on the plane.
pub type Sub<T> = Subscriber<ipc::Service, T, ()>;

/// A camera's frame publisher: a [`CameraFrameHeader`] beside the pixels as a byte slice.
pub type FramePub = Publisher<ipc::Service, [u8], CameraFrameHeader>;
/// A camera's frame subscriber.
pub type FrameSub = Subscriber<ipc::Service, [u8], CameraFrameHeader>;

/// Queue sizes and port limits of a service.
#[derive(Debug, Clone, Copy)]
pub struct Qos {
    /// Samples a late subscriber receives at once.
    pub history: usize,
    /// Samples a subscriber holds before the oldest is overwritten.
    pub buffer: usize,
    /// Publishers allowed.
    pub publishers: usize,
    /// Subscribers allowed.
    pub subscribers: usize,
}

/// A service: its name, payload and QoS.
pub struct Topic<T> {
    /// Service name.
    pub name: &'static str,
    /// QoS.
    pub qos: Qos,
    payload: PhantomData<fn() -> T>,
}

pub(crate) const fn topic<T>(
    name: &'static str,
    history: usize,
    buffer: usize,
    publishers: usize,
    subscribers: usize,
) -> Topic<T> {
    Topic {
        name,
        qos: Qos {
            history,
            buffer,
            publishers,
            subscribers,
        },
        payload: PhantomData,
    }
}

/// Driver → all: one frame per control cycle. A late subscriber gets the newest at once; the
/// supervisor needs every frame of its stall window, so the buffer spans a few cycles.
pub const JOINT_STATE: Topic<JointState> = topic("nori/joint-state", 1, 16, 2, 8);
/// Goals into the driver for the arms and grippers (a wheel named here is refused). Not
/// replayed: a restarted driver starts from present positions.
pub const GOALS: Topic<GoalFrame> = topic("nori/goals", 0, 4, 8, 4);
/// Driver → all: the joint layout, published at start (history 1).
pub const LAYOUT: Topic<JointLayout> = topic("nori/layout", 1, 2, 2, 8);
/// Supervisor → driver: torque limits and bus enables; newest wins.
pub const DIRECTIVES: Topic<Directives> = topic("nori/directives", 1, 4, 2, 4);
/// Supervisor and driver → all: what was decided or observed. Buffered: events must not be lost.
pub const EVENTS: Topic<SupervisorEvent> = topic("nori/events", 16, 256, 4, 8);
/// Driver's heartbeat.
pub const DRIVER_HEARTBEAT: Topic<Heartbeat> = topic("nori/heartbeat/driver", 1, 4, 2, 4);
/// Supervisor's heartbeat.
pub const SUPERVISOR_HEARTBEAT: Topic<Heartbeat> = topic("nori/heartbeat/supervisor", 1, 4, 2, 4);
/// Supervisor → all: grip force beside raw current, per joint-state frame.
pub const GRIP: Topic<GripFrame> = topic("nori/grip", 1, 16, 2, 8);
/// Operator → supervisor: explicit commands (re-enable a tripped bus).
pub const COMMANDS: Topic<SupervisorCommand> = topic("nori/supervisor-commands", 0, 8, 4, 2);
/// Driver → all: error counts by kind per bus, every 100 ms (history 1: the newest at once).
pub const BUS_HEALTH: Topic<crate::frames::BusHealth> = topic("nori/bus-health", 1, 4, 2, 8);
/// Driver → the black box: each bus's bytes on the wire, one frame per bus per cycle. No
/// history; 64 frames queued (80 ms of four buses at 200 Hz), the oldest overwritten: a slow
/// or hung reader loses traffic, never holds the driver.
pub const BUS_WIRE: Topic<WireFrame> = topic("nori/bus-wire", 0, 64, 2, 2);
/// Operator → the black box: freeze the last minutes now.
pub const BLACKBOX_SAVE: Topic<BlackboxSave> = topic("nori/blackbox/save", 0, 4, 4, 2);

/// Tools, the fleet agent → the base controller: velocity commands (a queue: none is lost
/// between two of the controller's periods; the newest wins).
pub const BASE_COMMAND: Topic<BaseCommand> = topic("nori/base/command", 0, 8, 4, 2);
/// Base controller → driver: the wheels' speeds, the only path that drives them (so every
/// wheel goal has passed the protective field, the ramp and the command timeout).
pub const WHEEL_GOALS: Topic<GoalFrame> = topic("nori/base/wheel-goals", 0, 4, 2, 4);
/// Base controller → all: odometry, what it commanded and why, every control period.
pub const BASE_STATE: Topic<BaseState> = topic("nori/base/state", 1, 4, 1, 8);

/// Tools, the fleet agent → the lift's controller: heights (a queue; the newest wins).
pub const LIFT_COMMAND: Topic<LiftCommand> = topic("nori/lift/command", 0, 8, 4, 2);
/// Lift controller → all: where the lift is, every control period.
pub const LIFT_STATE: Topic<LiftState> = topic("nori/lift/state", 1, 4, 1, 8);

/// Base controller → tools: where the whole body is, every control period.
pub const BODY_FRAMES: Topic<BodyFrames> = topic("nori/body/frames", 1, 4, 1, 8);

/// Supervisor → the lift's controller: whether the duty-cycle budget allows travel.
pub const LIFT_ALLOWANCE: Topic<LiftAllowance> = topic("nori/lift/allowance", 1, 4, 2, 4);

/// Lidar → all: one frame per revolution (8–12 Hz). A late subscriber gets the newest at once.
pub const LIDAR_SCAN: Topic<LidarScan> = topic("nori/lidar/scan", 1, 4, 1, 8);

/// What a camera service carries.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CameraStream {
    /// Decoded pixels, RGB24 (`nori/camera/<name>`): what readers of images take.
    Rgb,
    /// The device's own JPEG of each frame published on the RGB stream, untouched
    /// (`nori/camera/<name>/mjpeg`, same `seq`): what a recording stores without encoding
    /// anything again. Only for cameras that deliver MJPEG.
    Mjpeg,
}

/// The service of camera `name`'s `stream`.
pub fn camera_service(name: &str, stream: CameraStream) -> String {
    match stream {
        CameraStream::Rgb => format!("nori/camera/{name}"),
        CameraStream::Mjpeg => format!("nori/camera/{name}/mjpeg"),
    }
}

/// A camera's frames: the newest at once for a late subscriber, and two in each subscriber's
/// queue, the older overwritten: a reader that falls behind loses frames, never holds the
/// camera. Each queued frame is a block of shared memory as large as the biggest image, so
/// the subscribers are few (recorder, fleet agent, operator page, one tool).
pub const CAMERA_QOS: Qos = Qos {
    history: 1,
    buffer: 2,
    publishers: 1,
    subscribers: 4,
};

/// A service builder with a [`Qos`] applied: the one place the QoS reaches iceoryx2, for typed
/// frames and camera slices alike. Overflow is safe everywhere: a full queue loses its oldest
/// sample, a publisher never waits for a reader.
trait WithQos {
    fn with_qos(self, q: Qos) -> Self;
}

impl<P, H> WithQos for iceoryx2::service::builder::publish_subscribe::Builder<P, H, ipc::Service>
where
    P: std::fmt::Debug + IceoryxSend + ?Sized,
    H: std::fmt::Debug + ZeroCopySend,
{
    fn with_qos(self, q: Qos) -> Self {
        self.history_size(q.history)
            .subscriber_max_buffer_size(q.buffer)
            .max_publishers(q.publishers)
            .max_subscribers(q.subscribers)
            .enable_safe_overflow(true)
    }
}

/// The type name a frame type carries on the plane (`nori::JointState/1`).
pub(crate) fn type_name(detail: &TypeDetail) -> String {
    String::from_utf8_lossy(detail.type_name().as_bytes_const()).into_owned()
}

/// A state-plane operation that failed, with iceoryx2's own error as its source.
#[derive(Debug, Error)]
pub enum PlaneError {
    /// A domain or node name iceoryx2 does not accept.
    #[error("state plane: {what} {name:?} is not a valid name")]
    Name {
        /// What the name is for ("domain", "node").
        what: &'static str,
        /// The name.
        name: String,
        /// iceoryx2's error.
        source: SemanticStringError,
    },
    /// A service name iceoryx2 does not accept.
    #[error("state plane: service {service:?} is not a valid name")]
    ServiceName {
        /// The name.
        service: String,
        /// iceoryx2's error.
        source: ServiceNameError,
    },
    /// The process's node could not be created (shared memory, permissions).
    #[error("state plane: creating node {name:?}")]
    Node {
        /// The node's name.
        name: String,
        /// iceoryx2's error.
        source: NodeCreationFailure,
    },
    /// The domain's nodes could not be listed.
    #[error("state plane: listing the nodes")]
    ListNodes(#[source] NodeListFailure),
    /// `/dev/shm` could not be read.
    #[error("state plane: reading /dev/shm")]
    SharedMemory(#[source] std::io::Error),
    /// A service already carries another version of its frame: a process of another version
    /// of the stack holds it (an upgrade that did not stop the whole stack first).
    #[error(
        "state plane: service {service} carries {theirs}, and this build speaks {ours}: \
         a process of another version of the stack is running; stop the whole stack \
         (systemctl stop nori.target) before starting this version"
    )]
    OtherVersion {
        /// The service.
        service: String,
        /// This build's frame type, with its version.
        ours: String,
        /// The running service's frame type, with its version.
        theirs: String,
    },
    /// A service could not be opened or created (another QoS, another payload type).
    #[error("state plane: opening service {service}")]
    Service {
        /// The service.
        service: String,
        /// iceoryx2's error.
        source: PublishSubscribeOpenOrCreateError,
    },
    /// A publisher could not be created (too many).
    #[error("state plane: a publisher on {service}")]
    Publisher {
        /// The service.
        service: String,
        /// iceoryx2's error.
        source: PublisherCreateError,
    },
    /// A subscriber could not be created (too many).
    #[error("state plane: a subscriber on {service}")]
    Subscriber {
        /// The service.
        service: String,
        /// iceoryx2's error.
        source: SubscriberCreateError,
    },
    /// No shared memory for a sample (a frame larger than the service's maximum, all samples
    /// held by slow readers).
    #[error("state plane: loaning a sample")]
    Loan(#[source] LoanError),
    /// A sample could not be sent.
    #[error("state plane: sending")]
    Send(#[source] SendError),
}

fn domain_config(domain: &str) -> Result<Config, PlaneError> {
    let mut config = Config::default();
    config.global.prefix =
        FileName::new(format!("{domain}_").as_bytes()).map_err(|source| PlaneError::Name {
            what: "domain",
            name: domain.into(),
            source,
        })?;
    Ok(config)
}

/// One process's node on the plane.
pub struct Plane {
    node: Node<ipc::Service>,
}

impl Plane {
    /// Joins `domain` as node `name`. iceoryx2's own signal handling is disabled: the process
    /// owns its signals.
    pub fn open(domain: &str, name: &str) -> Result<Self, PlaneError> {
        iceoryx2::prelude::set_log_level(LogLevel::Warn);
        let config = domain_config(domain)?;
        let node_name = NodeName::new(name).map_err(|source| PlaneError::Name {
            what: "node",
            name: name.into(),
            source,
        })?;
        let node = NodeBuilder::new()
            .name(&node_name)
            .config(&config)
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<ipc::Service>()
            .map_err(|source| PlaneError::Node {
                name: name.into(),
                source,
            })?;
        Ok(Plane { node })
    }

    /// Clears a domain no process uses any more: the resources of dead processes, then the
    /// node counter iceoryx2 keeps per domain (its one segment that outlives every process, by
    /// design). Returns the files removed; none while a process of the domain is alive.
    pub fn remove_unused_domain(domain: &str) -> Result<usize, PlaneError> {
        Plane::open(domain, "cleanup")?.cleanup_dead();
        let config = domain_config(domain)?;
        let mut alive = 0;
        Node::<ipc::Service>::list(&config, |state| {
            if matches!(state, NodeState::Alive(_)) {
                alive += 1;
            }
            CallbackProgression::Continue
        })
        .map_err(PlaneError::ListNodes)?;
        if alive > 0 {
            return Ok(0);
        }
        let prefix = format!("{domain}_");
        let suffix = config.global.node.global_mgmt_suffix.to_string();
        let mut removed = 0;
        for entry in std::fs::read_dir("/dev/shm")
            .map_err(PlaneError::SharedMemory)?
            .flatten()
        {
            let name = entry.file_name();
            let name = name.to_string_lossy();
            if name.starts_with(&prefix)
                && name.ends_with(&suffix)
                && std::fs::remove_file(entry.path()).is_ok()
            {
                removed += 1;
            }
        }
        Ok(removed)
    }

    /// Removes the resources of dead processes of this domain (after a crash).
    pub fn cleanup_dead(&self) {
        let _ = self.node.try_cleanup_dead_nodes();
    }

    fn service<T>(
        &self,
        topic: &Topic<T>,
    ) -> Result<
        iceoryx2::service::port_factory::publish_subscribe::PortFactory<ipc::Service, T, ()>,
        PlaneError,
    >
    where
        T: std::fmt::Debug + ZeroCopySend + 'static,
    {
        self.node
            .service_builder(&ServiceName::new(topic.name).map_err(|source| {
                PlaneError::ServiceName {
                    service: topic.name.into(),
                    source,
                }
            })?)
            .publish_subscribe::<T>()
            .with_qos(topic.qos)
            .open_or_create()
            .map_err(|source| {
                let ours = type_name(&TypeDetail::new::<T>(TypeVariant::FixedSize));
                self.service_error(topic.name, &ours, source)
            })
    }

    /// The error of opening `service` for frames of `ours`: another version's frame named.
    fn service_error(
        &self,
        service: &str,
        ours: &str,
        source: PublishSubscribeOpenOrCreateError,
    ) -> PlaneError {
        let incompatible = PublishSubscribeOpenOrCreateError::PublishSubscribeOpenError(
            PublishSubscribeOpenError::IncompatibleTypes,
        );
        let theirs = (source == incompatible)
            .then(|| self.payload_type(service))
            .flatten();
        match theirs {
            Some(theirs) if theirs != ours => PlaneError::OtherVersion {
                service: service.into(),
                ours: ours.into(),
                theirs,
            },
            _ => PlaneError::Service {
                service: service.into(),
                source,
            },
        }
    }

    /// The payload type `service` was created with, if it exists.
    fn payload_type(&self, service: &str) -> Option<String> {
        let name = ServiceName::new(service).ok()?;
        let details = <ipc::Service as iceoryx2::service::Service>::details(
            &name,
            self.node.config(),
            iceoryx2::service::messaging_pattern::MessagingPattern::PublishSubscribe,
        )
        .ok()??;
        match details.static_details.messaging_pattern() {
            ServicePattern::PublishSubscribe(c) => {
                let payload = &c.message_type_details().payload;
                Some(type_name(payload))
            }
            _ => None,
        }
    }

    /// A publisher on `topic`.
    pub fn publisher<T>(&self, topic: &Topic<T>) -> Result<Pub<T>, PlaneError>
    where
        T: std::fmt::Debug + ZeroCopySend + 'static,
    {
        self.service(topic)?
            .publisher_builder()
            .create()
            .map_err(|source| PlaneError::Publisher {
                service: topic.name.into(),
                source,
            })
    }

    /// A subscriber on `topic`.
    pub fn subscriber<T>(&self, topic: &Topic<T>) -> Result<Sub<T>, PlaneError>
    where
        T: std::fmt::Debug + ZeroCopySend + 'static,
    {
        self.service(topic)?
            .subscriber_builder()
            .create()
            .map_err(|source| PlaneError::Subscriber {
                service: topic.name.into(),
                source,
            })
    }
}

impl Plane {
    fn camera_service_port(
        &self,
        camera: &str,
        stream: CameraStream,
    ) -> Result<
        iceoryx2::service::port_factory::publish_subscribe::PortFactory<
            ipc::Service,
            [u8],
            CameraFrameHeader,
        >,
        PlaneError,
    > {
        let service = camera_service(camera, stream);
        let name = ServiceName::new(&service).map_err(|source| PlaneError::ServiceName {
            service: service.clone(),
            source,
        })?;
        self.node
            .service_builder(&name)
            .publish_subscribe::<[u8]>()
            .user_header::<CameraFrameHeader>()
            .with_qos(CAMERA_QOS)
            .open_or_create()
            .map_err(|source| PlaneError::Service { service, source })
    }

    /// The publisher of camera `camera`'s `stream`, of at most `max_bytes` a frame. Its shared
    /// memory is allocated once, here (static allocation: nothing is allocated per frame).
    pub fn camera_publisher(
        &self,
        camera: &str,
        stream: CameraStream,
        max_bytes: usize,
    ) -> Result<FramePub, PlaneError> {
        self.camera_service_port(camera, stream)?
            .publisher_builder()
            .initial_max_slice_len(max_bytes)
            .allocation_strategy(AllocationStrategy::Static)
            .create()
            .map_err(|source| PlaneError::Publisher {
                service: camera_service(camera, stream),
                source,
            })
    }

    /// A subscriber of camera `camera`'s `stream`.
    pub fn camera_subscriber(
        &self,
        camera: &str,
        stream: CameraStream,
    ) -> Result<FrameSub, PlaneError> {
        self.camera_service_port(camera, stream)?
            .subscriber_builder()
            .create()
            .map_err(|source| PlaneError::Subscriber {
                service: camera_service(camera, stream),
                source,
            })
    }
}

/// Publishes one camera frame of `len` bytes: `fill` writes the pixels straight into shared
/// memory (the decoder's output is the sample: no copy), and returns whether it succeeded; a
/// frame it refuses is not sent. Returns whether one was sent.
pub fn publish_frame(
    publisher: &FramePub,
    header: &CameraFrameHeader,
    len: usize,
    fill: impl FnOnce(&mut [u8]) -> bool,
) -> Result<bool, PlaneError> {
    let mut sample = publisher.loan_slice(len).map_err(PlaneError::Loan)?;
    *sample.user_header_mut() = *header;
    if !fill(sample.payload_mut()) {
        return Ok(false);
    }
    sample.send().map(|_| true).map_err(PlaneError::Send)
}

/// Publishes `value` by copying it into a loaned sample (no heap allocation).
pub fn publish<T: std::fmt::Debug + ZeroCopySend + Copy + 'static>(
    publisher: &Pub<T>,
    value: &T,
) -> Result<(), PlaneError> {
    publisher
        .send_copy(*value)
        .map(|_| ())
        .map_err(PlaneError::Send)
}

/// Hands the history of `publisher`'s service to the subscribers that joined since its last
/// sample (iceoryx2 delivers it only when a publisher updates its connections, which a send
/// does): for a publisher that sends rarely, such as the events'. A failure is only logged
/// (the next call or send tries again).
pub fn offer_history<T: std::fmt::Debug + ZeroCopySend + 'static>(publisher: &Pub<T>) {
    use iceoryx2::port::update_connections::UpdateConnections;
    if let Err(e) = publisher.update_connections() {
        tracing::debug!("updating a publisher's connections: {e:?}");
    }
}

/// The newest sample waiting on `subscriber`, older ones dropped; `None` if nothing new.
pub fn newest<T: std::fmt::Debug + ZeroCopySend + Copy + 'static>(
    subscriber: &Sub<T>,
) -> Option<T> {
    let mut last = None;
    while let Some(v) = next(subscriber) {
        last = Some(v);
    }
    last
}

/// The oldest sample waiting on `subscriber`, in order; `None` if nothing is waiting.
pub fn next<T: std::fmt::Debug + ZeroCopySend + Copy + 'static>(subscriber: &Sub<T>) -> Option<T> {
    match subscriber.receive() {
        Ok(Some(sample)) => Some(*sample.payload()),
        _ => None,
    }
}

/// No driver published its layout in time.
#[derive(Debug, Error)]
#[error("no joint layout on domain {domain:?} within {waited_s} s: is the bus-driver running?")]
pub struct NoLayout {
    /// The state plane's domain.
    pub domain: String,
    /// How long it was waited for, s.
    pub waited_s: f64,
}

/// The running driver's layout on `domain`, waited for up to `timeout` (or until `stop` is
/// set): the one source of joint and bus names for the tools.
pub fn wait_for_layout(
    layouts: &Sub<JointLayout>,
    domain: &str,
    timeout: std::time::Duration,
    stop: Option<&std::sync::atomic::AtomicBool>,
) -> Result<JointLayout, NoLayout> {
    let until = std::time::Instant::now() + timeout;
    loop {
        if let Some(l) = newest(layouts).filter(|l| l.joint_count > 0) {
            return Ok(l);
        }
        let stopped = stop.is_some_and(|s| s.load(std::sync::atomic::Ordering::Relaxed));
        if std::time::Instant::now() > until || stopped {
            return Err(NoLayout {
                domain: domain.into(),
                waited_s: timeout.as_secs_f64(),
            });
        }
        std::thread::sleep(std::time::Duration::from_millis(10));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn state_and_goals_cross_the_plane() {
        let domain = format!("nori_test_{}", std::process::id());
        let a = Plane::open(&domain, "a").unwrap();
        let b = Plane::open(&domain, "b").unwrap();
        let publisher = a.publisher(&JOINT_STATE).unwrap();
        let subscriber = b.subscriber(&JOINT_STATE).unwrap();
        for seq in 1..=3 {
            let s = JointState {
                seq,
                joint_count: 2,
                ..JointState::default()
            };
            publish(&publisher, &s).unwrap();
        }
        assert_eq!(next(&subscriber).map(|s| s.seq), Some(1), "in order");
        assert_eq!(newest(&subscriber).map(|s| s.seq), Some(3), "newest wins");
        assert!(newest(&subscriber).is_none());

        let goals = b.publisher(&GOALS).unwrap();
        let driver_side = a.subscriber(&GOALS).unwrap();
        let mut g = GoalFrame {
            seq: 9,
            mask: 1,
            ..GoalFrame::default()
        };
        g.position_rad[0] = 0.25;
        publish(&goals, &g).unwrap();
        assert_eq!(newest(&driver_side), Some(g));
        // Other domains see nothing.
        let other = Plane::open(&format!("{domain}x"), "c").unwrap();
        assert!(newest(&other.subscriber(&JOINT_STATE).unwrap()).is_none());
    }

    #[test]
    fn camera_frames_cross_the_plane_and_a_slow_reader_loses_the_oldest() {
        let domain = format!("nori_test_cam_{}", std::process::id());
        let a = Plane::open(&domain, "camera").unwrap();
        let b = Plane::open(&domain, "reader").unwrap();
        let publisher = a.camera_publisher("head", CameraStream::Rgb, 64).unwrap();
        let reader = b.camera_subscriber("head", CameraStream::Rgb).unwrap();
        let other_camera = b.camera_subscriber("neck", CameraStream::Rgb).unwrap();
        let other_stream = b.camera_subscriber("head", CameraStream::Mjpeg).unwrap();
        for seq in 0..5u64 {
            let mut h = CameraFrameHeader {
                seq,
                width: 4,
                height: 2,
                ..Default::default()
            };
            h.set_camera("head");
            let sent = publish_frame(&publisher, &h, 8, |px| {
                px.fill(seq as u8);
                true
            })
            .unwrap();
            assert!(sent);
        }
        // Five sent into a queue of two: the reader gets the newest two, in order.
        let mut got = Vec::new();
        while let Ok(Some(sample)) = reader.receive() {
            assert_eq!(sample.user_header().camera(), "head");
            assert_eq!(sample.payload().len(), 8);
            assert!(sample
                .payload()
                .iter()
                .all(|&p| p == sample.user_header().seq as u8));
            got.push(sample.user_header().seq);
        }
        assert_eq!(got, [3, 4]);
        assert!(
            other_camera.receive().unwrap().is_none(),
            "cameras are apart"
        );
        assert!(
            other_stream.receive().unwrap().is_none(),
            "a camera's streams are apart"
        );
        assert_eq!(
            camera_service("head", CameraStream::Rgb),
            "nori/camera/head"
        );
        assert_eq!(
            camera_service("head", CameraStream::Mjpeg),
            "nori/camera/head/mjpeg"
        );

        // A refused frame is not sent; one larger than the maximum is an error, not a panic.
        let h = CameraFrameHeader::default();
        assert!(!publish_frame(&publisher, &h, 8, |_| false).unwrap());
        assert!(reader.receive().unwrap().is_none());
        assert!(matches!(
            publish_frame(&publisher, &h, 65, |_| true),
            Err(PlaneError::Loan(_))
        ));
    }
}
