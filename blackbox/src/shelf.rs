//! The boxes on disk. Each is named `NNNNNN-TIME-KIND.mcap`: `NNNNNN` counts up across restarts,
//! so their order never depends on the wall clock (a robot without a real-time clock may boot
//! with its clock set back). Beyond the cap the oldest files go, whatever state they are in
//! (whole, cut short, damaged), except the box being written.

use crate::frozen::PARTIAL_SUFFIX;
use std::path::{Path, PathBuf};

/// The directory of boxes.
#[derive(Debug)]
pub struct Shelf {
    dir: PathBuf,
    next: u64,
}

/// The number a file of the shelf begins with (six digits or more, then `-`); `None` for a
/// file that is not a box (an operator's export, say), which the shelf neither counts nor
/// removes.
fn number(path: &Path) -> Option<u64> {
    let name = path.file_name()?.to_str()?;
    let (n, _) = name.split_once('-')?;
    if n.len() < 6 {
        return None;
    }
    n.parse().ok()
}

impl Shelf {
    /// The shelf in `dir` (created), numbering on from the highest number there.
    pub fn open(dir: &Path) -> std::io::Result<Shelf> {
        std::fs::create_dir_all(dir)?;
        let mut shelf = Shelf {
            dir: dir.into(),
            next: 0,
        };
        shelf.next = shelf
            .files()
            .iter()
            .map(|(n, _, _)| n.saturating_add(1))
            .max()
            .unwrap_or(1);
        Ok(shelf)
    }

    /// Its directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The name of a new box being written, frozen by `kind` at wall time `stamp`.
    pub fn new_partial(&mut self, stamp: &str, kind: &str) -> PathBuf {
        let n = self.next;
        self.next += 1;
        self.dir
            .join(format!("{n:06}-{stamp}-{kind}{PARTIAL_SUFFIX}"))
    }

    /// Every file of the shelf: its number, path and size, oldest first.
    pub fn files(&self) -> Vec<(u64, PathBuf, u64)> {
        files_in(&self.dir)
    }

    /// The whole boxes, oldest first.
    pub fn boxes(&self) -> Vec<PathBuf> {
        whole_boxes(&self.dir).into_iter().map(|f| f.1).collect()
    }

    /// The boxes a crash cut short, oldest first.
    pub fn partials(&self) -> Vec<PathBuf> {
        self.files()
            .into_iter()
            .map(|(_, p, _)| p)
            .filter(|p| p.to_string_lossy().ends_with(PARTIAL_SUFFIX))
            .collect()
    }

    /// Removes the oldest files until the shelf holds at most `cap` bytes, never `keep` (the
    /// box being written); the files removed, and the errors of those that could not be.
    pub fn trim(&self, cap: u64, keep: Option<&Path>) -> (Vec<PathBuf>, Vec<std::io::Error>) {
        let files = self.files();
        let mut total: u64 = files.iter().map(|(_, _, size)| size).sum();
        let (mut removed, mut errors) = (Vec::new(), Vec::new());
        for (_, p, size) in files {
            if total <= cap {
                break;
            }
            if Some(p.as_path()) == keep {
                continue;
            }
            match std::fs::remove_file(&p) {
                Ok(()) => {
                    total -= size;
                    removed.push(p);
                }
                Err(e) => errors.push(e),
            }
        }
        (removed, errors)
    }
}

/// Every box file in `dir`: its number, path and size, oldest first (none if `dir` cannot be
/// read).
fn files_in(dir: &Path) -> Vec<(u64, PathBuf, u64)> {
    let mut out: Vec<(u64, PathBuf, u64)> = std::fs::read_dir(dir)
        .into_iter()
        .flatten()
        .flatten()
        .filter(|e| e.file_type().is_ok_and(|t| t.is_file()))
        .filter_map(|e| {
            let p = e.path();
            let size = e.metadata().map_or(0, |m| m.len());
            Some((number(&p)?, p, size))
        })
        .collect();
    out.sort();
    out
}

/// The finished boxes in `dir` (not those being written, cut short or damaged): number, path
/// and size, oldest first. A reader's view that changes nothing: the fleet agent sends them.
pub fn whole_boxes(dir: &Path) -> Vec<(u64, PathBuf, u64)> {
    files_in(dir)
        .into_iter()
        .filter(|(_, p, _)| p.extension().is_some_and(|x| x == "mcap"))
        .collect()
}

/// The name a finished box takes.
pub fn whole_name(partial: &Path) -> PathBuf {
    let s = partial.to_string_lossy();
    PathBuf::from(format!("{}.mcap", s.trim_end_matches(PARTIAL_SUFFIX)))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scratch(tag: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("nori-shelf-{tag}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        d
    }

    #[test]
    fn numbers_go_on_across_restarts_and_order_the_boxes_whatever_the_clock() {
        let dir = scratch("numbers");
        let mut shelf = Shelf::open(&dir).unwrap();
        let a = shelf.new_partial("20261129T120000Z", "thermal_trip");
        std::fs::write(whole_name(&a), b"a").unwrap();
        // The clock set back by a boot without a real-time clock: the name's time is older.
        let mut again = Shelf::open(&dir).unwrap();
        let b = again.new_partial("19700101T000010Z", "saved");
        std::fs::write(&b, b"b").unwrap();
        assert!(b
            .file_name()
            .unwrap()
            .to_string_lossy()
            .starts_with("000002-"));
        let files: Vec<PathBuf> = again.files().into_iter().map(|f| f.1).collect();
        assert_eq!(
            files,
            vec![whole_name(&a), b.clone()],
            "by number, not by time"
        );
        assert_eq!(again.boxes(), vec![whole_name(&a)]);
        let whole: Vec<PathBuf> = whole_boxes(&dir).into_iter().map(|f| f.1).collect();
        assert_eq!(whole, vec![whole_name(&a)], "not the one being written");
        assert_eq!(again.partials(), vec![b]);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn the_oldest_files_go_beyond_the_cap_in_any_state_but_the_box_being_written() {
        let dir = scratch("trim");
        let mut shelf = Shelf::open(&dir).unwrap();
        let names: Vec<PathBuf> = ["a.mcap", "b.mcap.damaged", "c.mcap.partial", "d.mcap"]
            .iter()
            .map(|s| {
                let p = shelf.new_partial("T", "k");
                let p = PathBuf::from(p.to_string_lossy().replace("k.mcap.partial", s));
                std::fs::write(&p, [0u8; 100]).unwrap();
                p
            })
            .collect();
        let export = dir.join("an-operators-export.csv");
        std::fs::write(&export, [0u8; 1000]).unwrap();
        let (removed, errors) = shelf.trim(250, Some(&names[0]));
        assert!(export.exists(), "not a box: neither counted nor removed");
        assert!(errors.is_empty());
        assert_eq!(removed, vec![names[1].clone(), names[2].clone()]);
        let left: Vec<PathBuf> = shelf.files().into_iter().map(|f| f.1).collect();
        assert_eq!(left, vec![names[0].clone(), names[3].clone()]);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
