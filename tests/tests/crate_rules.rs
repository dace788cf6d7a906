//! The crate rules of ARCHITECTURE.md, kept by a test so the layered graph stays layered: which
//! workspace crate may depend on which, which crates alone may pull in the heavy or
//! side-effecting dependencies (zenoh, iceoryx2, parquet, the serial port, the HTTP server),
//! that no robot process's crate depends on what runs only off the robot, and that every crate
//! keeps the workspace lints (no `unwrap`/`expect` outside tests) without opting out of them.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use serde_json::Value;
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::process::Command;

/// Each workspace crate and the workspace crates it may depend on (normal dependencies).
const ALLOWED: &[(&str, &[&str])] = &[
    ("feetech", &[]),
    ("body", &["feetech"]),
    ("base", &["telemetry", "body"]),
    ("lift", &["telemetry"]),
    ("telemetry", &[]),
    ("bus-driver", &["feetech", "telemetry"]),
    ("supervisor", &["telemetry"]),
    // The black box's shelf, read to send its boxes to the fleet; the camera's pure
    // thumbnails for the dashboard's previews.
    ("fleet-agent", &["telemetry", "blackbox", "camera"]),
    ("camera", &["telemetry"]),
    ("lidar", &["telemetry"]),
    ("sim", &["feetech", "body", "telemetry", "camera"]),
    ("recorder", &["telemetry"]),
    // The body's frames for a viewer (the description's kinematics) and the cameras' pure
    // thumbnails.
    ("blackbox", &["telemetry", "feetech", "body", "camera"]),
    ("model-lab", &["sim", "blackbox", "feetech"]),
    ("fleet", &["fleet-agent", "telemetry", "blackbox"]),
    ("stack", &["telemetry", "sim", "bus-driver"]),
    // The automatic calibration plans from the description and finds stops by the
    // supervisor's stall rule (its pure `stall` module, not its process).
    (
        "commission",
        &["feetech", "body", "bus-driver", "telemetry", "supervisor"],
    ),
    (
        "nori",
        &["telemetry", "feetech", "bus-driver", "commission", "body"],
    ),
    ("lab", &["telemetry", "body"]),
    (
        "bench",
        &[
            "feetech",
            "telemetry",
            "bus-driver",
            "fleet-agent",
            "fleet",
            "sim",
            "model-lab",
            "stack",
            "camera",
            "body",
        ],
    ),
    (
        "nori-tests",
        &[
            "bus-driver",
            "feetech",
            "sim",
            "stack",
            "fleet",
            "supervisor",
            "fleet-agent",
            "model-lab",
            "telemetry",
            "camera",
            "lidar",
            "recorder",
            "base",
            "lift",
            "blackbox",
        ],
    ),
];

/// Outside dependencies only these crates may name directly.
const CONFINED: &[(&str, &[&str])] = &[
    ("zenoh", &["fleet-agent"]),
    ("iceoryx2", &["telemetry"]),
    ("parquet", &["recorder"]),
    ("serialport", &["bus-driver", "lidar", "lift"]),
    ("v4l", &["camera"]),
    ("tiny_http", &["fleet"]),
    // nori-tests speaks Nori Lab's page link as a page would (a second implementation of it).
    ("tungstenite", &["lab", "stack", "nori-tests"]),
    ("prometheus-client", &["fleet"]),
    ("mcap", &["blackbox"]),
];

/// The crates of the programs that run on the robot (its processes and the operator's `nori`),
/// and what they may never reach, even through another crate: the fleet's side, the
/// orchestration, the simulator, the model lab, the benchmarks.
const ROBOT: &[&str] = &[
    "feetech",
    "body",
    "telemetry",
    "bus-driver",
    "supervisor",
    "fleet-agent",
    "recorder",
    "blackbox",
    "camera",
    "lidar",
    "base",
    "lift",
    "nori",
    "commission",
    "lab",
];
const OFF_ROBOT: &[&str] = &["fleet", "stack", "bench", "nori-tests", "model-lab", "sim"];

struct Package {
    manifest: PathBuf,
    /// Normal (not dev, not build) dependencies: name → whether it is a workspace path.
    deps: BTreeMap<String, bool>,
    /// Features enabled on `telemetry`, when it is a dependency.
    telemetry_features: Vec<String>,
}

fn workspace() -> BTreeMap<String, Package> {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).parent().unwrap();
    let out = Command::new(cargo)
        .args([
            "metadata",
            "--format-version",
            "1",
            "--no-deps",
            "--offline",
        ])
        .current_dir(root)
        .output()
        .expect("running cargo metadata");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let meta: Value = serde_json::from_slice(&out.stdout).unwrap();
    let mut packages = BTreeMap::new();
    for p in meta["packages"].as_array().unwrap() {
        let mut deps = BTreeMap::new();
        let mut telemetry_features = Vec::new();
        for d in p["dependencies"].as_array().unwrap() {
            if !d["kind"].is_null() {
                continue;
            }
            let name = d["name"].as_str().unwrap().to_string();
            if name == "telemetry" {
                telemetry_features = d["features"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .map(|f| f.as_str().unwrap().to_string())
                    .collect();
            }
            deps.insert(name, d["path"].is_string());
        }
        packages.insert(
            p["name"].as_str().unwrap().to_string(),
            Package {
                manifest: PathBuf::from(p["manifest_path"].as_str().unwrap()),
                deps,
                telemetry_features,
            },
        );
    }
    packages
}

#[test]
fn workspace_crates_depend_only_downward() {
    let ws = workspace();
    let allowed: BTreeMap<&str, &[&str]> = ALLOWED.iter().copied().collect();
    let listed: BTreeSet<&str> = allowed.keys().copied().collect();
    let present: BTreeSet<&str> = ws.keys().map(String::as_str).collect();
    assert_eq!(
        listed, present,
        "every workspace crate has its row in ALLOWED (and ARCHITECTURE.md's crate table)"
    );
    let mut wrong = Vec::new();
    for (name, p) in &ws {
        for (dep, &is_workspace) in &p.deps {
            if is_workspace && !allowed[name.as_str()].contains(&dep.as_str()) {
                wrong.push(format!("{name} → {dep}"));
            }
        }
    }
    assert!(
        wrong.is_empty(),
        "dependencies against the rules: {wrong:?}"
    );
}

#[test]
fn heavy_and_side_effecting_dependencies_stay_in_their_crate() {
    let ws = workspace();
    let mut wrong = Vec::new();
    for (dep, owners) in CONFINED {
        for (name, p) in &ws {
            if p.deps.contains_key(*dep) && !owners.contains(&name.as_str()) {
                wrong.push(format!("{name} names {dep} (only {owners:?} may)"));
            }
        }
    }
    assert!(wrong.is_empty(), "{wrong:?}");
    // The recorder's library reads frames, never the shared memory (its process `nori-record`
    // does, behind its `process` feature): its tests need no iceoryx2 services.
    assert!(
        ws["recorder"].telemetry_features.is_empty(),
        "recorder enables telemetry features {:?}",
        ws["recorder"].telemetry_features
    );
}

#[test]
fn no_robot_crate_reaches_what_runs_off_the_robot() {
    let ws = workspace();
    for robot in ROBOT {
        // Everything reachable through workspace dependencies.
        let mut seen = BTreeSet::new();
        let mut todo = vec![robot.to_string()];
        while let Some(c) = todo.pop() {
            for (dep, &is_workspace) in &ws[&c].deps {
                if is_workspace && seen.insert(dep.clone()) {
                    todo.push(dep.clone());
                }
            }
        }
        let reached: Vec<&String> = seen
            .iter()
            .filter(|c| OFF_ROBOT.contains(&c.as_str()))
            .collect();
        assert!(reached.is_empty(), "{robot} reaches {reached:?}");
    }
}

#[test]
fn every_crate_keeps_the_workspace_lints_and_no_library_opts_out() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).parent().unwrap();
    let top = std::fs::read_to_string(root.join("Cargo.toml")).unwrap();
    for lint in ["unwrap_used = \"warn\"", "expect_used = \"warn\""] {
        assert!(top.contains(lint), "workspace lint {lint} is gone");
    }
    let clippy = std::fs::read_to_string(root.join("clippy.toml")).unwrap();
    assert!(clippy.contains("allow-unwrap-in-tests = true"));
    for (name, p) in workspace() {
        let manifest = std::fs::read_to_string(&p.manifest).unwrap();
        assert!(
            manifest.contains("[lints]\nworkspace = true"),
            "{name} does not inherit the workspace lints"
        );
        // Source outside tests may not allow unwrap/expect: only a test module may (the opt-out
        // sits within a few lines of its `#[cfg(test)]`/`mod tests`).
        let src = p.manifest.parent().unwrap().join("src");
        for file in rust_files(&src) {
            let text = std::fs::read_to_string(&file).unwrap();
            let lines: Vec<&str> = text.lines().collect();
            for (i, line) in lines.iter().enumerate() {
                if !(line.contains("allow(clippy::unwrap_used")
                    || line.contains("allow(clippy::expect_used"))
                {
                    continue;
                }
                let in_test = name == "nori-tests"
                    || lines[i.saturating_sub(3)..i]
                        .iter()
                        .any(|l| l.contains("#[cfg(test)]") || l.contains("mod tests"));
                assert!(
                    in_test,
                    "{}:{}: unwrap/expect allowed outside a test module",
                    file.display(),
                    i + 1
                );
            }
        }
    }
}

fn rust_files(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let Ok(entries) = std::fs::read_dir(dir) else {
        return out;
    };
    for e in entries.flatten() {
        let path = e.path();
        if path.is_dir() {
            out.extend(rust_files(&path));
        } else if path.extension().is_some_and(|x| x == "rs") {
            out.push(path);
        }
    }
    out
}

/// The modules `file` declares (`mod name;`, `pub mod name;`, `pub(crate) mod name;`), in
/// order: declarations of a file of their own, not inline modules.
fn declared_modules(text: &str) -> Vec<String> {
    text.lines()
        .filter_map(|l| {
            let l = l.trim_start();
            let rest = l
                .strip_prefix("pub mod ")
                .or_else(|| l.strip_prefix("pub(crate) mod "))
                .or_else(|| l.strip_prefix("mod "))?;
            rest.strip_suffix(';').map(str::to_string)
        })
        .collect()
}

/// A library's map (its `//!` docs, in `lib.rs` or a module's `mod.rs`) names every module it
/// declares, so a reader who opens it finds each room: a module added without a line in its
/// map fails here.
#[test]
fn every_library_s_map_names_each_of_its_modules() {
    let mut missing = Vec::new();
    for (_, p) in workspace() {
        let src = p.manifest.parent().unwrap().join("src");
        for file in rust_files(&src) {
            let name = file.file_name().unwrap().to_string_lossy().to_string();
            if name != "lib.rs" && name != "mod.rs" {
                continue;
            }
            let text = std::fs::read_to_string(&file).unwrap();
            let map: String = text
                .lines()
                .take_while(|l| l.starts_with("//!") || l.is_empty())
                .collect::<Vec<_>>()
                .join("\n");
            for module in declared_modules(&text) {
                if !map.contains(&format!("`{module}`")) {
                    missing.push(format!("{}: {module}", file.display()));
                }
            }
        }
    }
    assert!(
        missing.is_empty(),
        "modules their library's map does not name:\n{}",
        missing.join("\n")
    );
}

/// Positional numbers are named: no function may take more arguments than clippy's limit on
/// them allows (7), and no file may switch that lint off.
#[test]
fn no_function_opts_out_of_the_argument_limit() {
    let lint = ["clippy::too_many", "arguments"].join("_");
    let mut found = Vec::new();
    for (_, p) in workspace() {
        for file in rust_files(p.manifest.parent().unwrap()) {
            let text = std::fs::read_to_string(&file).unwrap();
            if text.contains(&lint) {
                found.push(file.display().to_string());
            }
        }
    }
    assert!(found.is_empty(), "{lint} allowed in {found:?}");
}

/// A function fits on a screen or two: clippy's limit on a function's lines is 120 in every
/// crate (`clippy.toml`, the workspace's lints), and no function of a crate's `src/` switches
/// it off (a scenario test may, saying why, until it is split into phases).
#[test]
fn no_function_of_the_product_runs_past_120_lines() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).parent().unwrap();
    let top = std::fs::read_to_string(root.join("Cargo.toml")).unwrap();
    assert!(
        top.contains("too_many_lines = \"warn\""),
        "the lint is gone"
    );
    let clippy = std::fs::read_to_string(root.join("clippy.toml")).unwrap();
    assert!(
        clippy.contains("too-many-lines-threshold = 120"),
        "the limit moved: {clippy}"
    );
    let lint = ["clippy::too_many", "lines"].join("_");
    let mut found = Vec::new();
    for (name, p) in workspace() {
        if name == "nori-tests" {
            continue;
        }
        for file in rust_files(&p.manifest.parent().unwrap().join("src")) {
            let text = std::fs::read_to_string(&file).unwrap();
            if text.contains(&lint) {
                found.push(file.display().to_string());
            }
        }
    }
    assert!(found.is_empty(), "{lint} allowed in {found:?}");
}

/// A doc comment says what the name does not: none is one capitalised word and a full stop
/// (`/// Width.` over `width`, `/// Cause.` over `source`), written only to quiet
/// `missing_docs`. Give the unit, what a count counts, the range, why the padding is there;
/// where the name and an error's message already say it all, allow `missing_docs` on the
/// item instead, with the reason. A doc comment is a run of `///` (or `//!`) lines: one
/// wrapped line of a longer comment (`/// Repeatable.`) is prose, not a one-word doc.
#[test]
fn no_doc_comment_is_a_single_word() {
    let mut found = Vec::new();
    for (_, p) in workspace() {
        for file in rust_files(p.manifest.parent().unwrap()) {
            let text = std::fs::read_to_string(&file).unwrap();
            let lines: Vec<&str> = text.lines().collect();
            let mut i = 0;
            while i < lines.len() {
                let Some(marker) = doc_marker(lines[i]) else {
                    i += 1;
                    continue;
                };
                let first = i;
                let mut words = Vec::new();
                while i < lines.len() && doc_marker(lines[i]) == Some(marker) {
                    words.push(lines[i].trim_start()[marker.len()..].trim());
                    i += 1;
                }
                if is_one_capitalised_word(words.join(" ").trim()) {
                    found.push(format!("{}:{}", file.display(), first + 1));
                }
            }
        }
    }
    assert!(
        found.is_empty(),
        "one-word doc comments (say what the name does not, or allow missing_docs on the item \
         with the reason):\n{}",
        found.join("\n")
    );
}

/// The doc comment marker a line starts with (`///` or `//!`; `////` is a plain comment).
fn doc_marker(line: &str) -> Option<&'static str> {
    let line = line.trim_start();
    if line.starts_with("////") {
        None
    } else if line.starts_with("///") {
        Some("///")
    } else if line.starts_with("//!") {
        Some("//!")
    } else {
        None
    }
}

/// Whether `text` is one capitalised word and a full stop: `Width.`, `Padding.`.
fn is_one_capitalised_word(text: &str) -> bool {
    let Some(word) = text.strip_suffix('.') else {
        return false;
    };
    let mut chars = word.chars();
    chars.next().is_some_and(|c| c.is_ascii_uppercase())
        && !chars.as_str().is_empty()
        && chars.all(|c| c.is_ascii_lowercase())
}
