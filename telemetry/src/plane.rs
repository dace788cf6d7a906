//! The state plane: the iceoryx2 services of one robot, opened with their QoS in this one place
//! (the first process to create a service fixes its QoS; every other must ask for no more).
//!
//! | service              | payload        | publishers            | subscribers               |
//! |----------------------|----------------|-----------------------|---------------------------|
//! | `nori/joint-state`   | [`JointState`] | bus-driver            | supervisor, fleet-agent, tools |
//! | `nori/goals`         | [`GoalFrame`]  | fleet-agent, tools    | bus-driver                |
//!
//! A *domain* (the iceoryx2 prefix) separates robots or test runs on one machine.

use crate::frames::{GoalFrame, JointState};
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use thiserror::Error;

/// Joint state, one frame per driver cycle.
pub const JOINT_STATE: &str = "nori/joint-state";
/// Goals into the driver.
pub const GOALS: &str = "nori/goals";
/// The default domain.
pub const DEFAULT_DOMAIN: &str = "nori";

/// A publisher of `T` on the plane.
pub type Pub<T> = Publisher<ipc::Service, T, ()>;
/// A subscriber of `T` on the plane.
pub type Sub<T> = Subscriber<ipc::Service, T, ()>;

/// An iceoryx2 failure, with what was being done.
#[derive(Debug, Error)]
#[error("state plane: {what}: {detail}")]
pub struct PlaneError {
    /// The operation.
    pub what: String,
    /// iceoryx2's error.
    pub detail: String,
}

fn err<E: std::fmt::Debug>(what: impl Into<String>) -> impl FnOnce(E) -> PlaneError {
    let what = what.into();
    move |e| PlaneError {
        what,
        detail: format!("{e:?}"),
    }
}

struct Qos {
    history: usize,
    buffer: usize,
    publishers: usize,
    subscribers: usize,
}

const STATE_QOS: Qos = Qos {
    // A late subscriber gets the newest frame at once.
    history: 1,
    buffer: 4,
    publishers: 2,
    subscribers: 8,
};
const GOAL_QOS: Qos = Qos {
    // Goals are not replayed to a late (restarted) driver: it starts from present positions.
    history: 0,
    buffer: 4,
    publishers: 4,
    subscribers: 4,
};

/// One process's node on the plane.
pub struct Plane {
    node: Node<ipc::Service>,
}

impl Plane {
    /// Joins `domain` as node `name`. iceoryx2's own signal handling is disabled: the process
    /// owns its signals.
    pub fn open(domain: &str, name: &str) -> Result<Self, PlaneError> {
        iceoryx2::prelude::set_log_level(LogLevel::Warn);
        let mut config = Config::default();
        config.global.prefix = FileName::new(format!("{domain}_").as_bytes())
            .map_err(err(format!("domain {domain:?}")))?;
        let node = NodeBuilder::new()
            .name(&NodeName::new(name).map_err(err(format!("node name {name:?}")))?)
            .config(&config)
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<ipc::Service>()
            .map_err(err("create node"))?;
        Ok(Plane { node })
    }

    /// Removes the resources of dead processes of this domain (after a crash).
    pub fn cleanup_dead(&self) {
        let _ = self.node.try_cleanup_dead_nodes();
    }

    fn service<T>(
        &self,
        name: &str,
        qos: &Qos,
    ) -> Result<
        iceoryx2::service::port_factory::publish_subscribe::PortFactory<ipc::Service, T, ()>,
        PlaneError,
    >
    where
        T: std::fmt::Debug + ZeroCopySend + 'static,
    {
        self.node
            .service_builder(&ServiceName::new(name).map_err(err(format!("service name {name}")))?)
            .publish_subscribe::<T>()
            .history_size(qos.history)
            .subscriber_max_buffer_size(qos.buffer)
            .max_publishers(qos.publishers)
            .max_subscribers(qos.subscribers)
            .enable_safe_overflow(true)
            .open_or_create()
            .map_err(err(format!("open service {name}")))
    }

    /// Publisher of joint state (the driver).
    pub fn joint_state_publisher(&self) -> Result<Pub<JointState>, PlaneError> {
        self.service::<JointState>(JOINT_STATE, &STATE_QOS)?
            .publisher_builder()
            .create()
            .map_err(err("joint-state publisher"))
    }

    /// Subscriber of joint state.
    pub fn joint_state_subscriber(&self) -> Result<Sub<JointState>, PlaneError> {
        self.service::<JointState>(JOINT_STATE, &STATE_QOS)?
            .subscriber_builder()
            .create()
            .map_err(err("joint-state subscriber"))
    }

    /// Publisher of goals.
    pub fn goal_publisher(&self) -> Result<Pub<GoalFrame>, PlaneError> {
        self.service::<GoalFrame>(GOALS, &GOAL_QOS)?
            .publisher_builder()
            .create()
            .map_err(err("goal publisher"))
    }

    /// Subscriber of goals (the driver).
    pub fn goal_subscriber(&self) -> Result<Sub<GoalFrame>, PlaneError> {
        self.service::<GoalFrame>(GOALS, &GOAL_QOS)?
            .subscriber_builder()
            .create()
            .map_err(err("goal subscriber"))
    }
}

/// Publishes `value` by copying it into a loaned sample (no heap allocation).
pub fn publish<T: std::fmt::Debug + ZeroCopySend + Copy + 'static>(
    publisher: &Pub<T>,
    value: &T,
) -> Result<(), PlaneError> {
    publisher.send_copy(*value).map(|_| ()).map_err(err("send"))
}

/// The newest sample waiting on `subscriber`, older ones dropped; `None` if nothing new.
pub fn newest<T: std::fmt::Debug + ZeroCopySend + Copy + 'static>(
    subscriber: &Sub<T>,
) -> Option<T> {
    let mut last = None;
    while let Ok(Some(sample)) = subscriber.receive() {
        last = Some(*sample.payload());
    }
    last
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn state_and_goals_cross_the_plane() {
        let domain = format!("nori_test_{}", std::process::id());
        let a = Plane::open(&domain, "a").unwrap();
        let b = Plane::open(&domain, "b").unwrap();
        let publisher = a.joint_state_publisher().unwrap();
        let subscriber = b.joint_state_subscriber().unwrap();
        for seq in 1..=3 {
            let s = JointState {
                seq,
                joint_count: 2,
                ..JointState::default()
            };
            publish(&publisher, &s).unwrap();
        }
        assert_eq!(newest(&subscriber).map(|s| s.seq), Some(3), "newest wins");
        assert!(newest(&subscriber).is_none());

        let goals = b.goal_publisher().unwrap();
        let driver_side = a.goal_subscriber().unwrap();
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
        assert!(newest(&other.joint_state_subscriber().unwrap()).is_none());
    }
}
