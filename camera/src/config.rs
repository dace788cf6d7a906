//! The camera process's configuration (`deploy/config/camera.toml`, embedded).

use crate::mode::{check, format_named, Mode};
use serde::Deserialize;
use std::path::{Path, PathBuf};
use telemetry::config::{invalid, parse, ConfigError, ProcessConfig};
use telemetry::frames::NAME_LEN;

/// The commented default.
pub const DEFAULT_CONFIG_TOML: &str = include_str!("../../deploy/config/camera.toml");

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
struct File {
    camera: Vec<CameraFile>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
struct CameraFile {
    name: String,
    device: PathBuf,
    format: String,
    width: u32,
    height: u32,
    fps: u32,
}

/// One camera.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraConfig {
    /// Name: the plane's service `nori/camera/<name>`, the dataset's `observation.images.<name>`.
    pub name: String,
    /// V4L2 device or the simulator's socket.
    pub device: PathBuf,
    /// What it delivers.
    pub mode: Mode,
}

/// Every camera of the robot.
#[derive(Debug, Clone, PartialEq)]
pub struct CamerasConfig {
    /// In the file's order.
    pub cameras: Vec<CameraConfig>,
}

impl ProcessConfig for CamerasConfig {
    const DEFAULT_TOML: &'static str = DEFAULT_CONFIG_TOML;
    const FILE_NAME: &'static str = "camera.toml";

    fn parse_in(text: &str, origin: &str, _dir: Option<&Path>) -> Result<Self, ConfigError> {
        let file: File = parse(text, origin)?;
        let mut cameras: Vec<CameraConfig> = Vec::new();
        for (i, c) in file.camera.into_iter().enumerate() {
            let key = |k: &str| format!("camera[{i}].{k}");
            let name_ok = telemetry::sensors::valid_camera_name(&c.name);
            if !name_ok {
                return Err(invalid(
                    origin,
                    key("name"),
                    format!(
                        "{:?}: 1 to {NAME_LEN} of a-z, 0-9 and _ (it names a service and a \
                         dataset key)",
                        c.name
                    ),
                ));
            }
            if cameras.iter().any(|o| o.name == c.name) {
                return Err(invalid(origin, key("name"), format!("{:?} twice", c.name)));
            }
            check(c.width, c.height, c.fps)
                .map_err(|(k, reason)| invalid(origin, key(k), reason))?;
            let format = format_named(&c.format).ok_or_else(|| {
                invalid(
                    origin,
                    key("format"),
                    format!("{:?}: \"mjpeg\" or \"yuyv\"", c.format),
                )
            })?;
            cameras.push(CameraConfig {
                name: c.name,
                device: c.device,
                mode: Mode {
                    format,
                    width: c.width,
                    height: c.height,
                    fps: c.fps,
                },
            });
        }
        Ok(CamerasConfig { cameras })
    }
}

impl CamerasConfig {
    /// The camera named `name`.
    pub fn camera(&self, name: &str) -> Option<&CameraConfig> {
        self.cameras.iter().find(|c| c.name == name)
    }

    /// Every camera's device at `dir/camera-<name>` (the simulator's sockets).
    pub fn with_device_dir(mut self, dir: &Path) -> Self {
        for c in &mut self.cameras {
            c.device = dir.join(format!("camera-{}", c.name));
        }
        self
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use telemetry::sensors::PixelFormat;

    #[test]
    fn the_embedded_default_has_the_four_cameras_of_the_a3() {
        let c = CamerasConfig::embedded().unwrap();
        let names: Vec<_> = c.cameras.iter().map(|c| c.name.as_str()).collect();
        assert_eq!(names, ["head", "neck", "left_wrist", "right_wrist"]);
        let head = c.camera("head").unwrap();
        assert_eq!(
            head.mode,
            Mode {
                format: PixelFormat::Mjpeg,
                width: 1280,
                height: 720,
                fps: 30
            }
        );
        let moved = c.with_device_dir(Path::new("/tmp/sim"));
        assert_eq!(
            moved.camera("neck").unwrap().device,
            Path::new("/tmp/sim/camera-neck")
        );
    }

    #[test]
    fn a_bad_camera_is_refused_with_its_key() {
        let base = "name = \"head\"\ndevice = \"/dev/video0\"\nformat = \"mjpeg\"\n";
        let cases = [
            ("width = 1280\nheight = 720\nfps = 0", "camera[0].fps"),
            ("width = 1281\nheight = 720\nfps = 30", "camera[0].width"),
            ("width = 4096\nheight = 2160\nfps = 30", "camera[0].width"),
            ("width = 8\nheight = 720\nfps = 30", "camera[0].width"),
            (
                "width = 1280\nheight = 720\nfps = 30\nexposure = 3",
                "exposure",
            ),
        ];
        for (rest, key) in cases {
            let text = format!("[[camera]]\n{base}{rest}\n");
            let err = CamerasConfig::parse_in(&text, "t.toml", None).unwrap_err();
            assert!(err.to_string().contains(key), "{rest}: {err}");
        }
        let bad_name = "[[camera]]\nname = \"Head Cam\"\ndevice = \"/dev/video0\"\n\
                        format = \"mjpeg\"\nwidth = 640\nheight = 480\nfps = 30\n";
        let err = CamerasConfig::parse_in(bad_name, "t.toml", None).unwrap_err();
        assert!(err.to_string().contains("camera[0].name"), "{err}");
        let twice = format!("{bad}{bad}", bad = bad_name.replace("Head Cam", "head"));
        let err = CamerasConfig::parse_in(&twice, "t.toml", None).unwrap_err();
        assert!(err.to_string().contains("camera[1].name"), "{err}");
        let h264 = bad_name
            .replace("Head Cam", "head")
            .replace("mjpeg", "h264");
        assert!(CamerasConfig::parse_in(&h264, "t.toml", None).is_err());
    }
}
