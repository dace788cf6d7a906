//! The command lines of the stack's processes, spelled once for `nori up`, the scenario runner,
//! the benchmarks and the process tests.

use std::path::Path;

/// One run of the stack: its state-plane domain, the simulator's device directory, and the trip
/// record the supervisor and the driver share.
#[derive(Debug, Clone, Copy)]
pub struct Run<'a> {
    /// State-plane domain.
    pub domain: &'a str,
    /// Where the simulator links its buses and the driver finds them.
    pub device_dir: &'a Path,
    /// The trip record (`--trip-file` of both); the processes' default when absent.
    pub trips: Option<&'a Path>,
    /// Status printing off (`--status-every 0`): runs whose logs nobody reads live.
    pub quiet: bool,
}

fn s(v: impl Into<String>) -> String {
    v.into()
}

impl Run<'_> {
    fn common(&self) -> Vec<String> {
        let mut args = vec![s("--domain"), s(self.domain)];
        if self.quiet {
            args.extend([s("--status-every"), s("0")]);
        }
        if let Some(trips) = self.trips {
            args.extend([s("--trip-file"), trips.display().to_string()]);
        }
        args
    }

    /// `nori-sim` serving `buses` (all when empty), its report written to `report`.
    pub fn simulator(&self, buses: &[&str], report: &Path) -> Vec<String> {
        let mut args = vec![
            s("--dir"),
            self.device_dir.display().to_string(),
            s("--report"),
            report.display().to_string(),
        ];
        for bus in buses {
            args.extend([s("--bus"), s(*bus)]);
        }
        args
    }

    /// `supervisor`.
    pub fn supervisor(&self) -> Vec<String> {
        self.common()
    }

    /// `bus-driver` on `buses` (all of its configuration's when empty).
    pub fn driver(&self, buses: &[&str]) -> Vec<String> {
        let mut args = Vec::new();
        for bus in buses {
            args.extend([s("--bus"), s(*bus)]);
        }
        args.extend([s("--device-dir"), self.device_dir.display().to_string()]);
        args.extend(self.common());
        args
    }

    /// `nori-blackbox record`, its boxes in `dir`.
    pub fn blackbox(&self, dir: &Path) -> Vec<String> {
        vec![
            s("record"),
            s("--domain"),
            s(self.domain),
            s("--dir"),
            dir.display().to_string(),
        ]
    }

    /// `fleet-agent` (status printing and the trip record are not its business).
    pub fn agent(&self) -> Vec<String> {
        vec![s("--domain"), s(self.domain)]
    }

    /// `nori-base`, the base's controller.
    pub fn base(&self) -> Vec<String> {
        vec![s("--domain"), s(self.domain)]
    }

    /// `nori-lift` driving the simulator's lift.
    pub fn lift(&self) -> Vec<String> {
        self.lidar()
    }

    /// `nori-lidar` reading the simulator's lidar.
    pub fn lidar(&self) -> Vec<String> {
        vec![
            s("--device-dir"),
            self.device_dir.display().to_string(),
            s("--domain"),
            s(self.domain),
        ]
    }

    /// `nori-camera` for camera `name`, reading the simulator's.
    pub fn camera(&self, name: &str) -> Vec<String> {
        let mut args = vec![s("--camera"), s(name)];
        args.extend(self.lidar());
        args
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_sensors_read_the_simulators_devices_on_the_runs_domain() {
        let run = Run {
            domain: "d",
            device_dir: Path::new("/dev/x"),
            trips: None,
            quiet: true,
        };
        assert_eq!(run.lidar().join(" "), "--device-dir /dev/x --domain d");
        assert_eq!(
            run.camera("head").join(" "),
            "--camera head --device-dir /dev/x --domain d"
        );
    }

    #[test]
    fn the_supervisor_and_the_driver_share_the_domain_and_the_trip_record() {
        let run = Run {
            domain: "d",
            device_dir: Path::new("/dev/x"),
            trips: Some(Path::new("/t/trips")),
            quiet: true,
        };
        let driver = run.driver(&["left_arm"]).join(" ");
        assert_eq!(
            driver,
            "--bus left_arm --device-dir /dev/x --domain d --status-every 0 --trip-file /t/trips"
        );
        assert_eq!(
            run.supervisor().join(" "),
            "--domain d --status-every 0 --trip-file /t/trips"
        );
        let loud = Run {
            trips: None,
            quiet: false,
            ..run
        };
        assert_eq!(loud.driver(&[]).join(" "), "--device-dir /dev/x --domain d");
        assert_eq!(
            run.simulator(&["a", "b"], Path::new("/r.json")).join(" "),
            "--dir /dev/x --report /r.json --bus a --bus b"
        );
    }
}
