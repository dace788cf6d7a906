//! A file replaced atomically and durably: written to a temporary file beside it, flushed to
//! the disk, renamed over it, and the directory flushed, so a crash or power cut leaves the old
//! file or the new one, whole, never half of one and never none.

use std::io::Write;
use std::path::{Path, PathBuf};

/// What was being done when the file system refused.
pub type Step = &'static str;

/// The temporary file `path` is written to before it is renamed over it.
pub fn temp_path(path: &Path) -> PathBuf {
    let mut name = path.file_name().unwrap_or_default().to_os_string();
    name.push(".tmp");
    path.with_file_name(name)
}

/// Replaces the file at `path` with `bytes`; on failure, the step that failed and why.
pub fn replace(path: &Path, bytes: &[u8]) -> Result<(), (Step, std::io::Error)> {
    let tmp = temp_path(path);
    let mut f = std::fs::File::create(&tmp).map_err(|e| ("creating the temporary file", e))?;
    f.write_all(bytes).map_err(|e| ("writing", e))?;
    f.sync_all().map_err(|e| ("syncing", e))?;
    std::fs::rename(&tmp, path).map_err(|e| ("renaming into place", e))?;
    // The rename is durable only once the directory entry is: without this, a power loss can
    // bring back the old file (or none) although the new one was announced.
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    std::fs::File::open(dir)
        .and_then(|d| d.sync_all())
        .map_err(|e| ("syncing the directory", e))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn the_file_is_replaced_whole_and_no_temporary_is_left() {
        let dir = std::env::temp_dir().join(format!("nori-durable-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("record.toml");
        replace(&path, b"first").unwrap();
        replace(&path, b"second").unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), b"second");
        assert!(!temp_path(&path).exists());
        let (step, _) = replace(&dir.join("no/such/file"), b"x").unwrap_err();
        assert_eq!(step, "creating the temporary file");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
