//! Durable file replacement: write a temporary beside the target, fsync it, rename it over the
//! target, fsync the directory. A crash leaves the old file or the new one, never a mix; the
//! temporary's name ends in `.tmp`, which LeRobot's `*/*.parquet` glob never matches.

use crate::error::RecordError;
use std::fs::{File, OpenOptions};
use std::io::Write;
use std::path::{Path, PathBuf};

/// The temporary name used for `path`.
pub fn temp_path(path: &Path) -> PathBuf {
    let mut name = path
        .file_name()
        .map(|n| n.to_os_string())
        .unwrap_or_default();
    name.push(".tmp");
    path.with_file_name(name)
}

/// Makes the directory (and parents) and syncs the parent so the new entry is durable.
pub fn create_dir(dir: &Path) -> Result<(), RecordError> {
    if dir.is_dir() {
        return Ok(());
    }
    std::fs::create_dir_all(dir).map_err(RecordError::io(dir, "creating the directory"))?;
    if let Some(parent) = dir.parent() {
        sync_dir(parent)?;
    }
    Ok(())
}

/// fsync of a directory (its entries: created, renamed, removed files).
pub fn sync_dir(dir: &Path) -> Result<(), RecordError> {
    File::open(dir)
        .and_then(|d| d.sync_all())
        .map_err(RecordError::io(dir, "syncing the directory"))
}

/// Replaces `path` with what `write` produces, durably and atomically.
pub fn replace_with<F>(path: &Path, write: F) -> Result<(), RecordError>
where
    F: FnOnce(&mut File) -> Result<(), RecordError>,
{
    let dir = path.parent().ok_or_else(|| {
        RecordError::Request(format!("{} has no parent directory", path.display()))
    })?;
    create_dir(dir)?;
    let tmp = temp_path(path);
    let mut file = OpenOptions::new()
        .write(true)
        .create(true)
        .truncate(true)
        .open(&tmp)
        .map_err(RecordError::io(&tmp, "creating"))?;
    write(&mut file)?;
    drop(file);
    rename_into_place(&tmp, path)
}

/// Makes the finished temporary `tmp` (written by another program, e.g. FFmpeg) the file at
/// `path`, durably: fsync of the temporary, rename, fsync of the directory.
pub fn rename_into_place(tmp: &Path, path: &Path) -> Result<(), RecordError> {
    File::open(tmp)
        .and_then(|f| f.sync_all())
        .map_err(RecordError::io(tmp, "syncing"))?;
    std::fs::rename(tmp, path)
        .map_err(RecordError::io(path, "renaming the new version into place"))?;
    match path.parent() {
        Some(dir) => sync_dir(dir),
        None => Ok(()),
    }
}

/// Replaces `path` with `bytes`, durably and atomically.
pub fn replace(path: &Path, bytes: &[u8]) -> Result<(), RecordError> {
    replace_with(path, |f| {
        f.write_all(bytes).map_err(RecordError::io(path, "writing"))
    })
}

/// Removes leftover temporaries (`*.tmp`) under `dir`, recursively; returns how many.
pub fn remove_temporaries(dir: &Path) -> Result<usize, RecordError> {
    let mut removed = 0;
    let Ok(entries) = std::fs::read_dir(dir) else {
        return Ok(0);
    };
    for e in entries.flatten() {
        let p = e.path();
        if p.is_dir() {
            removed += remove_temporaries(&p)?;
        } else if p.extension().is_some_and(|x| x == "tmp") {
            std::fs::remove_file(&p)
                .map_err(RecordError::io(&p, "removing a leftover temporary"))?;
            removed += 1;
        }
    }
    Ok(removed)
}
