//! Shared memory a process was killed while creating.
//!
//! iceoryx2 creates a segment write-only, sizes it, fills it and only then makes it
//! readable; a process that opens it meanwhile waits for that. iceoryx2 0.10 waits with a
//! timeout for a segment that is sized but not readable yet, but **forever** for one of
//! size zero (`posix_shared_memory.rs`, `MappingSizeIsZero`). A process killed between
//! creating a segment and sizing it (a stage SIGKILLed at start, a crash) leaves such a
//! segment, and every later node creation (which cleans up the dead process's services)
//! spins on it: each pipeline started after that hangs before it logs anything.
//!
//! Creation takes microseconds, so a segment still not readable after [`GRACE`] was left
//! by a dead process and is removed: nobody can ever open it.

use std::os::unix::fs::{MetadataExt, PermissionsExt};
use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime};

/// Where POSIX shared memory lives on Linux.
pub const SHARED_MEMORY_DIR: &str = "/dev/shm";

/// How long a segment may stay unreadable before it counts as abandoned: thousands of
/// times what creating the largest one takes, short enough that a start-up waits for it.
pub const GRACE: Duration = Duration::from_secs(5);

/// How often a young unfinished segment is looked at again.
const POLL: Duration = Duration::from_millis(10);

/// Removes the segments in `dir` whose names start with `prefix` and that are not readable
/// by their owner (not finished) and have not changed for `grace`. A younger unfinished
/// segment is waited for, at most `grace` past its last change: it is either finished by
/// its creator or removed. Returns the paths removed. A directory that cannot be read
/// (none on this system) removes nothing.
pub fn remove_unfinished_segments(dir: &Path, prefix: &str, grace: Duration) -> Vec<PathBuf> {
    let mut removed = Vec::new();
    // Each young segment either finishes or ages past `grace`; a busy machine creating new
    // ones all the time must not keep this waiting, hence the overall bound.
    let give_up = SystemTime::now() + grace * 2;
    loop {
        let now = SystemTime::now();
        let mut waiting = false;
        let Ok(entries) = std::fs::read_dir(dir) else { return removed };
        for entry in entries.flatten() {
            if !entry.file_name().to_str().is_some_and(|name| name.starts_with(prefix)) {
                continue;
            }
            let Ok(meta) = entry.metadata() else { continue };
            if !meta.is_file() || meta.permissions().mode() & 0o400 != 0 {
                continue;
            }
            if age(&meta, now) >= grace {
                match std::fs::remove_file(entry.path()) {
                    Ok(()) => removed.push(entry.path()),
                    // Another process swept it first.
                    Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
                    // Not ours to remove: nothing to be done here, and opening it fails
                    // or waits in iceoryx2 as it would have.
                    Err(_) => {}
                }
            } else {
                waiting = true;
            }
        }
        if !waiting || now >= give_up {
            return removed;
        }
        std::thread::sleep(POLL);
    }
}

/// Time since the segment last changed: created, sized or written (modification), or its
/// mode changed (status change).
fn age(meta: &std::fs::Metadata, now: SystemTime) -> Duration {
    let changed = SystemTime::UNIX_EPOCH
        + Duration::new(meta.ctime().max(0) as u64, meta.ctime_nsec().clamp(0, 999_999_999) as u32);
    let last = meta.modified().map_or(changed, |modified| modified.max(changed));
    now.duration_since(last).unwrap_or(Duration::ZERO)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::fs::{File, Permissions};
    use std::time::Instant;

    fn segment(dir: &Path, name: &str, mode: u32, bytes: usize) -> PathBuf {
        let path = dir.join(name);
        std::fs::write(&path, vec![0u8; bytes]).unwrap();
        std::fs::set_permissions(&path, Permissions::from_mode(mode)).unwrap();
        path
    }

    #[test]
    fn only_unfinished_segments_of_the_prefix_that_stopped_changing_are_removed() {
        let dir = tempfile::tempdir().unwrap();
        let empty = segment(dir.path(), "hf0_a.dynamic", 0o200, 0);
        let half = segment(dir.path(), "hf0_b.event_mgmt", 0o200, 2103);
        let finished = segment(dir.path(), "hf0_c.dynamic", 0o600, 64);
        let foreign = segment(dir.path(), "iox2_d.dynamic", 0o200, 0);
        let removed = remove_unfinished_segments(dir.path(), "hf0_", Duration::ZERO);
        assert_eq!(removed.len(), 2, "{removed:?}");
        assert!(!empty.exists() && !half.exists());
        assert!(finished.exists(), "a finished segment is in use");
        assert!(foreign.exists(), "another prefix is another user's or program's");
    }

    #[test]
    fn a_segment_being_created_is_waited_for_and_kept_once_finished() {
        let dir = tempfile::tempdir().unwrap();
        let creating = segment(dir.path(), "hf0_e.dynamic", 0o200, 0);
        let path = creating.clone();
        let creator = std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(150));
            File::options().write(true).open(&path).unwrap().set_len(4096).unwrap();
            std::fs::set_permissions(&path, Permissions::from_mode(0o600)).unwrap();
        });
        let started = Instant::now();
        let removed = remove_unfinished_segments(dir.path(), "hf0_", Duration::from_secs(3));
        creator.join().unwrap();
        assert!(removed.is_empty() && creating.exists());
        let waited = started.elapsed();
        assert!(waited >= Duration::from_millis(150) && waited < Duration::from_secs(3), "{waited:?}");
    }

    #[test]
    fn a_segment_nobody_finishes_is_removed_once_the_grace_has_passed() {
        let dir = tempfile::tempdir().unwrap();
        let abandoned = segment(dir.path(), "hf0_f.dynamic", 0o200, 0);
        let started = Instant::now();
        let removed = remove_unfinished_segments(dir.path(), "hf0_", Duration::from_millis(300));
        assert_eq!(removed, vec![abandoned.clone()]);
        assert!(!abandoned.exists());
        assert!(started.elapsed() >= Duration::from_millis(250), "{:?}", started.elapsed());
    }
}
